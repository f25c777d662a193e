"""LiDAR simulation: batched ray casting of many poses in one Warp launch, plus scan helpers."""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene

from ..config import NOISE_CODES, LidarConfig, PolarGrid
from ..devices import cpu_cores, warp_device
from .kernels import lidar as kernels
from .poses import check_pose_results, check_poses
from .scene import warp_scene

# A Lidar's k-th call draws its noise from seed (Lidar seed * SEED_STRIDE + k) mod SEED_MODULUS:
# a prime stride keeps the sequences of nearby Lidar seeds apart; the modulus keeps seeds in int32.
SEED_STRIDE = 1_000_003
SEED_MODULUS = 2**31 - 1


# Threads per block of the scan kernels: blocks of 64 cast 1.07-1.10x the rays/s of Warp's 256 on
# the office (an H200, 2D and 3D scans; 512 cast 0.7x): a warp's rays finish their BVH walks at
# different times, and small blocks let the SM start the next block sooner.
SCAN_BLOCK_DIM = 64
# A scan of fewer rays casts through the scene's own tree (the sonar's, of BVH_LEAF_SIZE leaves)
# rather than building the LiDAR's tree of one-triangle leaves (scene.LIDAR_BVH_LEAF_SIZE). That tree
# casts 1.1-1.3x the rays/s, but it is built on the host: a dataset episode (100 poses of 1,081
# beams, ~0.03 ms of an H100's time) spent ~10 % of its rendering process's CPU building it
# (py-spy over `generate` on an H100, benchmarks/results/multi_gpu/session37).
OWN_TREE_RAYS = 10_000_000


@dataclass
class LidarScan:
    """Device-resident result of `Lidar.cast`, valid until the next call (buffers are reused).

    Attributes:
        range_m: Range per (pose, beam) [m], float32 (pose_count, beam_count); inf = no return.
        face: Index of the face hit, int32 (pose_count, beam_count); -1 = no return.
    """

    range_m: wp.array
    face: wp.array


