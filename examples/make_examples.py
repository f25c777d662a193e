"""Make the README's example inputs: plan.svg, building.obj, lab.obj, lab_materials.toml, lab_suite.toml
and pings.npz (my_suite.toml is hand-written).

Run from the repository root: `.venv/bin/python examples/make_examples.py` (about 10 s on a 2-core CPU).
The same three rooms appear as a floor plan (plan.svg) and as a mesh (building.obj); lab.obj is a room
whose faces carry material names (usemtl), with a round pillar made by trimesh, its material table
and a suite that makes a dataset of it; pings.npz holds eight pings simulated by our sonar along a
drive through the office, as a recording would hold them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# The building, in metres: an 8 x 6 m outline split into three rooms by a wall at x = 4 m (door at
# y = 2.4..3.6 m) and a wall at y = 3 m right of it (door at x = 5.4..6.6 m); a pillar in the left room.
SIZE = (8.0, 6.0)
WALLS = [  # (x0, y0, x1, y1): wall centre lines
    (0.0, 0.0, 8.0, 0.0),
    (8.0, 0.0, 8.0, 6.0),
    (8.0, 6.0, 0.0, 6.0),
    (0.0, 6.0, 0.0, 0.0),
    (4.0, 0.0, 4.0, 2.4),
    (4.0, 3.6, 4.0, 6.0),
    (4.0, 3.0, 5.4, 3.0),
    (6.6, 3.0, 8.0, 3.0),
]
PILLAR = (2.0, 4.0, 0.2)  # centre x, y and radius [m]
WALL_HEIGHT, WALL_THICKNESS = 2.5, 0.1


def plan_svg() -> str:
    """The building as an SVG floor plan in centimetres (render it with --scene-arg scale=0.01)."""
    cm = 100.0
    width, height = SIZE[0] * cm, SIZE[1] * cm
    lines = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:g}" height="{height:g}" '
        f'viewBox="0 0 {width:g} {height:g}">',
        "  <!-- three rooms, 1 unit = 1 cm; SVG y points down (from_svg flips it) -->",
        f'  <rect x="0" y="0" width="{width:g}" height="{height:g}" fill="none" stroke="black"/>',
    ]
    for x0, y0, x1, y1 in WALLS[4:]:  # the outline is the rect
        lines.append(
            f'  <line x1="{x0 * cm:g}" y1="{(SIZE[1] - y0) * cm:g}" x2="{x1 * cm:g}" y2="{(SIZE[1] - y1) * cm:g}" '
            'stroke="black"/>'
        )
    x, y, r = PILLAR
    lines.append(f'  <circle cx="{x * cm:g}" cy="{(SIZE[1] - y) * cm:g}" r="{r * cm:g}" fill="grey"/>')
    lines.append("</svg>")
    return "\n".join(lines) + "\n"


def _box(low, high) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward-wound triangles (12, 3) of an axis-aligned box."""
    (x0, y0, z0), (x1, y1, z1) = low, high
    v = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)])
    f = [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4]]
    f += [[2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]]
    return v, np.array(f)


def building_obj() -> str:
    """The building as a closed-room mesh (walls, floor and ceiling slabs, a square pillar), z up."""
    half = WALL_THICKNESS / 2
    boxes = [((-half, -half, -0.05), (SIZE[0] + half, SIZE[1] + half, 0.0))]  # floor slab
    boxes.append(((-half, -half, WALL_HEIGHT), (SIZE[0] + half, SIZE[1] + half, WALL_HEIGHT + 0.05)))  # ceiling
    for x0, y0, x1, y1 in WALLS:
        lo = (min(x0, x1) - half, min(y0, y1) - half, 0.0)
        boxes.append((lo, (max(x0, x1) + half, max(y0, y1) + half, WALL_HEIGHT)))
    x, y, r = PILLAR
    boxes.append(((x - r, y - r, 0.0), (x + r, y + r, WALL_HEIGHT)))
    out = ["# three rooms (8 x 6 m, walls 2.5 m high), metres, z up; made by examples/make_examples.py"]
    faces = []
    for i, (low, high) in enumerate(boxes):
        v, f = _box(low, high)
        out += [f"v {a:g} {b:g} {c:g}" for a, b, c in v]
        faces += [f"f {a} {b} {c}" for a, b, c in f + 1 + 8 * i]
    return "\n".join(out + faces) + "\n"


# The lab, in metres, z up: a 6 x 4 m room 2.6 m high whose wall at y = 4 m is glass from x = 2 to 4 m,
# a steel cabinet against the wall at y = 0, and a round pillar from floor to ceiling.
LAB_SIZE = (6.0, 4.0, 2.6)
LAB_GLASS_X = (2.0, 4.0)
LAB_CABINET = ((4.6, 0.1, 0.0), (5.8, 0.6, 1.9))  # low and high corners [m]
LAB_PILLAR = (2.0, 1.8, 0.15)  # centre x, y and radius [m]
LAB_MATERIALS = """\
# examples/lab_materials.toml
# lab.obj's material names (usemtl) -> ours, before the name patterns
[materials]
walls = "brick"           # the pattern would say painted_wall; the table comes first
pillar = "painted_wall"   # no pattern knows "pillar": without this line it gets the default, with a warning
"""
LAB_SUITE = """\
# examples/lab_suite.toml
# a dataset of your own building (lab.obj, made by make_examples.py)
name = "lab"
frames = 16
episode_frames = 8
[physics]
ray_count = 5000
[[scenarios]]
name = "lab"
mesh = "lab.obj"                   # read from this file's folder, as is the table
materials = "lab_materials.toml"
up = "z"
units = "m"
"""


