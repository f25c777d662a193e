"""The simulator's inputs, as a fault probe finds them (issue 38): a FIFO or /dev/urandom as any
input file, sizes no machine can hold, malformed suite, plan and shard files, CHIRP recordings
that are complex, rate-less, point outside themselves or claim a billion pings, Ctrl-C in
`generate`. Each is refused before anything is opened, allocated or written, in one line that
names the file or field; no size refusal here allocates anything big (claims and sparse files).

CLI paths run as subprocesses, started together in a module fixture (as tests/test_cli_errors.py
does); the rest call the same functions in this process, under a deadline where a defect would
hang (a FIFO opened for reading waits for a writer forever).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np
import pytest

import scenes
from acoustic_sim.cli import main
from acoustic_sim.config import ConfigError, SimConfig, SonarConfig
from acoustic_sim.datasets import folder
from acoustic_sim.datasets.plan import Episode, ShardTask, check_shard_memory, plan
from acoustic_sim.datasets.shards import DatasetError, ShardFrames, dataset_shards, write_shard
from acoustic_sim.datasets.suites import SUITES, load_suite
from acoustic_sim.settings import apply_settings
from clitools.limits import SizeError

from .crafted import sigint_as_from_a_terminal

ROOT = Path(__file__).resolve().parents[1]
MB = 10**6


@pytest.fixture
def small_memory(monkeypatch):
    """This machine as one with 100 MB of memory free, so that files and claims of a few MB are
    "too large" here and a defect that read them anyway would read a few MB, not the machine."""
    from clitools import limits

    monkeypatch.setattr(limits, "_read_available_memory", lambda: 100 * MB)
    monkeypatch.setattr(limits, "_MEMORY_READ", [-1.0, 0.0])  # read again now, and after the test


@contextlib.contextmanager
def deadline(seconds: float = 20.0):
    """Raise TimeoutError in this thread after `seconds` (a blocked open() of a FIFO is
    interrupted too), so that a defect fails the test instead of hanging the suite."""

    def expire(*_):
        raise TimeoutError(f"still running after {seconds} s: the input was read, not refused")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "Traceback" not in err, err
    return err


# ------------------------------------------------------------------------------ crafted inputs


def chirp_file(path: Path, *, pings=2, samples=2048, dtype=np.float32, rate=450e3, claim=False, lidar=True, move=None):
    """A small CHIRP recording as the format's reader reads it: the eRTIS array sampled at `rate`,
    `pings` pings of `samples` samples (with `claim`, a chunked dataset of that shape with no data
    written: a header claiming pings, 13 KB on disk), optionally a LiDAR seeing one point 2 m
    ahead with the calibration `move` (4x4)."""
    with h5py.File(path, "w") as f:
        f.attrs.update(format="chirp", format_version="2.1", reference_sensor="acoustic_sensor_00")
        f.attrs["n_reference_captures"] = pings
        sonar = f.create_group("sensors/acoustic_sensor_00")
        sonar.attrs.update(sensor_type="acoustic_sensor", sync_mode="reference_capture", reference_frame="origin")
        sonar.attrs.update(sample_rate_hz=rate, num_channels=32)
        sonar["calibration/to_origin"] = np.eye(4)
        sonar["calibration/receiver_relative_translations"] = np.asarray(SonarConfig.ertis().microphones_m)
        if claim:
            sonar.create_dataset("data/signals", (pings, samples, 32), dtype, chunks=(1, samples, 32))
            sonar.create_dataset("data/timestamps", (pings,), np.float64, chunks=(1024,))
        else:
            sonar["data/signals"] = np.zeros((pings, samples, 32), dtype)
            sonar["data/timestamps"] = 1.7e9 + 0.1 * np.arange(pings)
        if lidar:
            scanner = f.create_group("sensors/lidar_00")
            scanner.attrs.update(sensor_type="lidar", sync_mode="reference_capture", reference_frame="origin")
            scanner["calibration/to_origin"] = np.eye(4) if move is None else move
            scanner["data/timestamps"] = 1.7e9 + 0.1 * np.arange(pings)
            scanner["data/points"] = np.tile(np.array([[[2.0, 0.0, 0.0, 1.0]]], np.float32), (pings, 1, 1))
            scanner["data/point_counts"] = np.ones(pings, np.int32)
    return path


def tiny_shard(path: Path) -> Path:
    """A valid two-frame shard of a small grid, written by the shard writer (nothing simulated)."""
    grid = dataclasses.replace(SimConfig().processing.grid, range_max_m=0.3, azimuth_min_deg=-2, azimuth_max_deg=2)
    shape = (2, *grid.shape)
    frames = ShardFrames(
        energyscape=[np.ones(shape)],
        lidar_ranges=[np.full((2, 5), 1.0)],
        lidar_image=[np.zeros(shape)],
        pose=[np.tile(np.eye(4), (2, 1, 1))],
        time=[np.arange(2) * 0.1],
        episode=[np.zeros(2)],
        scenario=[np.zeros(2)],
    )
    attrs = {"plan_id": "x", "config": {"sim": SimConfig().to_dict()}, "episodes": [{"index": 0}], "scenarios": ["a"]}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_shard(path, frames, attrs=attrs, range_m=grid.range_m, azimuth_rad=grid.azimuth_rad)
    return path


@pytest.fixture(scope="module")
def crafted(tmp_path_factory) -> dict[str, Path]:
    """Every bad input of the subprocess cases, made once."""
    tmp = tmp_path_factory.mktemp("faults")
    made = {"tmp": tmp}
    for name in ("plan.svg", "suite.toml", "ping.bin", "rec.h5"):
        os.mkfifo(tmp / f"fifo-{name}")
        made[f"fifo_{name.split('.')[1]}"] = tmp / f"fifo-{name}"
    (tmp / "random.stl").symlink_to("/dev/urandom")
    made["urandom_stl"] = tmp / "random.stl"
    texts = {
        "huge.toml": 'base = "tiny"\nframes = 1e12\n',
        "deep.json": '{"base": "tiny", "settings": ' + "[" * 100_000 + "]" * 100_000 + "}",
        "typo.toml": 'base = "tiny"\nframes = "many"\n',
    }
    for name, text in texts.items():
        (tmp / name).write_text(text)
        made[name.replace(".", "_")] = tmp / name
    (tmp / "listed").mkdir()
    (tmp / "listed" / "plan.json").write_text("[1, 2]")
    made["listed"] = tmp / "listed"
    return made


# ------------------------------------------------------------------------------ the CLI, as a user runs it

# (id, argv with {placeholders}, words the one error line must contain): as subprocesses, the way a
# user meets them (a hang is killed after a minute and fails its case)
CASES = [
    ("svg-fifo", "render --svg {fifo_svg} --out {tmp}/a.png", "is a FIFO"),
    ("mesh-urandom", "render --mesh {urandom_stl} --out {tmp}/b.png", "character device (the symlink leads to"),
    ("chirp-fifo", "import {fifo_h5} --format chirp --out {tmp}/c1", "is a FIFO"),
    ("frames-1e9", "generate --suite tiny --out {tmp}/g2 --frames 1000000000", "free on the disk of"),
    ("record-samples", "render --sonar --set sonar.record_samples=1e12 --out {tmp}/c.png", "record_samples"),
    ("suite-deep", "generate --suite {deep_json} --out {tmp}/g4", "nests lists or tables deeper"),
]
# The same through `main` in this process (its modules loaded once): the one-line path is the same.
IN_PROCESS = [
    ("suite-fifo", "generate --suite {fifo_toml} --out {tmp}/g1", "is a FIFO"),
    ("pdm-fifo", "import {fifo_bin} --format pdm --out {tmp}/p.npy", "is a FIFO"),
    ("suite-frames-1e12", "generate --suite {huge_toml} --out {tmp}/g3", "1,000,000,000,000 frames"),
    ("rays", "render --sonar --rays 1000000000000 --out {tmp}/d.png", "ray_count 1,000,000,000,000"),
    ("suite-type", "generate --suite {typo_toml} --out {tmp}/g5", "typo.toml: frames must be a whole number"),
    ("plan-list", "generate --suite tiny --out {listed}", "plan.json holds a JSON list"),
]
NOT_MADE = ("g1", "g2", "g3", "g4", "g5", "c1", "p.npy")


@pytest.fixture(scope="module")
def cli_results(crafted) -> dict[str, subprocess.CompletedProcess]:
    def run(case):
        argv = case[1].format(**crafted).split()
        command = [sys.executable, "-m", "acoustic_sim", *argv]
        try:
            return case[0], subprocess.run(command, capture_output=True, text=True, timeout=60, cwd=ROOT)
        except subprocess.TimeoutExpired as err:  # a hang is the defect: report it as the result
            return case[0], subprocess.CompletedProcess(command, -1, "", f"timed out: {err}")

    with ThreadPoolExecutor(3) as pool:
        return dict(pool.map(run, CASES))


@pytest.mark.parametrize(("case", "argv", "words"), CASES, ids=[c[0] for c in CASES])
def test_cli_refuses_in_one_line(case, argv, words, cli_results, crafted):
    """Exit code 2, one `error:` line with the words, no traceback, and no output made."""
    done = cli_results[case]
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and words in lines[0], done.stderr[-2000:]
    assert not [made for made in NOT_MADE if (crafted["tmp"] / made).exists()]


@pytest.mark.parametrize(("case", "argv", "words"), IN_PROCESS, ids=[c[0] for c in IN_PROCESS])
def test_main_refuses_in_one_line(case, argv, words, crafted, capsys):
    with deadline():
        assert main(argv.format(**crafted).split()) == 2
    assert words in one_error_line(capsys)
    assert not [made for made in NOT_MADE if (crafted["tmp"] / made).exists()]
    assert sorted(p.name for p in crafted["listed"].iterdir()) == ["plan.json"]


def test_ctrl_c_in_generate_stops_the_workers_and_keeps_the_folder_resumable(tmp_path):
    """SIGINT to the process group (what a terminal's Ctrl-C sends) once a shard is written: one
    line, exit code 130, the workers gone, no lock, no half-written shard, plan.json and the
    finished shards kept."""
    out = tmp_path / "data"
    cheap = [
        "sonar.record_samples=2048",
        "tracer.ray_count=300",
        "tracer.max_bounces=0",
        "processing.grid.range_max_m=2",
    ]
    argv = ["generate", "--suite", "tiny", "--frames", "96", "--shards", "12", "--workers", "2", "--out", str(out)]
    argv += [item for setting in cheap for item in ("--set", setting)] + ["--quiet", "--device", "cpu"]
    process = subprocess.Popen(
        [sys.executable, "-m", "acoustic_sim", *argv],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group, as a shell gives a command
        preexec_fn=sigint_as_from_a_terminal,
    )
    try:
        for _ in range(1200):  # until the first shard has its final name (at most 2 min)
            if list(out.glob("shard-*.h5")) or process.poll() is not None:
                break
            time.sleep(0.1)
        assert process.poll() is None, "generate ended before it could be interrupted"
        os.killpg(process.pid, signal.SIGINT)
        _, err = process.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    lines = err.strip().splitlines()
    assert process.returncode == 130 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"interrupted: {out} keeps") and "the same command resumes it" in lines[0]
    with pytest.raises(ProcessLookupError):  # no worker of the group is left
        os.killpg(process.pid, 0)
    names = sorted(p.name for p in out.iterdir())
    assert "plan.json" in names and folder.LOCK_FILE not in names and not [n for n in names if n.endswith(".tmp")]
    assert 1 <= len([n for n in names if n.startswith("shard-")]) < 12


def sleeping_work(tasks, device, on_frames) -> dict:
    """A worker's share that takes half a minute (a long shard on a CPU)."""
    time.sleep(30)
    return {}


def test_interrupted_workers_are_stopped_at_once_not_after_their_shard(monkeypatch):
    """Ctrl-C closes the pool with now=True: the workers, each half a minute from the end of
    its share, are gone within the 15 s deadline (without it, closing waits for them)."""
    import multiprocessing

    from acoustic_sim.datasets import workers

    if workers.start_method() != "fork":
        pytest.skip("this process has started CUDA: its workers cannot be forked")
    pool = workers.LocalWorkers("cpu", 2, sleeping_work)
    try:
        pool.wait_ready()
        with deadline(15):
            pool.close(abort=True, now=True)
        assert not multiprocessing.active_children()
    finally:
        for child in multiprocessing.active_children():
            child.kill()


# ------------------------------------------------------------------------------ sizes


@pytest.mark.parametrize(
    ("setting", "field"),
    [
        ("sonar.record_samples=1e12", "SonarConfig.record_samples"),
        ("tracer.ray_count=1e12", "TracerConfig.ray_count"),
        ("tracer.table_size=1099511627776", "table_size 1,099,511,627,776"),
        ("processing.grid.range_bin_m=1e-9", "PolarGrid of 4,800,000,000 x 181 cells"),
        ("lidar.azimuth_count=1e12", "LidarConfig.azimuth_count"),
        ("sonar.chirp.duration_s=1e6", "ChirpConfig.duration_s"),
    ],
)
def test_a_config_beyond_this_machine_is_refused_with_the_figures(setting, field):
    """The config's own check, before anything is allocated: the estimate (TB) and what is free."""
    with pytest.raises(ConfigError, match="memory free on this machine") as refused:
        apply_settings(SimConfig(), [setting])
    assert field in str(refused.value) and " TB, more than the " in str(refused.value)


def test_a_shard_too_large_for_memory_and_a_scan_too_long_are_refused(capsys):
    """A shard of ten million frames (a claim: no frame exists), and --frames beyond what one
    scan array can index (render refuses before it builds the drive)."""
    episode = Episode(0, 0, "room", "box_room", {}, 10_000_000, 1)
    task = ShardTask("x/shard-00000.h5", "", 0, "id", 0, {"name": "tiny"}, {}, (episode,))
    with pytest.raises(SizeError, match=r"filling shards of up to 10,000,000 frames .* give more --shards"):
        check_shard_memory([task], 1)
    with deadline():
        assert main(["render", "--frames", "3000000", "--out", "unused.png"]) == 2
    assert "3,000,000 frames x 1,081 LiDAR beams exceeds" in one_error_line(capsys)


def test_frames_beyond_the_disk_are_refused_before_episodes_are_planned(tmp_path, monkeypatch):
    """The plan compares the shards' least size with the disk's free space first (ten million
    episodes are never planned): with 1 MB free, 100 frames of ~46 KB do not fit."""
    from acoustic_sim.datasets import plan as planning

    monkeypatch.setattr(planning, "free_disk_bytes", lambda path: 1_000_000)
    monkeypatch.setattr(planning, "plan_episodes", lambda *a: pytest.fail("planned before the size was checked"))
    with pytest.raises(SizeError, match=r"100 frames \(1 variant, 4\d KB a frame or more\) needs 4\.\d MB, more than"):
        plan(SUITES["tiny"], tmp_path / "out", frames=100)
    assert not (tmp_path / "out").exists()


def sparse(path: Path, size: int) -> Path:
    """A file of `size` bytes of which no block is written (it takes no disk)."""
    with open(path, "wb") as f:
        f.truncate(size)
    return path


@pytest.mark.parametrize(
    ("name", "read", "limit"),
    [
        ("plan.svg", scenes.from_svg, "666.7 KB"),  # 150 bytes of memory a byte of SVG
        ("mesh.obj", scenes.from_mesh, "3.1 MB"),  # 32 a byte of mesh
        ("suite.toml", load_suite, "1.0 MB"),  # a suite is kilobytes, whatever the memory
    ],
)
def test_a_file_larger_than_its_kind_is_refused_unread(name, read, limit, tmp_path, small_memory):
    """A 4 MB (sparse) SVG, mesh or suite file with 100 MB free: refused by its size before it
    is opened (read, such a file takes 150 or 32 times its size: /dev/urandom behind an SVG's
    name took 24 GB before it was killed)."""
    path = sparse(tmp_path / name, 4 * MB)
    with deadline(), pytest.raises(ValueError, match=rf"holds 4\.0 MB, over the limit of {limit} for its kind"):
        read(str(path))


def test_pdm_recordings_beyond_memory_are_refused_unread(tmp_path, capsys, small_memory):
    """2 MB of PDM with 100 MB free: the words, 64 bytes a byte to decode them, and a float32
    energyscape of 240 x 181: 2 + 128 + 0.17 MB."""
    path = sparse(tmp_path / "ping.bin", 2 * MB)
    with deadline():
        assert main(["import", str(path), "--format", "pdm", "--out", str(tmp_path / "rec.npy")]) == 2
    assert "1 PDM file(s) of 2.0 MB (1 ping(s)) needs 130.2 MB, more than the 100.0 MB" in one_error_line(capsys)
    assert not (tmp_path / "rec.npy").exists()


def test_svg_walls_are_built_at_once_and_equal_the_boxes_one_by_one():
    """The walls of a 60-point random polyline, made at once, are the boxes `box_mesh` makes one
    by one (vertices to 1e-12 m, faces in order), so a plan of 100k points builds in seconds."""
    from scenes.scene import box_mesh
    from scenes.svg import _wall_boxes

    rng = np.random.default_rng(0)
    ends = rng.uniform(0, 10, (60, 2, 2))
    got = _wall_boxes(ends, 0.1, 2.5)
    parts = []
    for a, b in ends:
        length, yaw = float(np.linalg.norm(b - a)), float(np.arctan2(*(b - a)[::-1]))
        parts.append(box_mesh((*(a + b) / 2, 1.25), (length + 0.1, 0.1, 2.5), yaw))
    np.testing.assert_allclose(got.triangles, np.concatenate([p.triangles for p in parts]), atol=1e-12)


def _reference_place(placer, radius, *, wall_gap=None, passage=None, tries=200):
    """The placer's search as it was written first: one spot drawn and checked at a time."""
    passage = placer.passage if passage is None else passage
    wall_gap = passage if wall_gap is None else wall_gap
    lo, hi = radius + wall_gap, placer.size[:2] - radius - wall_gap
    if (hi > lo).all():
        for _ in range(tries):
            x, y = placer.rng.uniform(lo, hi)
            if all(np.hypot(x - px, y - py) > radius + pr + min(passage, pp) for px, py, pr, pp in placer.placed):
                placer.placed.append((x, y, radius, passage))
                return float(x), float(y)
    placer.skipped += 1
    return None


@pytest.mark.parametrize("builder", ["random_world", "office"])
def test_crowded_rooms_place_objects_as_one_by_one_and_say_what_did_not_fit(builder, monkeypatch):
    """Seeded crowded rooms are identical, mesh for mesh, to the one-by-one search (the same
    draws, the same spots); 20,000 walls asked of a 10 m room warn about those left out."""
    from scenes import builders

    cases = {
        "random_world": dict(size=(5.0, 5.0, 2.5), wall_count=12, cylinder_count=40),
        "office": dict(size=(4.0, 4.0, 3.0), clutter="high"),
    }[builder]
    build = getattr(scenes, builder)
    with pytest.warns(UserWarning, match="did not fit"):
        got = [build(seed=seed, **cases).mesh for seed in range(3)]
    monkeypatch.setattr(builders._Placer, "place", _reference_place)
    with pytest.warns(UserWarning, match="did not fit"):
        want = [build(seed=seed, **cases).mesh for seed in range(3)]
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    if builder == "random_world":
        monkeypatch.undo()
        with pytest.warns(UserWarning, match=r"random_world: 19\d{3} objects did not fit"):
            scenes.random_world(wall_count=20_000, cylinder_count=0)


# ------------------------------------------------------------------------------ suite, plan and shard files


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('base = "tiny"\ndt_s = "fast"\n', "dt_s must be a number"),
        ('base = "tiny"\nspeed_m_s = [0.2, "x"]\n', "speed_m_s must be a number or [low, high]"),
        ('base = "tiny"\n[physics]\nsnr_db = "abc"\n', "physics.snr_db must be a number or [low, high]"),
        ('base = "tiny"\n[physics]\nmax_bounces = "abc"\n', "physics.max_bounces"),
        ('base = "tiny"\n[physics]\nbounces = 2\n', "unknown physics fields ['bounces']"),
        ('base = "tiny"\nvariants = 3\n', "variants must be a table of tables"),
        ('base = "tiny"\nscenarios = 3\n', "scenarios must be a list of tables"),
        ('base = "tiny"\n[[scenarios]]\nname = "a"\n', "scenarios[0]: give its builder"),
        ('base = "tiny"\n[[scenarios]]\nname = "a"\nbuilder = "office"\nweight = "x"\n', "weight must be a number"),
        ('base = "nope"\n', "base 'nope' is not a suite"),
        ('base = "tiny"\nsettings = "lidar=x"\n', "settings must be a list of strings"),
        ("x = " + "[" * 50_000 + "]" * 50_000 + "\n", "nests lists or tables deeper"),
    ],
)
def test_suite_file_errors_name_the_file_and_the_field(text, words, tmp_path):
    path = tmp_path / "my_suite.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as refused:
        load_suite(path)
    assert words in str(refused.value) and "my_suite.toml" in str(refused.value), refused.value


