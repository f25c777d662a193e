"""A suite scenario can be a user's mesh file: checked when the suite is loaded, hashed into the plan
id, loaded once per process, and simulated as the builders' scenes are.

The room used throughout: a 4 x 3 x 2.5 m box room (inward faces) whose corner lies at (10, -3, 0),
with a 0.6 x 0.6 x 1 m crate in it, written as an OBJ with `usemtl` floor, walls, ceiling and crate;
its table maps walls -> brick and crate -> wood.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh

from acoustic_sim.datasets import mesh_scenarios
from acoustic_sim.datasets.generate import SuiteRenderer, generate
from acoustic_sim.datasets.plan import plan
from acoustic_sim.datasets.suites import load_suite, mesh_files

from .cli_runner import run_commands
from .reference.raycast import first_hits

CORNER = np.array([10.0, -3.0, 0.0])
ROOM = (4.0, 3.0, 2.5)
CRATE = ((12.6, -1.6, 0.0), (13.2, -1.0, 1.0))  # low and high corners [m]
TABLE = '[materials]\nwalls = "brick"\ncrate = "wood"\n'
SUITE = """name = "mine"
frames = 4
episode_frames = 4
[physics]
ray_count = 500
lidar_noise = "none"
[[scenarios]]
name = "room"
mesh = "{mesh}"
materials = "{table}"
up = "z"
units = "m"
"""


def room_parts(size=ROOM, corner=CORNER, crate=CRATE) -> list[tuple[str, trimesh.Trimesh]]:
    """(material name, mesh) of the room: its shell split by face direction, and the crate."""
    box = trimesh.creation.box(extents=size)
    box.apply_translation(np.asarray(corner) + np.asarray(size) / 2)
    shell = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)  # normals into the room
    up = shell.face_normals[:, 2]
    parts = [
        (name, shell.submesh([np.flatnonzero(keep)], append=True))
        for name, keep in (("floor", up > 0.5), ("walls", np.abs(up) <= 0.5), ("ceiling", up < -0.5))
    ]
    if crate is not None:
        low, high = np.asarray(crate[0]), np.asarray(crate[1])
        parts.append(("crate", trimesh.creation.box(bounds=np.stack([low, high]))))
    return parts


def obj_text(parts) -> str:
    lines, offset = ["# a test room"], 1
    for name, mesh in parts:
        lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in mesh.vertices]
        lines.append(f"usemtl {name}")
        lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(mesh.faces) + offset]
        offset += len(mesh.vertices)
    return "\n".join(lines) + "\n"


def write_suite(folder: Path, *, mesh="room.obj", table="room_materials.toml", parts=None, suite=SUITE) -> Path:
    """The room (or `parts`), its table and a suite naming both relative to it, in `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / mesh).write_text(obj_text(room_parts() if parts is None else parts))
    (folder / table).write_text(TABLE)
    path = folder / "suite.toml"
    path.write_text(suite.format(mesh=mesh, table=table))
    return path


@pytest.fixture(scope="module")
def mesh_dataset(tmp_path_factory, device):
    """One 4-frame drive through the room, generated from its suite file on the test device."""
    folder = tmp_path_factory.mktemp("mesh_suite")
    suite = load_suite(write_suite(folder / "building"))
    out = folder / "data"
    generate(suite, out, device=device, progress=False)
    return folder, out


def test_dataset_scenes_are_the_mesh(mesh_dataset):
    """Each LiDAR range equals Open3D's ray cast on the OBJ (read by trimesh alone) from the recorded
    pose (no LiDAR noise in the suite), and the episode's scene record has the OBJ's bounds and the
    table's materials: the dataset was simulated in the user's mesh, not in some builder's room."""
    folder, out = mesh_dataset
    with h5py.File(out / "shard-00000.h5") as f:
        ranges, poses = f["lidar/ranges"][()], f["pose"][()]
        config = json.loads(f.attrs["config"])
        record = json.loads(f.attrs["episodes"])[0]
    reference = trimesh.load(folder / "building" / "room.obj", force="mesh", process=False)
    lidar = config["sim"]["lidar"]
    azimuths = np.deg2rad(np.linspace(lidar["azimuth_min_deg"], lidar["azimuth_max_deg"], lidar["azimuth_count"]))
    beams = np.stack([np.cos(azimuths), np.sin(azimuths), np.zeros_like(azimuths)], axis=1)
    for pose, scan in zip(poses, ranges, strict=True):
        origins = np.repeat(pose[None, :3, 3], len(beams), axis=0)
        want, _ = first_hits(reference.vertices, reference.faces, origins, beams @ pose[:3, :3].T)
        want[(want < lidar["range_min_m"]) | (want > lidar["range_max_m"])] = np.inf
        assert np.isfinite(want).mean() > 0.9  # the room encloses the sensor
        np.testing.assert_allclose(scan, want, atol=1e-3)
    scene = json.loads(record["scene"])
    np.testing.assert_allclose(scene["bounds_m"], reference.bounds, atol=1e-4)
    assert sorted(m["name"] for m in scene["materials"]) == ["brick", "ceiling_tile", "floor", "wood"]
    assert scene["params"]["file"] == "room.obj" and scene["params"]["sha256"] == record["scene_params"]["sha256"]


def test_dataset_records_the_mesh_by_name_and_hash(mesh_dataset):
    """plan.json, manifest.json and the card name the mesh and its table with their SHA-256, and no
    file of the dataset holds the folder they lie in (a path of this machine)."""
    folder, out = mesh_dataset
    sha = mesh_scenarios.file_sha256(folder / "building" / "room.obj")
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["meshes"]["room"]["file"] == "room.obj" and manifest["meshes"]["room"]["sha256"] == sha
    assert json.loads((out / "plan.json").read_text())["suite_config"]["scenarios"][0]["mesh"]["sha256"] == sha
    card = (out / "README.md").read_text()
    assert "`room.obj` (sha256 " + sha[:16] in card and "`room_materials.toml`" in card
    mapped = [(m["name"], m["material"], m["faces"]) for m in manifest["meshes"]["room"]["material_map"]]
    assert mapped == [
        ("floor", "floor", 2),
        ("walls", "brick", 8),
        ("ceiling", "ceiling_tile", 2),
        ("crate", "wood", 12),
    ]
    assert "| room: `crate` | wood (12 faces; table: 'crate') |" in card
    with h5py.File(out / "shard-00000.h5") as f:
        attrs = json.dumps({k: str(v) for k, v in f.attrs.items()})
    for text in (attrs, card, (out / "plan.json").read_text(), (out / "manifest.json").read_text()):
        assert str(folder) not in text


def plan_id(suite_path: Path) -> str:
    return plan(load_suite(suite_path), suite_path.parent / "out", frames=4)[0].plan_id


def test_plan_id_follows_the_bytes_not_the_place(tmp_path):
    """One byte more in the mesh or in the table changes the plan id; the same files moved to
    another folder and renamed (the suite naming the new names) keep it."""
    first = write_suite(tmp_path / "a")
    moved = write_suite(tmp_path / "elsewhere" / "b", mesh="lab.obj", table="lab_materials.toml")
    assert plan_id(moved) == plan_id(first)
    for name in ("room.obj", "room_materials.toml"):
        changed = tmp_path / f"changed_{name}"
        shutil.copytree(tmp_path / "a", changed)
        with open(changed / name, "a") as f:
            f.write(" ")  # one byte: the same geometry and materials, other bytes
        assert plan_id(changed / "suite.toml") != plan_id(first), name


def test_relative_paths_read_from_the_suite_folder(tmp_path, monkeypatch):
    """Loaded from another working folder that holds files of the same names (an empty closet
    and another table), the suite finds its own room and table beside it."""
    suite = write_suite(tmp_path / "suite_folder")
    decoy = tmp_path / "cwd"
    write_suite(decoy, parts=room_parts(size=(5.0, 5.0, 3.0), crate=None))
    (decoy / "room_materials.toml").write_text('[materials]\nwalls = "glass"\n')
    monkeypatch.chdir(decoy)
    mesh = load_suite(Path(os.path.relpath(suite, decoy))).scenarios[0].mesh
    assert mesh.sha256 == mesh_scenarios.file_sha256(suite.parent / "room.obj")
    assert mesh.materials_sha256 == mesh_scenarios.file_sha256(suite.parent / "room_materials.toml")
    assert Path(mesh.path).is_absolute() and Path(mesh.path).samefile(suite.parent / "room.obj")


def test_each_mesh_loads_once_per_process(tmp_path, monkeypatch, device):
    """Loading the suite loads the mesh once; two episodes simulated after it load it no more."""
    calls = []
    real = mesh_scenarios.load
    monkeypatch.setattr(mesh_scenarios, "load", lambda *a, **k: calls.append(a) or real(*a, **k))
    monkeypatch.setattr(mesh_scenarios, "_SCENES", {})
    path = write_suite(tmp_path, suite=SUITE.replace("episode_frames = 4", "episode_frames = 2"))
    suite = load_suite(path)
    generate(suite, tmp_path / "out", device=device, progress=False, frames=4)
    assert len(calls) == 1


def test_a_mesh_changed_after_loading_is_refused(tmp_path, monkeypatch):
    """A worker that loads the mesh anew refuses a file whose bytes no longer hash as planned."""
    mesh = load_suite(write_suite(tmp_path)).scenarios[0].mesh
    monkeypatch.setattr(mesh_scenarios, "_SCENES", {})
    with open(mesh.path, "a") as f:
        f.write("# edited\n")
    with pytest.raises(ValueError, match="changed since its suite was loaded"):
        mesh_scenarios.mesh_scene(mesh)


def test_several_meshes_with_physics_drawn_per_episode(tmp_path):
    """Two scenarios, two files: the episodes are dealt to both, each prepared in its own mesh (its
    bounds), and the suite's surfaces table draws what the walls reflect per episode, as for a builder."""
    path = write_suite(tmp_path)
    (tmp_path / "hall.obj").write_text(obj_text(room_parts(size=(8.0, 6.0, 4.0), corner=(0.0, 0.0, 0.0), crate=None)))
    surfaces = 'surfaces = { walls = { reflection = [0.5, 0.6] } }\n[[scenarios]]\nname = "room"'
    path.write_text(
        path.read_text().replace('[[scenarios]]\nname = "room"', surfaces)
        + '[[scenarios]]\nname = "hall"\nmesh = "hall.obj"\nup = "z"\nunits = "m"\n'
    )
    suite = load_suite(path)
    renderer = SuiteRenderer(mesh_files(suite))
    tasks = plan(suite, tmp_path / "out", frames=8)
    seen = {}
    for episode in tasks[0].episodes:
        ready = renderer.prepare(tasks[0], episode)
        seen[episode.scenario_name] = ready.scene.mesh.bounds
        walls = [m for m in ready.scene.materials if m.name.endswith(":walls")]
        assert walls and all(0.5 <= m.acoustic_reflection <= 0.6 for m in walls)
        assert 0.5 <= ready.acoustics["walls"]["reflection"] <= 0.6
    np.testing.assert_allclose(seen["room"], [CORNER, CORNER + ROOM])
    np.testing.assert_allclose(seen["hall"], [(0.0, 0.0, 0.0), (8.0, 6.0, 4.0)])


def test_builder_and_mesh_fields_do_not_mix(tmp_path):
    """A scenario with a builder and a mesh, or with mesh fields and no mesh, is refused by name."""
    path = write_suite(tmp_path)
    text = path.read_text()
    path.write_text(text.replace('name = "room"\n', 'name = "room"\nbuilder = "office"\n'))
    with pytest.raises(ValueError, match=r"scenarios\[0\] \('room'\): give a builder or a mesh, not both"):
        load_suite(path)
    path.write_text(text.replace('mesh = "room.obj"\n', ""))
    with pytest.raises(ValueError, match=r"scenarios\[0\]: give its builder \(or its mesh file"):
        load_suite(path)


CLI_CASES = {
    # name: (suite text or None, argv after `python -m acoustic_sim`, words the error line holds)
    "missing-mesh": (SUITE.replace("{mesh}", "nowhere.obj"), "generate", ["scenarios[0]", "mesh", "nowhere.obj"]),
    "bad-material": (
        SUITE.replace("{table}", "bad.toml"),
        "generate",
        ["scenarios[0]", "bad.toml", "'walls' = 'granite' is not one of our materials"],
    ),
    "list-material": (
        SUITE.replace("{table}", "list.toml"),
        "generate",
        ["scenarios[0]", "list.toml", "'walls' = ['brick'] is a list"],
    ),
    "vary": (
        SUITE.replace('up = "z"', 'up = "z"\nvary = {{ size = [3.0, 5.0] }}'),
        "generate",
        ["scenarios[0]", "vary applies to builders, not to a mesh file"],
    ),
    "no-room": (
        SUITE.replace("{mesh}", "closet.obj"),
        "generate",
        ["scenarios[0]", "closet.obj", "no room for a robot"],
    ),
    "render-up": (None, "render --up y --out {tmp}/x.png", ["--up applies to --mesh only", "--scene office"]),
}


@pytest.fixture(scope="module")
def cli_results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mesh_suite_cli")
    commands = {}
    for name, (suite, argv, _) in CLI_CASES.items():
        folder = tmp / name
        if suite is not None:
            write_suite(folder)
            (folder / "closet.obj").write_text(obj_text(room_parts(size=(0.6, 0.6, 2.5), crate=None)))
            (folder / "bad.toml").write_text('[materials]\nwalls = "granite"\n')
            (folder / "list.toml").write_text('[materials]\nwalls = ["brick"]\n')
            (folder / "suite.toml").write_text(suite.format(mesh="room.obj", table="room_materials.toml"))
            argv = f"generate --suite {folder / 'suite.toml'} --out {folder / 'out'} --device cpu"
        commands[name] = ("acoustic_sim", argv.format(tmp=tmp).split())
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return tmp, run_commands(commands, env=env, parallel=2 * (os.cpu_count() or 1))


@pytest.mark.parametrize("name", list(CLI_CASES))
def test_bad_mesh_scenarios_are_one_error_line(cli_results, name):
    """Each bad input ends with exit code 2 and one `error:` line naming the suite file and the
    field (or the option), before anything is written."""
    tmp, done = cli_results
    result, words = done[name], CLI_CASES[name][2]
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert len(errors) == 1 and result.stderr.strip().endswith(errors[0]), result.stderr[-3000:]
    if CLI_CASES[name][0] is not None:
        words = [str(tmp / name / "suite.toml"), *words]
        assert not (tmp / name / "out").exists()
    for word in words:
        assert word in errors[0], (word, errors[0])
