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
        faces: The faces a path meets, in order, int32 (n, MAX_ORDER), -1 after its last: off
            planes, each reflection's face; off a sphere or cylinder, the face whose material it
            reflects with; for a scattered echo the faces its ray reflected off and last the one
            that scattered it, where the tracer recorded them (`PathTracer(scattered_faces=True)`),
            else all -1. What the amplitude owes to each surface (`surface_factors`): sqrt(R (1 - s))
            per reflection, R and s of that face; sqrt(R s) for the face that scattered, sqrt(R)
            where an edge band scattered (`edge`). None where the arrivals were not traced here.
        edge: Whether an edge band scattered the echo (it scatters all it reflects), bool (n,);
            False for specular echoes and wherever the faces were not recorded.
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
    edge: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.delay_s)

    def select(self, mask: np.ndarray) -> Arrivals:
        return Arrivals(**{k: None if v is None else v[mask] for k, v in self.__dict__.items()})

    def surface_counts(self, face_surface: np.ndarray, surfaces: int) -> np.ndarray:
        """How often each arrival's path meets each surface class, int64 (n, surfaces): `face_surface`
        gives every face's class (e.g. `Scene.face_material`). Zero rows for arrivals whose faces
        are not recorded (see `faces`)."""
        if self.faces is None:
            raise ValueError("these arrivals carry no faces (trace them with PathTracer or Sonar.trace)")
        return self._counts(face_surface, surfaces, self.faces >= 0)

    def surface_factors(self, face_surface: np.ndarray, surfaces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What each arrival's amplitude owes to each surface class, as powers of square roots:
        (reflections, kept, scattered), int64 (n, surfaces) each, so that the amplitude scales
        as prod_k sqrt(R_k)^reflections sqrt(1 - s_k)^kept sqrt(s_k)^scattered. A specular
        reflection counts in the first two, a scattering face in the first and (but at an edge
        band, which scatters all) the third."""
        reflected, kept, scattered = self.face_roles()
        return tuple(self._counts(face_surface, surfaces, which) for which in (reflected, kept, scattered))

    def face_roles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which entries of `faces` reflect (every face met), keep their specular share (all but a
        scattered echo's last) and scatter (that last, where no edge band scattered it): bool
        (n, MAX_ORDER) each."""
        if self.faces is None:
            raise ValueError("these arrivals carry no faces (trace them with PathTracer or Sonar.trace)")
        reflected = self.faces >= 0
        last = np.zeros_like(reflected)
        scattering = np.nonzero(self.kind == KIND_SCATTERED)[0]
        last[scattering, np.maximum(reflected[scattering].sum(axis=1) - 1, 0)] = reflected[scattering].any(axis=1)
        edge = np.zeros(len(self), dtype=bool) if self.edge is None else self.edge
        return reflected, reflected & ~last, last & ~edge[:, None]

    def _counts(self, face_surface: np.ndarray, surfaces: int, which: np.ndarray) -> np.ndarray:
        """Per arrival, how many of its faces where `which` (n, MAX_ORDER) belong to each class."""
        rows = np.nonzero(which)[0]
        counts = np.zeros((len(self), surfaces), dtype=np.int64)
        np.add.at(counts, (rows, np.asarray(face_surface)[self.faces[which]]), 1)
        return counts

    def for_pose(self, i: int) -> Arrivals:
        """The arrivals of ping i, sorted by delay."""
        sub = self.select(self.pose_index == i)
        return sub.select(np.argsort(sub.delay_s, kind="stable"))


@dataclass
class TraceBuffers:
    """A batch's device arrays (see `PathTracer._buffers_for`): pose checks, the sequence and
    image tables, counters and the echoes found."""

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
    hit_faces: wp.array  # (pings, rays, MAX_ORDER) int32 each hit's face; no rays unless faces are recorded
    curved: PointEchoes  # (pings, curved surfaces) echoes off spheres and cylinders

    @property
    def echoes(self) -> TracedEchoes:
        return TracedEchoes(self.specular, self.scattered, self.curved, self.ray_queries, self.hit_faces)


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
    ray: wp.array = None  # scattered: each slot's ray, -(ray + 1) off an edge band; no slots unless recorded


@dataclass
class TracedEchoes:
    specular: SpecularEchoes
    scattered: PointEchoes
    curved: PointEchoes  # first-order specular echoes off curved surfaces, one slot per surface
    ray_queries: wp.array  # (pings,) BVH ray queries made per ping, all stages
    hit_faces: wp.array | None = None  # see TraceBuffers

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
                edge=np.zeros(len(length), dtype=bool),
            )
        ]
        for echoes, kind in ((self.scattered, KIND_SCATTERED), (self.curved, KIND_SPECULAR)):
            if echoes.slots:
                found, slot = _point_arrivals(echoes, kind, speed_of_sound)
                found.faces = np.full((len(found), faces.shape[1]), -1, dtype=np.int32)
                found.edge = np.zeros(len(found), dtype=bool)
                if echoes is self.curved and curved_faces is not None:  # a curved echo's slot is its surface
                    found.faces[:, 0] = curved_faces[slot]
                if echoes is self.scattered and echoes.ray.shape[1]:
                    self._scattered_faces(found, slot)
                parts.append(found)
        found = concatenate(parts)
        return found.select(np.lexsort((found.order, found.delay_s, found.kind, found.pose_index)))

    def _scattered_faces(self, found: Arrivals, slot: np.ndarray) -> None:
        """Fill scattered arrivals' faces (the ray's hits up to the one that scattered) and edge flags."""
        code = self.scattered.ray.numpy()[found.pose_index, slot]
        found.edge = code < 0
        ray = np.where(found.edge, -code - 1, code)
        faces = self.hit_faces.numpy()[found.pose_index, ray]
        faces[np.arange(faces.shape[1])[None, :] >= found.order[:, None]] = -1
        found.faces = faces


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