def test_a_json_suite_that_is_a_list_and_a_fifo_are_refused(tmp_path):
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"list\.json holds a list, not a table of suite fields"):
        load_suite(tmp_path / "list.json")
    os.mkfifo(tmp_path / "pipe.toml")
    with deadline(), pytest.raises(ValueError, match="is a FIFO"):
        load_suite(tmp_path / "pipe.toml")


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ('"a string"', "holds a JSON str, not a plan"),
        ("[1, 2]", "holds a JSON list, not a plan"),
        ('{"format": ', "is not valid JSON"),
        ('{"format": "other"}', "is not a sonar2lidar-dataset plan"),
        (None, "is a FIFO"),
    ],
)
def test_a_plan_json_that_is_not_a_plan_is_refused_naming_it(content, words, tmp_path):
    path = tmp_path / folder.PLAN_FILE
    os.mkfifo(path) if content is None else path.write_text(content)
    with deadline(), pytest.raises(DatasetError) as refused:
        folder.read_plan(path)
    assert words in str(refused.value) and str(path) in str(refused.value) and "--out" in str(refused.value)


def test_a_refused_run_leaves_no_plan_and_names_the_scenario(tmp_path, device):
    """A scenario whose room has no room to drive: found while the first episode is prepared,
    after plan.json was written; the error names suite and scenario, and the folder it made is
    gone again (a rerun with other settings is not locked out)."""
    import dataclasses as dc

    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import Scenario

    tiny = SUITES["tiny"]
    cramped = Scenario(name="closet", builder="box_room", params={"size": [0.6, 0.6, 0.6]})
    suite = dc.replace(tiny, name="cramped", scenarios=(cramped,))
    out = tmp_path / "data"
    with pytest.raises(ValueError, match=r"suite 'cramped', scenario 'closet' \(episode 0\): no drive of 8 frames"):
        generate(suite, out, frames=8, device=device, progress=False)
    assert not out.exists()
    wrong = dc.replace(tiny, scenarios=(dc.replace(cramped, params={"size": "big"}),))
    with pytest.raises(ValueError, match=r"suite 'tiny', scenario 'closet': box_room\(\{'size': 'big'\}\) refused"):
        generate(wrong, out, frames=8, device=device, progress=False)
    assert not out.exists()


