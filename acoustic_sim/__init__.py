"""Physically based in-air sonar and LiDAR simulation on NVIDIA Warp (CPU and CUDA)."""

import importlib

_PUBLIC = {
    "AtmosphereConfig": "config",
    "ChirpConfig": "config",
    "ConfigError": "config",
    "LidarConfig": "config",
    "PolarGrid": "config",
    "ProcessingConfig": "config",
    "SimConfig": "config",
    "SonarConfig": "config",
    "TracerConfig": "config",
    "Beamformer": "engine.beamform",
    "energyscape": "engine.beamform",
    "Lidar": "engine.lidar",
    "LidarScan": "engine.lidar",
    "lidar_image": "engine.lidar",
    "ranges_to_points": "engine.lidar",
    "Arrivals": "engine.paths",
    "PathTracer": "engine.paths",
    "check_poses": "engine.poses",
    "WarpScene": "engine.scene",
    "warp_scene": "engine.scene",
    "Sonar": "engine.sonar",
    "SonarFrames": "engine.sonar",
}
"""Each public name and the module it lives in, imported on first use (PEP 562): `python -m
acoustic_sim` then starts without Warp and SciPy, which its commands import inside the part
that turns Ctrl-C into one line (a Ctrl-C while they loaded printed a trace)."""


def __getattr__(name: str):
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("sonar2lidar")
        except PackageNotFoundError:  # running from a source tree that was not installed
            value = "0+unknown"
    elif name in _PUBLIC:
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_PUBLIC, "__version__"})


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
