"""BROAD: real IMU recordings with optical ground truth (Laidig et al., Data 6(7):72, 2021), and
an attitude simulator whose sensor models match its IMU (``simulator``) for pre-training."""