def test_ray_address_without_ray_is_refused_before_anything_is_written(tmp_path, capsys, monkeypatch):
    from acoustic_sim.datasets import generate

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, as without the extra
    monkeypatch.setattr(generate, "check_plan_file", lambda *a: pytest.fail("plan.json written before Ray was"))
    out = tmp_path / "data"
    assert main(["generate", "--suite", "tiny", "--out", str(out), "--ray-address", "auto", "--quiet"]) == 2
    assert "--ray-address needs Ray (the `ray` extra)" in one_error_line(capsys) and not out.exists()


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        ("foreign", "is not a sonar2lidar-dataset shard (format attribute 'chirp')"),
        ("garbage", "is not a readable HDF5 file"),
        ("no-time", "missing ['time']"),
        ("bad-config", "its `config` attribute is not valid JSON"),
        ("fifo", "is a FIFO"),
    ],
)
def test_export_refuses_a_damaged_or_foreign_shard_naming_it(damage, words, tmp_path, capsys):
    data = tmp_path / "data"
    good = tiny_shard(data / "shard-00000.h5")
    assert dataset_shards(data) == [good]  # the shard as written passes
    bad = data / "shard-00001.h5"
    if damage == "foreign":
        chirp_file(bad, lidar=False)
    elif damage == "garbage":
        bad.write_text("not hdf5")
    elif damage == "fifo":
        os.mkfifo(bad)
    else:
        tiny_shard(bad)
        with h5py.File(bad, "a") as f:
            if damage == "no-time":
                del f["time"]
            else:
                f.attrs["config"] = "{broken"
    with deadline():
        assert main(["export", str(data), "--format", "mcap", "--out", str(tmp_path / "x.mcap")]) == 2
    line = one_error_line(capsys)
    assert words in line and str(bad) in line and not (tmp_path / "x.mcap").exists()


