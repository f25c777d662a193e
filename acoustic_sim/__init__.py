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
from .engine.beamform import Beamformer, energyscape
from .engine.lidar import Lidar, LidarScan, lidar_image, ranges_to_points
from .engine.paths import Arrivals, PathTracer
from .engine.poses import check_poses
from .engine.scene import WarpScene, warp_scene
from .engine.sonar import Sonar, SonarFrames

try:
    __version__ = version("sonar2lidar")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"

__all__ = [
    "Arrivals",
    "AtmosphereConfig",
    "Beamformer",
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
    "energyscape",
    "lidar_image",
    "ranges_to_points",
    "warp_scene",
]
