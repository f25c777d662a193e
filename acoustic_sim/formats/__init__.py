"""Files in and out of other tools: CHIRP recordings (`chirp`), raw PDM microphone recordings
(`recordings`), ROS 2 messages in MCAP (`mcap_export`), and the test set made by an independent
engine (`crossengine`). They use the engine's public stages and the dataset files, never its
kernels.
"""

PLANE_TOLERANCE_M = 0.05
"""CHIRP import: LiDAR points within this height of the sonar's plane make the 2D scan [m]."""
EPISODE_GAP_S = 0.5
"""CHIRP import: a longer pause between pings starts a new episode [s]."""
