"""Files in and out of other tools: CHIRP recordings (`chirp`), raw PDM microphone recordings
(`recordings`), ROS 2 messages in MCAP (`mcap_export`), and the test set made by an independent
engine (`crossengine`). They use the engine's public stages and the dataset files, never its
kernels.
"""
