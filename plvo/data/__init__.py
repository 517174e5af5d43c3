"""Datasets: KITTI odometry and raw, bags, plain folders, the synthetic town (plvo.data.registry opens them)."""

ROOT_ENV = "KITTI_ROOT"  # the dataset root when no --root is given (here, light, for the commands' help)