def _quad(corners) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (4, 3) and the two triangles of a planar quad, wound as its corners go."""
    return np.array(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def lab_parts() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The lab's parts: (material name, vertices (V, 3) [m], triangles (F, 3)); the room's surfaces
    face into it, the cabinet and the pillar out of themselves."""
    import trimesh

    x1, y1, z1 = LAB_SIZE
    g0, g1 = LAB_GLASS_X

    def wall(a, b):  # from (x, y) a to b with the room on its left (anticlockwise seen from above)
        return _quad([(*a, 0.0), (*a, z1), (*b, z1), (*b, 0.0)])

    walls = [wall((0.0, 0.0), (x1, 0.0)), wall((x1, 0.0), (x1, y1)), wall((x1, y1), (g1, y1))]
    walls += [wall((g0, y1), (0.0, y1)), wall((0.0, y1), (0.0, 0.0))]
    parts = [
        ("floor", *_quad([(0.0, 0.0, 0.0), (x1, 0.0, 0.0), (x1, y1, 0.0), (0.0, y1, 0.0)])),
        ("ceiling", *_quad([(0.0, 0.0, z1), (0.0, y1, z1), (x1, y1, z1), (x1, 0.0, z1)])),
        *(("walls", v, f) for v, f in walls),
        ("glass", *wall((g1, y1), (g0, y1))),
        ("metal", *_box(*LAB_CABINET)),
    ]
    x, y, r = LAB_PILLAR
    pillar = trimesh.creation.cylinder(radius=r, height=z1, sections=32)
    pillar.apply_translation((x, y, z1 / 2))
    side = np.abs(pillar.face_normals[:, 2]) < 0.5  # its caps would lie in the floor and the ceiling
    pillar = pillar.submesh([np.flatnonzero(side)], append=True)
    parts.append(("pillar", np.asarray(pillar.vertices), np.asarray(pillar.faces)))
    return parts


def lab_obj() -> str:
    """The lab as an OBJ file: one `usemtl` group per material name."""
    out = ["# a lab: 6 x 4 m, 2.6 m high, a glass wall, a steel cabinet, a round pillar; metres, z up;"]
    out.append("# made by examples/make_examples.py (the pillar by trimesh.creation.cylinder)")
    offset = 1
    for name, vertices, faces in lab_parts():
        out += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in vertices]
        out.append(f"usemtl {name}")
        out += [f"f {a} {b} {c}" for a, b, c in faces + offset]
        offset += len(vertices)
    return "\n".join(out) + "\n"


def pings(count: int = 8) -> dict[str, np.ndarray]:
    """`count` pings of the eRTIS along a drive through the office, as a recording holds them.

    Three secondary bounces and Gaussian microphone noise 30 dB below each ping's strongest sample,
    then one fixed gain for all pings and rounding to 8-bit counts: the quietest ping's noise has a
    standard deviation of 1 count (rounding adds 1/12 of that noise's power), the loudest samples
    stay below 128. Each record is cut to 14,336 of its 16,384 samples (31.9 ms: echoes from the
    grid's 5 m and the call); the energyscapes of the kept counts match those of the float signals
    to within 1 % of each ping's peak, which is checked here.
    """
    import acoustic_sim
    import scenes
    from acoustic_sim import energyscape

    scene = scenes.office(seed=0)
    poses = scenes.trajectory(scene, frames=count, seed=0)
    config = acoustic_sim.SonarConfig.ertis()
    sonar = acoustic_sim.Sonar(config, max_bounces=3, device="cpu")
    signals = sonar.record(sonar.trace(scene, poses), noise="gaussian", snr_db=30.0, seed=0)
    noise_std = np.abs(signals).max(axis=(1, 2)) * 10 ** (-30.0 / 20)
    counts = np.round(signals[:, :, :14_336] / noise_std.min())
    assert np.abs(counts).max() < 128, "int8 overflows: lower the gain"
    counts = counts.astype(np.int8)
    full, kept = energyscape(signals, config, device="cpu"), energyscape(counts, config, device="cpu")
    full, kept = (e / e.max(axis=(1, 2), keepdims=True) for e in (full, kept))
    assert np.abs(full - kept).max() < 0.01, "the stored counts lose the energyscape"
    return {"signals": counts, "pose": poses, "sample_rate_hz": np.float64(config.chirp.sample_rate_hz)}


def main() -> None:
    (HERE / "plan.svg").write_text(plan_svg())
    (HERE / "building.obj").write_text(building_obj())
    (HERE / "lab.obj").write_text(lab_obj())
    (HERE / "lab_materials.toml").write_text(LAB_MATERIALS)
    (HERE / "lab_suite.toml").write_text(LAB_SUITE)
    np.savez_compressed(HERE / "pings.npz", **pings())
    for name in ("plan.svg", "building.obj", "lab.obj", "lab_materials.toml", "lab_suite.toml", "pings.npz"):
        print(f"{HERE / name}: {(HERE / name).stat().st_size:,} bytes")


if __name__ == "__main__":
    main()