# ------------------------------------------------------------------------------ CHIRP import


def _broken(path):
    return chirp_file(path, move=np.full((4, 4), np.nan))


def _linked(path, kind):
    source = chirp_file(path.with_name("source.h5"))
    chirp_file(path)
    with h5py.File(path, "a") as f:
        if kind == "link":
            del f["sensors/lidar_00"]
            f["sensors/lidar_00"] = h5py.ExternalLink(str(source), "sensors/lidar_00")
            return path
        data = f["sensors/acoustic_sensor_00/data"]
        del data["timestamps"]
        if kind == "external":
            data.create_dataset("timestamps", (2,), np.float64, external=[("/etc/hostname", 0, 16)])
        else:
            layout = h5py.VirtualLayout(shape=(2,), dtype=np.float64)
            layout[:] = h5py.VirtualSource(str(source), "sensors/lidar_00/data/timestamps", shape=(2,))
            data.create_virtual_dataset("timestamps", layout)
    return path


CHIRP_CASES = {
    "complex": (lambda p: chirp_file(p, dtype=np.complex64), "signals are complex (complex64)"),
    "nan-rate": (lambda p: chirp_file(p, rate=float("nan")), "sample_rate_hz is nan"),
    "word-rate": (lambda p: chirp_file(p, rate="fast"), "sample_rate_hz is 'fast'"),
    "no-pings": (lambda p: chirp_file(p, pings=0), "holds no pings"),
    "broken-transform": (_broken, "is not a finite rigid transform"),
    "claimed-pings": (  # with 100 MB free: 100,000 pings need 13 GB for their energyscapes and labels
        lambda p: chirp_file(p, pings=100_000, claim=True, lidar=False),
        "100,000 pings of 2,048 samples x 32 channels needs",
    ),
    "external-dataset": (lambda p: _linked(p, "external"), "is an external dataset reading /etc/hostname"),
    "virtual-dataset": (lambda p: _linked(p, "virtual"), "is a virtual dataset reading"),
    "external-link": (lambda p: _linked(p, "link"), "is an external link to"),
}


