"""plvo: lidar-monocular visual odometry and SLAM with point and line features.

The library imports no viewer: stages hand typed results to `plvo.recording.Recorder` objects, and the
Rerun and viser recorders live in `plvo_app`.
"""

__version__ = "0.1.0"
