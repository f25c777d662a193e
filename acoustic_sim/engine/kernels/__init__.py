"""Warp kernels and functions only: no numpy, no I/O. The Python API around them is one level up."""
