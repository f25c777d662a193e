"""Sonar-to-LiDAR learning (PyTorch). Reads dataset shards only; never imports warp.

The learner (data windows, the paper's network, training and evaluation) is not implemented yet.
"""