@pytest.mark.parametrize("case", list(CHIRP_CASES))
def test_chirp_import_refuses_what_it_cannot_import_truthfully(case, tmp_path, capsys, small_memory):
    pytest.importorskip("chirppy")
    make, words = CHIRP_CASES[case]
    path = make(tmp_path / "rec.h5")
    out = tmp_path / "imported"
    with deadline():
        assert main(["import", str(path), "--format", "chirp", "--out", str(out)]) == 2
    line = one_error_line(capsys)
    assert words in line and str(path) in line and not out.exists(), line


def test_the_crafted_recording_passes_every_check(tmp_path):
    """The control: the same file with real signals, a rate and one LiDAR point passes the
    checks the refusals above come from."""
    chirppy = pytest.importorskip("chirppy")
    from acoustic_sim.formats import chirp_input

    path = chirp_file(tmp_path / "rec.h5")
    chirp_input.check_file(path)
    with chirppy.CHIRPDataset(path) as data:
        acoustic, mics, rate = chirp_input.microphones(data, 450e3, path)
        chirp_input.check_room(acoustic.signals.shape, SimConfig(), tmp_path / "out", path, block=64)
        assert rate == 450e3 and mics.shape == (32, 3) and len(chirp_input.ping_stamps(acoustic, path)) == 2


def test_bad_mesh_and_svg_files_are_named(tmp_path):
    (tmp_path / "broken.obj").write_text("v 1 2\nf 1 2 3\n")
    with pytest.raises(scenes.SceneError, match=r"broken\.obj \(trimesh: IndexError"):
        scenes.from_mesh(tmp_path / "broken.obj")
    (tmp_path / "empty.stl").write_text("solid x\nendsolid x\n")
    with pytest.raises(scenes.SceneError, match=r"empty\.stl holds no faces"):
        scenes.from_mesh(tmp_path / "empty.stl")
    (tmp_path / "cut.svg").write_text('<svg><line x1="0"')
    with pytest.raises(scenes.SceneError, match=r"could not parse SVG .*cut\.svg: unclosed token"):
        scenes.from_svg(str(tmp_path / "cut.svg"))


def test_a_builder_argument_of_the_wrong_type_is_named(capsys):
    with deadline():
        assert main(["render", "--scene", "box_room", "--scene-arg", "size=abc", "--out", "unused.png"]) == 2
    assert 'size="abc": size must be three finite numbers' in one_error_line(capsys)
