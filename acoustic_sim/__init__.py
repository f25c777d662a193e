"""Physically based in-air sonar and LiDAR simulation on NVIDIA Warp (CPU and CUDA)."""

from importlib.metadata import PackageNotFoundError, version

from .config import (
    AtmosphereConfig,
    ChirpConfig,
    ConfigError,
    LidarConfig,
    PolarGrid,
    ProcessingConfig,
    SimConfig,
    SonarConfig,
    TracerConfig,
)
from .lidar import Lidar, LidarScan, lidar_image, ranges_to_points
from .paths import Arrivals, PathTracer
from .poses import check_poses
from .scene import WarpScene, warp_scene
from .sonar import Sonar, SonarFrames

try:
    __version__ = version("sonar2lidar")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"

__all__ = [
    "Arrivals",
    "AtmosphereConfig",
    "ChirpConfig",
    "ConfigError",
    "Lidar",
    "LidarConfig",
    "LidarScan",
    "PathTracer",
    "PolarGrid",
    "ProcessingConfig",
    "SimConfig",
    "Sonar",
    "SonarConfig",
    "SonarFrames",
    "TracerConfig",
    "WarpScene",
    "check_poses",
    "lidar_image",
    "ranges_to_points",
    "warp_scene",
]
