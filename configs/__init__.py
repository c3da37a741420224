"""The hydra configs of manifold_nets as package data: the commands load pkg://manifold_nets_configs."""