class Lidar:
    """Scanning LiDAR: casts every beam of many poses in one kernel launch on a Warp device.

    Args:
        config: Beam pattern, limits and noise.
        device: Warp device ("cpu", "cuda:0", ...); None for Warp's default.
        seed: Seeds the measurement noise. Each call draws fresh noise, in a sequence that
            is the same for the same seed; pass `seed=` to a call to pin its noise.
    """

    def __init__(self, config: LidarConfig, *, device=None, seed: int = 0, cpu_threads: int | None = None):
        self.config = config
        self.device = warp_device(device)
        # Warp runs a CPU launch on one core; launches on disjoint slices of the poses from several
        # threads run side by side (Warp releases the GIL while a CPU kernel runs).
        if cpu_threads is not None and cpu_threads < 1:
            raise ValueError(f"cpu_threads must be >= 1, got {cpu_threads}")
        self.cpu_threads = cpu_threads or cpu_cores()
        self.seed = int(seed)
        self._calls = 0
        self._beam_dirs = wp.array(config.beam_directions().astype(np.float32), dtype=wp.vec3, device=self.device)
        self._buffers: dict[int, tuple[wp.array, ...]] = {}
        self._copies: tuple[wp.array, ...] | None = None  # page-locked results of `scan_begin`
        self._pending = None  # the event after the last scan_begin's copies, until waited for
        self._scans = 0  # scans queued so far: a PendingScan knows whether its buffers are still its own

    @property
    def beam_count(self) -> int:
        return self.config.beam_count

    def _buffers_for(self, pose_count: int) -> tuple[wp.array, ...]:
        """(host staging poses, device poses, pose errors, poses behind a surface, ranges, faces),
        reused across calls."""
        if pose_count not in self._buffers:
            self._buffers.clear()  # keep one size: a stream of equal batches reuses memory
            # Pinned staging makes the pose upload ~5x faster than from pageable numpy memory.
            pinned = self.device.is_cuda
            self._buffers[pose_count] = (
                wp.empty(pose_count, dtype=wp.mat44, device="cpu", pinned=pinned),
                wp.empty(pose_count, dtype=wp.mat44, device=self.device),
                wp.empty(pose_count, dtype=float, device=self.device),
                wp.empty(pose_count, dtype=wp.int32, device=self.device),
                wp.empty(pose_count * self.beam_count, dtype=float, device=self.device),
                wp.empty(pose_count * self.beam_count, dtype=wp.int32, device=self.device),
            )
        return self._buffers[pose_count]

    def cast(self, scene: Scene, poses: np.ndarray, *, seed: int | None = None) -> LidarScan:
        """Cast all beams from every pose; results stay on the device.

        Args:
            scene: The world.
            poses: Sensor-to-world transforms, shape (N, 4, 4) or (4, 4).
            seed: Noise seed for this call; default: the next in the Lidar's sequence.

        Raises:
            ValueError: for a pose that is not a finite rigid transform.
        """
        poses = check_poses(poses)
        _, _, error_buf, behind_buf, range_out, face_out = self._queue(scene, poses, seed)
        check_pose_results(error_buf.numpy(), behind_buf.numpy())  # waits for the launches
        shape = (len(poses), self.beam_count)
        return LidarScan(range_m=range_out.reshape(shape), face=face_out.reshape(shape))

    def scan(self, scene: Scene, poses: np.ndarray, *, seed: int | None = None) -> np.ndarray:
        """Ranges [m] of every beam from every pose, float32 (N, beam_count); inf = no return."""
        return self.scan_begin(scene, poses, seed=seed).ranges()

    def scan_begin(self, scene: Scene, poses: np.ndarray, *, seed: int | None = None) -> PendingScan:
        """Queue a scan (as `scan`) and the copy of its results to the host; `.ranges()` of what
        this returns waits for them. Work queued on the device in between (a sonar's frames) runs
        behind the scan, so the host waits for the device once instead of twice: on a GPU shared
        by several processes each wait is a turn in its time slices. One scan of a Lidar is
        pending at a time: the next call waits for it, and the ranges of a scan whose buffers a
        later call took are refused."""
        poses = check_poses(poses)
        _, _, error_buf, behind_buf, range_out, _ = self._queue(scene, poses, seed)
        results = (error_buf, behind_buf, range_out)
        if self.device.is_cuda:  # copies behind the scan into page-locked memory: no wait here
            copies = self._host_copies(len(poses))
            for host, device in zip(copies, results, strict=True):
                wp.copy(host, device)
            results, self._pending = copies, wp.get_stream(self.device).record_event()
        return PendingScan(self, self._scans, results, (len(poses), self.beam_count))

    def _finish_pending(self) -> None:
        if self._pending is not None:
            wp.synchronize_event(self._pending)
            self._pending = None

    def _host_copies(self, pose_count: int) -> tuple[wp.array, ...]:
        """Page-locked (pose errors, poses behind, ranges) for `scan_begin`, reused across calls."""
        if self._copies is None or len(self._copies[0]) != pose_count:
            self._copies = (
                wp.empty(pose_count, dtype=float, device="cpu", pinned=True),
                wp.empty(pose_count, dtype=wp.int32, device="cpu", pinned=True),
                wp.empty(pose_count * self.beam_count, dtype=float, device="cpu", pinned=True),
            )
        return self._copies

    def _queue(self, scene: Scene, poses: np.ndarray, seed: int | None) -> tuple[wp.array, ...]:
        """Queue the pose checks, the scan and its noise for checked `poses`; their buffers."""
        self._finish_pending()  # the staging buffer below may still feed a pending scan's upload
        self._scans += 1  # a pending scan's buffers are this call's now
        if seed is None:
            seed = (self.seed * SEED_STRIDE + self._calls) % SEED_MODULUS
            self._calls += 1
        ws = warp_scene(scene, self.device)
        staging, pose_buf, error_buf, behind_buf, range_out, face_out = self._buffers_for(len(poses))
        np.copyto(staging.numpy(), poses, casting="same_kind")
        wp.copy(pose_buf, staging)
        cfg = self.config
        launch = functools.partial(wp.launch, device=self.device)
        # Poses are checked on the device, in the same stream as the scan: one tiny launch and a
        # 4-byte-per-pose read-back cost far less than numpy on large batches.
        launch(kernels.pose_error, dim=len(poses), inputs=[ws.mesh.id, pose_buf], outputs=[error_buf, behind_buf])
        beams = self.beam_count
        own_tree = ws.has_lidar_mesh or len(poses) * beams >= OWN_TREE_RAYS
        beam_tree = ws.lidar_mesh.id if own_tree else ws.mesh.id  # built here, not by the threads below
        kernel, scene_in = kernels.lidar_scan_opaque, [beam_tree]
        if ws.lidar_sees_through:
            kernel, scene_in = kernels.lidar_scan, [beam_tree, ws.face_lidar_transparent]

        def scan_poses(first: int, last: int) -> None:
            rays = slice(first * beams, last * beams)
            beams_in = [pose_buf[first:last], self._beam_dirs, cfg.range_min_m, cfg.range_max_m]
            launch(
                kernel,
                dim=(last - first) * beams,
                inputs=[*scene_in, *beams_in],
                outputs=[range_out[rays], face_out[rays]],
                block_dim=SCAN_BLOCK_DIM,
            )

        threads = min(self.cpu_threads, len(poses)) if self.device.is_cpu else 1
        if threads == 1:
            scan_poses(0, len(poses))
        else:
            edges = np.linspace(0, len(poses), threads + 1).round().astype(int)
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(scan_poses, edges[:-1], edges[1:]))  # list(): raise a thread's error here
        if cfg.noise != "none" or cfg.dropout_probability > 0:
            launch(
                kernels.lidar_noise,
                dim=len(range_out),
                inputs=[cfg.range_min_m, NOISE_CODES[cfg.noise], cfg.noise_m, cfg.dropout_probability, int(seed)],
                outputs=[range_out, face_out],
            )
        return staging, pose_buf, error_buf, behind_buf, range_out, face_out


