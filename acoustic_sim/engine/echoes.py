"""What a trace leaves: echoes on the device, per kind, and their host copy (`Arrivals`).

Specular echoes off planes sit in the slots of a ping's sequence table (the image source and its
amplitude; 0 = empty or invalid); point echoes (scattered, and specular off curved surfaces) are
where the path last turned plus the path before it. `TracedEchoes.arrivals` copies a batch to
the host as flat numpy records.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .signals import EchoBuffer

KIND_SPECULAR = 0
KIND_SCATTERED = 1


@dataclass
class Arrivals:
    """Echoes of a batch of pings, flat over all poses (numpy, float64 unless noted).

    Attributes:
        pose_index: Ping each arrival belongs to, int64 (n,).
        delay_s: Emitter -> scene -> array centre travel time [s], (n,).
        direction: Unit direction the echo arrives from, sensor frame, (n, 3).
        amplitude: Pressure amplitude relative to 1 at 1 m on the emitter axis: spherical
            spreading, reflection factors and emitter directivity at the call's centre frequency
            (no air absorption: it depends on frequency and is applied when recording), (n,).
        order: Number of reflections, int64 (n,).
        kind: KIND_SPECULAR or KIND_SCATTERED, int64 (n,). A specular echo off a curved surface
            (sphere, cylinder) is KIND_SPECULAR of order 1 whose source_m equals its point_m.
        source_m: Where the echo seems to come from, sensor frame [m]: the image source of a
            specular path off planes (per-microphone delays |source - mic| / c), else the point
            where the path last turned (delays: the path before it plus |source - mic|), (n, 3).
        length_m: Path length [m], (n,).
        point_m: Where the echo last reflected or scattered, sensor frame [m], (n, 3).
        faces: The faces a specular path reflects off, in order, int32 (n, MAX_ORDER), -1 after
            its last: off planes, each reflection's face; off a sphere or cylinder, the face whose
            material it reflects with; all -1 for scattered echoes (their faces are not recorded).
            What the amplitude owes to each surface: a factor sqrt(R (1 - s)) per entry, R and s
            of that face (`surface_counts`). None where the arrivals were not traced here.
    """

    pose_index: np.ndarray
    delay_s: np.ndarray
    direction: np.ndarray
    amplitude: np.ndarray
    order: np.ndarray
    kind: np.ndarray
    source_m: np.ndarray
    length_m: np.ndarray
    point_m: np.ndarray
    faces: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.delay_s)

    def select(self, mask: np.ndarray) -> Arrivals:
        return Arrivals(**{k: None if v is None else v[mask] for k, v in self.__dict__.items()})

    def surface_counts(self, face_surface: np.ndarray, surfaces: int) -> np.ndarray:
        """How often each arrival's path reflects off each surface class, int64 (n, surfaces):
        `face_surface` gives every face's class (e.g. `Scene.face_material`). Zero rows for
        arrivals whose faces are not recorded (see `faces`)."""
        if self.faces is None:
            raise ValueError("these arrivals carry no faces (trace them with PathTracer or Sonar.trace)")
        face_surface = np.asarray(face_surface)
        hit = self.faces >= 0
        rows = np.nonzero(hit)[0]
        counts = np.zeros((len(self), surfaces), dtype=np.int64)
        np.add.at(counts, (rows, face_surface[self.faces[hit]]), 1)
        return counts

    def for_pose(self, i: int) -> Arrivals:
        """The arrivals of ping i, sorted by delay."""
        sub = self.select(self.pose_index == i)
        return sub.select(np.argsort(sub.delay_s, kind="stable"))


@dataclass
class TraceBuffers:
    """A batch's device arrays (see `PathTracer._buffers_for`): pose checks, the sequence and
    image tables, counters, the echoes found, and host copies of what the host reads."""

    errors: wp.array  # (pings,) float, pose_error
    behind: wp.array  # (pings,) int32, pose_error
    key: wp.array  # (pings, size) uint64 sequence hashes, 0 = empty slot
    planes: wp.array  # (pings, size, MAX_ORDER) int32 plane sequence per slot
    overflow: wp.array  # (pings,) int32 insertions that found no slot
    ray_queries: wp.array  # (pings,) int32 BVH ray queries, all stages
    image_table: wp.array  # (pings, size) uint64 image source hashes, 0 = empty slot
    image_rank: wp.array  # (pings, size) int32 lowest sequence rank per image source
    specular: SpecularEchoes
    scattered: PointEchoes
    curved: PointEchoes  # (pings, curved surfaces) echoes off spheres and cylinders
    host_checks: tuple[wp.array, wp.array, wp.array]  # errors, behind, overflow (page-locked on GPUs)

    @property
    def echoes(self) -> TracedEchoes:
        return TracedEchoes(self.specular, self.scattered, self.curved, self.ray_queries)


@dataclass
class SpecularEchoes(EchoBuffer):
    """Validated image-source paths in table slots (amplitude 0: empty or invalid)."""

    order: wp.array = None
    direction: wp.array = None
    point: wp.array = None
    faces: wp.array = None  # (pings, size, MAX_ORDER) int32: a valid slot's faces, in order


@dataclass
class PointEchoes(EchoBuffer):
    """Echoes from a point (source: where the path last reflected or scattered; extra_length: the
    path before it): scattered arrivals, and specular ones off curved surfaces."""

    order: wp.array = None


@dataclass
class TracedEchoes:
    specular: SpecularEchoes
    scattered: PointEchoes
    curved: PointEchoes  # first-order specular echoes off curved surfaces, one slot per surface
    ray_queries: wp.array  # (pings,) BVH ray queries made per ping, all stages

    @property
    def pose_count(self) -> int:
        return self.specular.amplitude.shape[0]

    def buffers(self) -> list[EchoBuffer]:
        return [self.specular, self.scattered, self.curved]

    def arrivals(self, speed_of_sound: float, curved_faces: np.ndarray | None = None) -> Arrivals:
        """Copy to the host as Arrivals, sorted by pose, kind, delay (a reproducible order).
        `curved_faces`: per curved surface the face whose material its echoes took (their faces)."""
        spec = self.specular
        amplitude = spec.amplitude.numpy()
        pose_index, slot = np.nonzero(amplitude > 0)
        source = spec.source.numpy()[pose_index, slot].astype(np.float64)
        length = np.linalg.norm(source, axis=1)
        order = spec.order.numpy()[pose_index, slot].astype(np.int64)
        faces = spec.faces.numpy()[pose_index, slot]
        faces[np.arange(faces.shape[1])[None, :] >= order[:, None]] = -1
        parts = [
            Arrivals(
                pose_index=pose_index.astype(np.int64),
                delay_s=length / speed_of_sound,
                direction=spec.direction.numpy()[pose_index, slot].astype(np.float64),
                amplitude=amplitude[pose_index, slot].astype(np.float64),
                order=order,
                kind=np.full(len(length), KIND_SPECULAR, dtype=np.int64),
                source_m=source,
                length_m=length,
                point_m=spec.point.numpy()[pose_index, slot].astype(np.float64),
                faces=faces,
            )
        ]
        for echoes, kind in ((self.scattered, KIND_SCATTERED), (self.curved, KIND_SPECULAR)):
            if echoes.slots:
                found, slot = _point_arrivals(echoes, kind, speed_of_sound)
                found.faces = np.full((len(found), faces.shape[1]), -1, dtype=np.int32)
                if echoes is self.curved and curved_faces is not None:  # a curved echo's slot is its surface
                    found.faces[:, 0] = curved_faces[slot]
                parts.append(found)
        found = concatenate(parts)
        return found.select(np.lexsort((found.order, found.delay_s, found.kind, found.pose_index)))


def _point_arrivals(echoes: PointEchoes, kind: int, speed_of_sound: float) -> tuple[Arrivals, np.ndarray]:
    """Arrivals of point echoes (slots below each ping's count with an amplitude), and their slots."""
    count = echoes.count.numpy()
    if (count > echoes.slots).any():  # cannot happen: each ray scatters at most once per order
        raise RuntimeError("point echo buffer overflow")
    amplitude = echoes.amplitude.numpy()
    keep = (np.arange(echoes.slots)[None, :] < count[:, None]) & (amplitude > 0)
    pose_index, slot = np.nonzero(keep)
    source = echoes.source.numpy()[keep].astype(np.float64)
    distance = np.linalg.norm(source, axis=1)
    length = echoes.extra_length.numpy()[keep].astype(np.float64) + distance
    return Arrivals(
        pose_index=pose_index.astype(np.int64),
        delay_s=length / speed_of_sound,
        direction=source / distance[:, None],
        amplitude=amplitude[keep].astype(np.float64),
        order=echoes.order.numpy()[keep].astype(np.int64),
        kind=np.full(len(length), kind, dtype=np.int64),
        source_m=source,
        length_m=length,
        point_m=source,
    ), slot


def concatenate(parts: list[Arrivals]) -> Arrivals:
    """Join arrival sets (kept flat; `for_pose` sorts by delay)."""

    def joined(key: str):
        arrays = [getattr(a, key) for a in parts]
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    return Arrivals(**{k: joined(k) for k in Arrivals.__dataclass_fields__})
