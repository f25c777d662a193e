"""Checks of sensor poses shared by the LiDAR and the sonar: shape on the host, then rigidity,
finiteness and "behind a surface" from `kernels.lidar.pose_error`, run on the device beside each
scan or trace."""

from __future__ import annotations

import numpy as np

from ..user_warning import warn_user
from .kernels.lidar import POSE_TOLERANCE
from .scene import warn_if_far


def check_poses(poses: np.ndarray) -> np.ndarray:
    """Validate the shape of sensor-to-world poses; returns float64 (N, 4, 4). (4, 4) gives N = 1.

    Rigidity and finiteness are checked where the poses are used (on the device for `Lidar`).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (N, 4, 4) or (4, 4), got {poses.shape}")
    if len(poses) == 0:
        raise ValueError("poses is empty")
    warn_if_far(poses[:, :3, 3], "sensor positions")
    return poses


def check_pose_results(error: np.ndarray, behind: np.ndarray) -> None:
    """Raise ValueError naming the first bad pose, and warn about poses behind a surface, given the
    per-pose outputs of `kernels.pose_error` for every pose of a call."""
    raise_for_bad_poses(error)
    warn_poses_behind(behind > 0)


def raise_for_bad_poses(error: np.ndarray, index: np.ndarray | None = None) -> None:
    """Raise ValueError naming the first pose whose `kernels.pose_error` error is too large (or not
    finite). `index`: the poses' indices in the caller's array, when `error` covers a batch of them."""
    bad = ~(error <= POSE_TOLERANCE)  # NaN counts as bad
    if not bad.any():
        return
    k = int(np.argmax(bad))
    name = k if index is None else int(index[k])
    if not np.isfinite(error[k]):
        raise ValueError(f"pose {name} contains NaN or inf")
    raise ValueError(
        f"pose {name} is not a rigid transform (rotation not orthonormal, a mirror with determinant -1, "
        f"or last row not [0, 0, 0, 1]; error {error[k]:.2g})"
    )


def warn_poses_behind(behind: np.ndarray) -> None:
    """One warning for the poses (bool, every pose of a call) that lie behind a surface, shown at
    the caller's line outside this package (the LiDAR and the sonar reach here at other depths)."""
    if behind.any():
        k = int(np.argmax(behind))
        warn_user(
            f"{int(behind.sum())} of {len(behind)} poses (first: pose {k}) lie behind the surfaces around them "
            "(most axis rays hit the back of a face): inside an object or outside the room, their scans and "
            "echoes do not come from free space"
        )