@dataclass
class PendingScan:
    """A scan queued by `Lidar.scan_begin`; `ranges()` waits for it."""

    lidar: Lidar
    number: int
    results: tuple  # (pose errors, poses behind, ranges): host arrays once the copies land
    shape: tuple[int, int]

    def ranges(self) -> np.ndarray:
        """Ranges [m] of every beam from every pose, float32 (N, beam_count); inf = no return.
        Raises ValueError for a pose that is not a finite rigid transform, as `Lidar.scan`."""
        if self.number != self.lidar._scans:
            raise RuntimeError("a later scan of this Lidar reused this scan's buffers: read ranges() before the next")
        self.lidar._finish_pending()
        error, behind, ranges = (r.numpy() for r in self.results)
        check_pose_results(error, behind)
        # Copied: the buffers are reused by the next scan (on the CPU .numpy() is a view of them).
        return np.array(ranges.reshape(self.shape), copy=True)


def ranges_to_points(ranges: np.ndarray, config: LidarConfig, poses: np.ndarray | None = None) -> np.ndarray:
    """Beam end points [m], shape (N, beam_count, 3); NaN where there was no return.

    In the sensor frame, or in the world frame when `poses` (N, 4, 4) are given.
    """
    ranges = np.atleast_2d(np.asarray(ranges, dtype=np.float64))
    if ranges.shape[-1] != config.beam_count:
        raise ValueError(f"ranges have {ranges.shape[-1]} beams, the config {config.beam_count}")
    r = np.where(np.isfinite(ranges), ranges, np.nan)
    points = r[..., None] * config.beam_directions()
    if poses is not None:
        poses = check_poses(poses)
        if len(poses) != len(points):
            raise ValueError(f"{len(poses)} poses for {len(points)} scans")
        points = points @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
    return points


def lidar_image(ranges: np.ndarray, config: LidarConfig, grid: PolarGrid | None = None, dtype=np.float32) -> np.ndarray:
    """Rasterise scans onto the range x azimuth grid of the energyscapes.

    A cell is 1 where a beam of the scan ends in it, else 0. Beams are assigned to the nearest
    azimuth bin; for 3D LiDARs only the ring closest to elevation 0 is used.

    Args:
        ranges: (N, beam_count) or (beam_count,) [m], inf = no return.
        config: The LiDAR's configuration.
        grid: Target grid; default `PolarGrid()` (0.2-5 m in 2 cm x -90..90 deg in 1 deg).
        dtype: Of the image (datasets store uint8: a quarter of float32's bytes to fill and move).

    Returns:
        (N, range_count, azimuth_count) of `dtype`.
    """
    grid = grid or PolarGrid()
    ranges = np.atleast_2d(np.asarray(ranges, dtype=np.float64))
    if ranges.shape[-1] != config.beam_count:
        raise ValueError(f"ranges have {ranges.shape[-1]} beams, the config {config.beam_count}")
    ring = int(np.argmin(np.abs(config.elevation_rad)))
    ranges = ranges.reshape(len(ranges), config.elevation_count, config.azimuth_count)[:, ring]
    az_bin = np.rint((np.rad2deg(config.azimuth_rad) - grid.azimuth_min_deg) / grid.azimuth_step_deg)
    az_bin = az_bin.astype(np.int64)
    with np.errstate(invalid="ignore"):
        r_bin = np.floor((ranges - grid.range_min_m) / grid.range_bin_m)
    valid = np.isfinite(r_bin) & (r_bin >= 0) & (r_bin < grid.range_count)
    valid &= ((az_bin >= 0) & (az_bin < grid.azimuth_count))[None, :]
    frame, beam = np.nonzero(valid)
    image = np.zeros((len(ranges), *grid.shape), dtype=dtype)
    image[frame, r_bin[frame, beam].astype(np.int64), az_bin[beam]] = 1
    return image
