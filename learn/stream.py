"""Streaming inference: a drive predicted frame by frame, as a robot runs it.

    stream = Stream.from_checkpoint("runs/memory/best.pt", device="cuda")
    for energyscape, pose in drive:  # (R, A) as beamformed; pose (x, y, yaw) or 4 x 4 sensor-to-odom
        result = stream.step(energyscape, pose)
        if result is not None:
            publish(result.frame, result.ranges)  # the scan of frame result.frame, inf = no return
    stream.reset()  # a new drive

`Stream` keeps a ring buffer of the last frames, each normalised once when it arrives (as
`learn.data.normalise` does, per frame), and their poses: as many as the checkpoint's window and
history reach back (`DataConfig.offsets`). Each step reads the window that ends at the newest frame
exactly as `learn.data.Windows` cuts it from a stored drive, history frames from before the drive
began absent as they are there, so a drive streamed gives the images `learn predict` gives it
(tests/test_stream.py holds the two equal). The result is the scan of the window's label frame:
with label "middle" that is K // 2 frames behind the newest one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .data import DataConfig, normalise
from .devices import torch_device
from .models import ModelConfig, trained_elevations
from .odometry import planar, relative
from .scan import first_return_ranges


@dataclass(frozen=True)
class StreamResult:
    """The scan of one frame of a drive.

    Attributes:
        frame: Which frame it is the scan of: 0 is the first frame stepped since the stream began
            or was reset (with label "middle", K // 2 steps before the newest frame).
        ranges: (A,) float32 range of the nearest return per beam [m], inf where there is none,
            read at the stream's threshold.
        image: (R, A) float16 predicted LiDAR image in [0, 1], as `learn predict` saves it (its
            scans are read from these values).
        pose: (3,) float64 planar pose of that frame as given (x, y [m], yaw [rad]), None where
            no pose was given.
    """

    frame: int
    ranges: np.ndarray
    image: np.ndarray
    pose: np.ndarray | None


class Stream:
    """A checkpoint's model run frame by frame with state (see the module docstring).

    Args:
        model: The network, in eval mode (`learn.checkpoint.load_checkpoint`).
        ckpt: Its checkpoint dict: data_config (window, history, label, floor), range_m,
            azimuth_rad, threshold.
        device: Where to run; None: where the model's weights are.
        threshold: Return threshold in (0, 1] overriding the checkpoint's calibrated one.
        amp: bfloat16 autocast on a GPU, as `learn predict` runs.
        graphs: On a GPU, replay each step's network and readout as one CUDA graph.
    """

    def __init__(
        self, model: torch.nn.Module, ckpt: dict, device=None, *, threshold=None, amp: bool = True, graphs: bool = True
    ):
        from .checkpoint import return_threshold
        from .evaluate import model_predictor

        weights = next(iter(model.parameters()), None)
        self.device = torch_device(device) if device is not None else (weights.device if weights is not None else None)
        self.model = model.to(self.device).eval()
        self.config = DataConfig(**ckpt["data_config"])
        self.uses_odometry = ModelConfig(**ckpt["model_config"]).uses_odometry
        self.threshold = return_threshold(ckpt, threshold)
        self.range_m = np.asarray(ckpt["range_m"], dtype=np.float64)
        self.azimuth_rad = np.asarray(ckpt["azimuth_rad"], dtype=np.float64)
        self.grid = (len(self.range_m), len(self.azimuth_rad))
        self.elevation_deg = trained_elevations(ckpt["model_config"].get("elevation_deg"))
        self.shape = (len(self.elevation_deg), *self.grid)  # one frame: (E, R, A)
        self._run = model_predictor(self.model, amp=amp)
        self.graphs, self._graph = graphs, None
        self._range = torch.as_tensor(self.range_m, device=self.device)
        offsets = self.config.offsets
        self.capacity = int(offsets[-1] - offsets[0] + 1)  # frames the oldest read lies behind the newest, and it
        self._offsets = offsets - offsets[-1]  # each frame read, relative to the newest (0 is the newest)
        # One slot more than the ring: it holds the image of an absent frame, which Windows makes
        # as the normalised image of zeros.
        self._frames = torch.zeros(self.capacity + 1, *self.shape, device=self.device)
        self._frames[self.capacity] = normalise(torch.zeros(self.shape, device=self.device), self.config.floor_db)
        self._poses = np.zeros((self.capacity, 3))
        self._posed = np.zeros(self.capacity, bool)  # whether the frame in each slot came with a pose
        self.reset()

    @classmethod
    def from_checkpoint(cls, path, device="cpu", *, threshold=None, amp: bool = True) -> Stream:
        """The stream of a .pt file written by `learn train`, checked as `learn predict` checks it."""
        from .checkpoint import load_checkpoint

        model, ckpt = load_checkpoint(path, device)
        return cls(model, ckpt, device, threshold=threshold, amp=amp)

    @property
    def delay(self) -> int:
        """Frames between the newest frame stepped and the frame its result is the scan of."""
        return self.config.frames - 1 - self.config.label_offset

    def reset(self) -> None:
        """Start a new drive: the frames before it are absent (as at the start of an episode)."""
        self.count = 0  # frames stepped since the drive began
        self._first_pose = None  # the pose Windows gives absent frames: the drive's first

    def step(self, energyscape, pose=None) -> StreamResult | None:
        """Take the next frame of the drive; return the scan of the window's label frame, or None
        while the first window is not complete (the first K - 1 frames of a drive).

        Args:
            energyscape: (R, A) energyscape on the checkpoint's grid, or (E, R, A) at the
                checkpoint's E elevations, as beamformed (any scale: each frame is normalised to
                its own peak), a numpy array or tensor.
            pose: The sensor's odometry pose: (x [m], y [m], yaw [rad]) or a 4 x 4
                sensor-to-odom matrix; None for a model without memory.

        Returns:
            StreamResult of frame `count - 1 - delay`, or None.
        """
        planar_pose = self._check_pose(pose)
        image = self._check_energyscape(energyscape)
        slot = self.count % self.capacity
        self._frames[slot] = normalise(image, self.config.floor_db)
        self._posed[slot] = planar_pose is not None
        if planar_pose is not None:
            self._poses[slot] = planar_pose
            if self._first_pose is None:
                self._first_pose = planar_pose
        self.count += 1
        if self.count < self.config.frames:
            return None
        return self._predict()

    def _predict(self) -> StreamResult:
        newest = self.count - 1
        frame = newest + self._offsets  # each frame the window reads, counted from the drive's start
        present = frame >= 0
        slots = np.where(present, frame % self.capacity, self.capacity)
        x = self._frames[torch.as_tensor(slots, device=self.device)][None].transpose(1, 2)  # (1, E, N, R, A)
        label_frame, anchor = newest - self.delay, self.config.anchor
        ring = slots % self.capacity
        pose = self._poses[ring[anchor]].copy() if self._posed[ring[anchor]] else None
        if self.uses_odometry:  # every frame came with a pose (_check_pose): absent ones get the first, as in Windows
            poses = np.where(present[:, None], self._poses[ring], self._first_pose)
            motion = np.concatenate([relative(poses, pose), present[:, None]], axis=1)
            x = (x, torch.as_tensor(motion[None], dtype=torch.float32, device=self.device))
        with torch.no_grad():
            image, ranges = self._graphed(x) if self.device.type == "cuda" and self.graphs else self._readout(x)
        return StreamResult(label_frame, ranges[0].cpu().numpy(), image[0].cpu().numpy(), pose)

    def _readout(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """The network's image (as predict saves it, float16: its scans read these) and scan."""
        image = self._run(x).float().clamp(0, 1)[:, 0].half()
        return image, first_return_ranges(image.float(), self._range, threshold=self.threshold).float()

    def _graphed(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """`_readout` replayed as one CUDA graph: at batch 1 the small network's ~100 kernel
        launches, not its arithmetic, are what a step waits for. Captured at the first step on
        inputs of fixed shape, which every later step copies its own into."""
        inputs = x if isinstance(x, tuple) else (x,)
        if self._graph is None:
            self._static = [t.clone() for t in inputs]
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):  # warm-up outside the graph: cuDNN picks its kernels
                for _ in range(3):
                    self._readout(self._packed())
            torch.cuda.current_stream(self.device).wait_stream(side)
            self._graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self._graph):
                self._out = self._readout(self._packed())
        for static, given in zip(self._static, inputs, strict=True):
            static.copy_(given)
        self._graph.replay()
        return self._out

    def _packed(self):
        return tuple(self._static) if len(self._static) > 1 else self._static[0]

    def _check_pose(self, pose) -> np.ndarray | None:
        if pose is None:
            if self.uses_odometry:
                raise ValueError(
                    "this model has memory (polar_memory) and reads each frame's odometry pose: give "
                    "step(energyscape, pose) a pose (x, y, yaw) or a 4 x 4 sensor-to-odom matrix"
                )
            return None
        pose = np.asarray(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64)
        if pose.shape == (4, 4):
            pose = planar(pose)
        if pose.shape != (3,):
            raise ValueError(f"pose must be (x, y, yaw) or a 4 x 4 sensor-to-odom matrix, got shape {pose.shape}")
        if not np.isfinite(pose).all():
            raise ValueError(f"pose {pose.tolist()} is not finite: give the odometry's pose of this frame")
        return pose

    def _check_energyscape(self, energyscape) -> torch.Tensor:
        if not isinstance(energyscape, torch.Tensor):
            energyscape = np.ascontiguousarray(energyscape)
            if energyscape.dtype.kind not in "fiu":
                raise ValueError(f"energyscape must hold real numbers, got dtype {energyscape.dtype}")
        image = torch.as_tensor(energyscape)
        if image.is_complex() or image.dtype == torch.bool:
            raise ValueError(f"energyscape must hold real numbers, got {image.dtype}")
        if tuple(image.shape) == self.grid and self.shape[0] == 1:
            image = image[None]
        if tuple(image.shape) != self.shape:
            elevations = ", ".join(f"{e:g}" for e in self.elevation_deg)
            raise ValueError(
                f"energyscape has shape {tuple(image.shape)}, but the model reads {self.shape[0]} elevation(s) "
                f"({elevations} deg) x {self.grid[0]} ranges x {self.grid[1]} azimuths (beamform on the checkpoint's "
                "grid and elevations)"
            )
        if not bool(torch.isfinite(image).all()):  # checked where it is (the host's, mostly): no wait on a GPU
            raise ValueError(f"energyscape of frame {self.count} holds NaN or inf values: pass finite energyscapes")
        return image.to(self.device)
