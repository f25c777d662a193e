"""The path tracer's kernel launches for one batch of pings (`paths.PathTracer` queues a batch;
this module says which kernels run on its buffers, with what).

Per ping, in stream order: the rays discover reflection sequences (and rain scattered echoes),
the image-source method validates each sequence as an exact specular path, every image source
is claimed by its lowest-ranked sequence and the others are dropped, and the curved surfaces
echo. Each ping has its own rows of every table, so slices of a batch may run in threads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import warp as wp

from .echoes import TraceBuffers
from .kernels import curved as curved_kernels
from .kernels import image_sources as image_kernels
from .kernels import paths as kernels
from .scene import WarpScene

# Threads per block of the ray-walking kernel: 64 made 1.05-1.12x the energyscapes/s of Warp's 256
# end to end on the office (an H100, 20k and 100k rays): its rays end their walks at different times.
RAY_BLOCK_DIM = 64


def reset_tables(buffers: TraceBuffers) -> None:
    """Tables and counters to zero (image ranks to RANK_NONE), as the kernels expect; every other
    array is read only where a kernel of the batch wrote it."""
    b = buffers
    for table in (b.key, b.specular.order, b.planes, b.image_table, b.overflow, b.ray_queries, b.scattered.count):
        table.zero_()
    b.image_rank.fill_(image_kernels.RANK_NONE)


@dataclass(frozen=True)
class TracerInputs:
    """What the pings of every batch read besides the scene and their poses."""

    emitter: wp.vec3  # emitter position, sensor frame [m]
    ray_dirs: wp.array  # vec3 (rays,) unit directions, sensor frame
    ray_energy: wp.array  # float (rays,) each ray's share of the emitted energy
    directivity: wp.array  # float (2 DIRECTIVITY_STEPS + 1,) emitter amplitude over cos(angle from its axis), -1..1
    emit_min_cosine: float  # paths leaving the emitter at a lower cosine from its axis are cut (its baffle)
    ray_count: int
    max_order: int  # reflections per path: max_bounces + 1
    edge_width_m: float  # band along sharp edges that scatters everything it reflects [m]
    scattering: bool  # rain scattered echoes


@dataclass(frozen=True)
class Rows:
    """Pings first..last-1 of a batch: `rows(a)` is their rows of a batch array `a`."""

    first: int
    last: int

    @property
    def count(self) -> int:
        return self.last - self.first

    def __call__(self, a: wp.array) -> wp.array:
        return a if 0 in a.shape else a[self.first : self.last]  # Warp cannot slice an array with an empty axis


@dataclass(frozen=True)
class BatchStages:
    """The stages of one batch, launched for any slice of its pings (`trace_rows`).

    Args:
        scene: The scene on the batch's device.
        buffers: The batch's device buffers, reset (`reset_tables`).
        poses, inverse: Sensor-to-world and world-to-sensor transforms, mat44 (pings,).
        size: Slots per ping of the sequence and image tables.
        inputs: The tracer's rays, emitter and settings.
        launch: `wp.launch` bound to the batch's device (threads must not share a scoped device).
    """

    scene: WarpScene
    buffers: TraceBuffers
    poses: wp.array
    inverse: wp.array
    size: int
    inputs: TracerInputs
    launch: Callable

    def trace_rows(self, first: int, last: int) -> None:
        """Every stage for pings first..last-1."""
        rows = Rows(first, last)
        poses, inverse = rows(self.poses), rows(self.inverse)
        self.discover_sequences(rows, poses, inverse)
        self.validate_sequences(rows, poses)
        self.drop_duplicate_images(rows)
        if self.scene.curved.count:
            self.curved_echoes(rows, poses, inverse)

    def discover_sequences(self, rows: Rows, poses: wp.array, inverse: wp.array) -> None:
        """One thread per ray: the sequence table, its overflow count and the scattered echoes
        (`poses`, `inverse`: the rows' transforms)."""
        ws, b, tracer = self.scene, self.buffers, self.inputs
        scattered = b.scattered
        self.launch(
            kernels.discover_sequences,
            dim=rows.count * tracer.ray_count,
            inputs=[
                ws.mesh.id,
                ws.face_plane,
                poses,
                inverse,
                tracer.emitter,
                tracer.ray_dirs,
                tracer.max_order,
                ws.face_reflection,
                ws.face_scattering,
                ws.face_sharp_edges,
                ws.face_altitudes,
                tracer.edge_width_m,
                tracer.ray_energy,
                int(tracer.scattering),
            ],
            outputs=[
                rows(b.key),
                rows(scattered.count),
                rows(b.specular.order),
                rows(b.planes),
                rows(b.overflow),
                rows(scattered.source),
                rows(scattered.extra_length),
                rows(scattered.amplitude),
                rows(scattered.order),
                rows(b.ray_queries),
                rows(b.hit_faces),
                rows(scattered.ray),
            ],
            block_dim=RAY_BLOCK_DIM,
        )

    def validate_sequences(self, rows: Rows, poses: wp.array) -> None:
        """One thread per table slot: the slot's exact specular path, or amplitude 0."""
        ws, b, specular = self.scene, self.buffers, self.buffers.specular
        self.launch(
            image_kernels.validate_sequences,
            dim=(rows.count, self.size),
            inputs=[
                ws.mesh.id,
                ws.face_plane,
                ws.plane_normal,
                ws.plane_offset,
                ws.face_reflection,
                ws.face_scattering,
                poses,
                self.inputs.emitter,
                rows(b.key),
                rows(specular.order),
                ws.plane_curved,
                self.inputs.directivity,
                self.inputs.emit_min_cosine,
                rows(b.planes),  # becomes each valid path's faces
            ],
            outputs=[
                rows(specular.amplitude),
                rows(specular.source),
                rows(specular.direction),
                rows(specular.point),
                rows(b.ray_queries),
            ],
        )

    def drop_duplicate_images(self, rows: Rows) -> None:
        """Sequences that found one image source keep one echo: the lowest-ranked claims it, the
        others get amplitude 0."""
        b, specular = self.buffers, self.buffers.specular
        slots = (rows.count, self.size)
        images = [rows(specular.order), rows(specular.source), rows(b.key)]
        self.launch(
            image_kernels.claim_images,
            dim=slots,
            inputs=[rows(specular.amplitude), *images],
            outputs=[rows(b.image_table), rows(b.image_rank)],
        )
        self.launch(
            image_kernels.drop_duplicate_images,
            dim=slots,
            inputs=[*images, rows(b.image_table), rows(b.image_rank)],
            outputs=[rows(specular.amplitude)],
        )

    def curved_echoes(self, rows: Rows, poses: wp.array, inverse: wp.array) -> None:
        """One thread per curved surface: its specular echo, where it has one."""
        ws, b, surfaces, curved = self.scene, self.buffers, self.scene.curved, self.buffers.curved
        self.launch(
            curved_kernels.curved_echoes,
            dim=(rows.count, surfaces.count),
            inputs=[
                ws.mesh.id,
                surfaces.kind,
                surfaces.centre,
                surfaces.radius,
                surfaces.z_range,
                surfaces.axis,
                surfaces.gain,
                poses,
                inverse,
                self.inputs.emitter,
                self.inputs.directivity,
                self.inputs.emit_min_cosine,
            ],
            outputs=[
                rows(curved.source),
                rows(curved.extra_length),
                rows(curved.amplitude),
                rows(curved.order),
                rows(b.ray_queries),
            ],
        )
