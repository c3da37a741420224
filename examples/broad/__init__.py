"""BROAD: real IMU recordings with optical ground truth, read into the project's dataset type.

The Berlin Robust Orientation Estimation Assessment Dataset (Laidig, Caruso, Cereatti, Seel,
Data 6(7):72, 2021, https://doi.org/10.3390/data6070072; data CC-BY-4.0,
https://github.com/dlaidig/broad). Modules:

* :mod:`.matfile`    read a ``.mat`` file's header first and only the fields asked for, bounded;
* :mod:`.data`       read and check a trial's ``.mat`` file, make a ``TrajectoryDataset`` of trials;
* :mod:`.metric`     the benchmark's error metric (total / heading / inclination RMSE, degrees);
* :mod:`.simulator`  an attitude simulator with this IMU's sensor models, for pre-training;
* :mod:`.learning`   the learned observer's shape, its measured start, the mounting augmentation;
* :mod:`.train`, :mod:`.evaluate`, :mod:`.apply`  the commands for the learned observer;
* :mod:`.filters`    classical filters: Mahony's complementary filter, the project's EKF;
* :mod:`.reference`  rows from maintained packages (VQF, ahrs) and the authors' published numbers;
* :mod:`.compare`    the comparison table, figures and the command that writes them;
* :mod:`.seeds`, :mod:`.crossval`  configurations over seeds, and over cross-validation folds.
"""
