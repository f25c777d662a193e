"""The simulator's command line under a second fault probe (issue 38, round two): the cases it
found that ended in a trace, a vague or misleading line, a silent wrong result or mixed data, as
a user meets them.

Each case runs `python -m acoustic_sim ...` in a process of its own (tests/cli_runner.py forks
them from one interpreter that made the heavy imports once), in two rounds of a module fixture:
the first generates a small dataset with the same command line, the second runs every case on
copies of it and on crafted files. A refused case ends with exit code 2 and one `error:` line
naming the file, field or option (no traceback); an accepted case checks what it wrote.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from .cli_runner import run_commands
from .crafted import ctrl_c_after
from .test_sim_input_faults import chirp_file, tiny_shard

ROOT = Path(__file__).resolve().parents[1]
CHEAP = "--quiet --device cpu --set tracer.ray_count=300 --set sonar.record_samples=4096"
RUN = f"generate --suite tiny --frames 16 --shards 2 {CHEAP} --out"  # two shards of one 8-frame drive each
RENDER = "render --scene box_room --frames 5"

# (id, argv with {placeholders}, words the one error line must contain)
REFUSED = [
    # a drive whose step outgrows the scene, or is not finite: was an IndexError's trace
    ("speed-beyond-scene", f"{RENDER} --speed 1e9 --out {{tmp}}/a.png", "longer than any route"),
    ("dt-inf", f"{RENDER} --dt inf --out {{tmp}}/a.png", "must be finite"),
    ("suite-dt-beyond-scene", f"generate --suite {{dt_huge}} {CHEAP} --out {{tmp}}/g1", "longer than any route"),
    # import's numeric options: were a trace (inf, 0), numpy's words, or misleading advice
    ("pdm-rate-inf", "import {ping} --format pdm --pdm-rate inf --out {tmp}/r.npy", "--pdm-rate inf"),
    ("pdm-rate-negative", "import {ping} --format pdm --pdm-rate=-4.5e6 --out {tmp}/r.npy", "--pdm-rate -4500000"),
    ("pdm-ping-zero", "import {ping} --format pdm --samples-per-ping 0 --out {tmp}/r.npy", "--samples-per-ping 0"),
    ("pdm-channels", "import {ping} --format pdm --channels 7 --out {tmp}/r.npy", "multiple of 8"),
    ("chirp-gap-nan", "import {rec} --format chirp --episode-gap nan --out {tmp}/c1", "--episode-gap nan"),
    ("chirp-tolerance", "import {rec} --format chirp --plane-tolerance -1 --out {tmp}/c2", "--plane-tolerance -1"),
    # seeds numpy or HDF5 cannot take: were numpy's or h5py's words
    ("seed-negative", f"generate --suite tiny --frames 4 {CHEAP} --seed -1 --out {{tmp}}/g2", "seed must lie in"),
    ("seed-beyond-int64", f"{RENDER} --seed 1180591620717411303424 --out {{tmp}}/a.png", "--seed must lie in"),
    # settings that leave nothing to compute: were h5py's, numpy's or the beamformer's words
    ("grid-without-bins", f"{RENDER} --set processing.grid.range_bin_m=10 --out {{tmp}}/a.png", "no range bin"),
    ("emitter-beyond-record", f"{RENDER} --set sonar.emitter_m=[1e9,0,0] --out {{tmp}}/a.png", "no echo could arrive"),
    ("call-of-one-sample", f"{RENDER} --set sonar.chirp.duration_s=1e-12 --out {{tmp}}/a.png", "1 sample"),
    ("array-at-a-point", f"{RENDER} --set sonar.microphones_m=[[0,0,0],[0,0,0]] --out {{tmp}}/a.png", "one point"),
    (
        "record-shorter",
        f"{RENDER} --set sonar.record_samples=100 --out {{tmp}}/a.png",
        "record_samples 100 < the call's",
    ),
    (
        "sonar-elevations",
        f"{RENDER} --sonar --rays 300 --set processing.elevation_deg=[0,10] --out {{tmp}}/a.png",
        "one angle",
    ),
    # CHIRP recordings: were unnamed lines, a trace, or silently NaN poses and a deaf array
    ("chirp-short", "import {short} --format chirp --out {tmp}/c3", "short.h5: acoustic_sensor_00: its pings hold 10"),
    ("chirp-nan-signals", "import {nan_signals} --format chirp --out {tmp}/c4", "nan_signals.h5: acoustic_sensor_00"),
    ("chirp-one-point", "import {one_point} --format chirp --out {tmp}/c5", "one_point.h5: acoustic_sensor_00"),
    ("chirp-lidar-short", "import {lidar_short} --format chirp --out {tmp}/c6", "lidar_00 has no whole capture"),
    ("chirp-odometry-nan", "import {odometry_nan} --format chirp --out {tmp}/c7", "odometry_00's pose at ping 0"),
    ("chirp-quaternion-0", "import {quaternion_0} --format chirp --out {tmp}/c8", "non-zero quaternion"),
    # exports: a new shard inside the dataset, repeated or damaged shards, a suite's variants
    ("export-into-dataset", "export {flat} --format mcap --out {flat}/x.mcap", "lies inside the dataset"),
    ("export-shard-twice", "export {twice} --format mcap --out {tmp}/x.mcap", "repeats shard-00000.h5"),
    ("export-two-runs", "export {two_runs} --format mcap --out {tmp}/y.mcap", "shards of 2 runs"),
    ("export-nan-pose", "export {nan_pose} --format mcap --out {tmp}/z.mcap", "pose of frame 1 is not finite"),
    (
        "export-signal-shape",
        "export {few_mics} --format chirp --out {tmp}/x.h5",
        "signals of shape (2, 5, 16384)",
    ),
    ("export-variants", "export {variants} --format mcap --out {tmp}/v.mcap", "its variants (bounces_0)"),
    # generate's folder: were errno lines, a misleading plan, or a stranger shard left to mix in
    ("lock-is-folder", f"{RUN} {{lock_dir}}", "in the way of generate's lock"),
    ("out-dangling-link", f"{RUN} {{dangling}}", "which does not exist"),
    ("shard-linked-twice", f"{RUN} {{linked}}", "holds shard 0 of this run"),
    ("shard-stranger", f"{RUN} {{stranger}}", "shard-00007.h5, which this run's"),
    ("shard-truncated", f"{RUN} {{truncated}}", "move it away and rerun"),
    # suite values: were a 600-digit line, a garbled field name, NaN shares
    ("suite-frames-1e300", f"generate --suite {{frames_huge}} {CHEAP} --out {{tmp}}/g3", "up to 2**63 - 1"),
    (
        "suite-speed-inverted",
        f"generate --suite {{speed_inverted}} {CHEAP} --out {{tmp}}/g4",
        "low <= high, got [1.0, 0.1]",
    ),
    ("suite-weight-inf", f"generate --suite {{weight_inf}} {CHEAP} --out {{tmp}}/g5", "finite number > 0"),
    (
        "suite-vary-nan",
        f"generate --suite {{vary_nan}} {CHEAP} --out {{tmp}}/g6",
        "vary.size: expected [low, high] of finite",
    ),
    # render's own options: were matplotlib's words after all the work, or silently ignored
    ("render-out-suffix", f"{RENDER} --out {{tmp}}/a.txt", ".txt is no picture format"),
    ("svg-unknown-arg", "render --svg {svg} --scene-arg height=3 --out {tmp}/a.png", "help(scenes.from_svg)"),
    ("scene-arg-seed", f"{RENDER} --scene-arg seed=abc --out {{tmp}}/a.png", "give the seed with --seed"),
    ("crossengine-variants", "generate --suite crossengine --variants x --out {tmp}/g7", "--variants does not apply"),
    ("crossengine-frames-0", "generate --suite crossengine --frames 0 --out {tmp}/g8", "frames and episode_frames"),
]
NOT_MADE = ["g1", "g2", "g3", "g4", "g5", "g6", "g7", "g8", "a.png", "a.txt", "r.npy", "x.mcap", "x.h5"]
NOT_MADE += [f"c{i}" for i in range(1, 9)]


def _suite_files(tmp: Path) -> dict[str, Path]:
    scenario = '[[scenarios]]\nname = "a"\nbuilder = "box_room"\n'
    texts = {
        "dt_huge": 'base = "tiny"\ndt_s = 1e300\nframes = 4\nepisode_frames = 4\n',
        "frames_huge": '{"base": "tiny", "frames": 1e300}',
        "speed_inverted": 'base = "tiny"\nspeed_m_s = [1.0, 0.1]\n',
        "weight_inf": f'base = "tiny"\n{scenario}weight = inf\n[[scenarios]]\nname = "b"\nbuilder = "corridor"\n',
        "vary_nan": f'base = "tiny"\n{scenario}[scenarios.vary]\nsize = [[4, nan], 4, 3]\n',
    }
    files = {}
    for name, text in texts.items():
        files[name] = tmp / (f"{name}.json" if text.startswith("{") else f"{name}.toml")
        files[name].write_text(text)
    return files


def _odometry(path: Path, *, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0)) -> Path:
    """A two-ping CHIRP recording (`chirp_file`) with an odometry sensor giving each ping the
    pose `position`, `orientation` (x, y, z, w), and the base_link transform."""
    chirp_file(path)
    with h5py.File(path, "a") as f:
        odometry = f.create_group("sensors/odometry_00")
        odometry.attrs.update(sensor_type="odometry", sync_mode="reference_capture", reference_frame="origin")
        odometry["calibration/to_origin"] = np.eye(4)
        odometry["data/timestamps"] = 1.7e9 + 0.1 * np.arange(2)
        odometry["data/position"] = np.tile(position, (2, 1))
        odometry["data/orientation"] = np.tile(orientation, (2, 1))
        odometry["data/yaw"] = np.zeros(2)
        for name in ("linear_velocity", "angular_velocity"):
            odometry[f"data/{name}"] = np.zeros((2, 3))
        for name in ("pose_covariance", "twist_covariance"):
            odometry[f"data/{name}"] = np.zeros((2, 6, 6))
        f["transforms/base_link_to_origin"] = np.eye(4)
    return path


def _edit(path: Path, name: str, value) -> Path:
    with h5py.File(path, "a") as f:
        del f[name]
        f[name] = value
    return path


def _recordings(tmp: Path) -> dict[str, Path]:
    """Raw PDM words and CHIRP recordings, good and crafted (two pings of 2,048 samples)."""
    acoustic = "sensors/acoustic_sensor_00"
    np.random.default_rng(0).integers(0, 2**32, 30_000, dtype=np.uint32).tofile(tmp / "ping.bin")
    made = {"ping": tmp / "ping.bin", "rec": chirp_file(tmp / "rec.h5")}
    made["short"] = chirp_file(tmp / "short.h5", samples=10)
    made["nan_signals"] = _edit(
        chirp_file(tmp / "nan_signals.h5"), f"{acoustic}/data/signals", np.full((2, 2048, 32), np.nan)
    )
    made["one_point"] = _edit(
        chirp_file(tmp / "one_point.h5"), f"{acoustic}/calibration/receiver_relative_translations", np.zeros((32, 3))
    )
    made["lidar_short"] = chirp_file(tmp / "lidar_short.h5")
    for name in ("timestamps", "points", "point_counts"):
        with h5py.File(made["lidar_short"], "r") as f:
            first = f[f"sensors/lidar_00/data/{name}"][:1]
        _edit(made["lidar_short"], f"sensors/lidar_00/data/{name}", first)
    made["odometry_nan"] = _odometry(tmp / "odometry_nan.h5", position=(np.nan, 0.0, 0.0))
    made["quaternion_0"] = _odometry(tmp / "quaternion_0.h5", orientation=(0.0, 0.0, 0.0, 0.0))
    return made


def _shard_folders(tmp: Path) -> dict[str, Path]:
    """Dataset folders of crafted shards (`tiny_shard`, two frames each; no simulation)."""
    made = {name: tmp / name for name in ("flat", "twice", "two_runs", "nan_pose", "few_mics", "variants")}
    tiny_shard(made["flat"] / "shard-00000.h5")
    tiny_shard(made["twice"] / "shard-00000.h5")
    (made["twice"] / "shard-00001.h5").symlink_to(made["twice"] / "shard-00000.h5")
    tiny_shard(made["two_runs"] / "shard-00000.h5")
    tiny_shard(made["two_runs"] / "shard-00001.h5")
    with h5py.File(made["two_runs"] / "shard-00001.h5", "a") as f:
        f.attrs.update(plan_id="another", shard="1")
    tiny_shard(made["nan_pose"] / "shard-00000.h5")
    with h5py.File(made["nan_pose"] / "shard-00000.h5", "a") as f:
        f["pose"][1, 0, 3] = np.nan
    tiny_shard(made["few_mics"] / "shard-00000.h5")
    with h5py.File(made["few_mics"] / "shard-00000.h5", "a") as f:
        f["signals"] = np.zeros((2, 5, 16384), np.float16)
    tiny_shard(made["variants"] / "bounces_0" / "shard-00000.h5")
    return made


def _run_folders(run: Path, tmp: Path) -> dict[str, Path]:
    """Copies of a finished run of RUN, each with one fault."""
    made = {}
    for name in ("lock_dir", "linked", "stranger", "truncated"):
        made[name] = tmp / name
        shutil.copytree(run, made[name], symlinks=True)
    (made["lock_dir"] / ".generate.lock").mkdir()
    (made["linked"] / "shard-00001.h5").unlink()
    (made["linked"] / "shard-00001.h5").symlink_to(made["linked"] / "shard-00000.h5")
    shutil.copy(run / "shard-00000.h5", made["stranger"] / "shard-00007.h5")
    whole = (run / "shard-00001.h5").read_bytes()
    (made["truncated"] / "shard-00001.h5").write_bytes(whole[: len(whole) // 2])
    made["dangling"] = tmp / "dangling"
    made["dangling"].symlink_to(tmp / "nowhere")
    return made


@pytest.fixture(scope="module")
def probe(tmp_path_factory) -> dict:
    pytest.importorskip("chirppy")
    tmp = tmp_path_factory.mktemp("probe_sim")
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    first = {
        "run": ("acoustic_sim", f"{RUN} {tmp / 'run'}".split()),
        "elevations": ("acoustic_sim", f"{RUN} {tmp / 'elevations'} --set processing.elevation_deg=[0,10]".split()),
    }
    made = run_commands(first, env=env, parallel=2)
    assert made["run"].returncode == 0, made["run"].stderr[-3000:]
    places = {"tmp": tmp, "svg": ROOT / "examples" / "plan.svg"} | _suite_files(tmp) | _recordings(tmp)
    places |= _shard_folders(tmp) | _run_folders(tmp / "run", tmp)
    commands = {name: ("acoustic_sim", argv.format(**places).split()) for name, argv, _ in REFUSED}
    return {"done": made | run_commands(commands, env=env, parallel=2 * (os.cpu_count() or 1)), "tmp": tmp}


@pytest.mark.parametrize(("name", "argv", "words"), REFUSED, ids=[c[0] for c in REFUSED])
def test_refused_in_one_line_naming_what(probe, name, argv, words):
    done = probe["done"][name]
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert len(errors) == 1 and done.stderr.strip().endswith(errors[0]), done.stderr[-3000:]
    assert words in errors[0], errors[0]


def test_nothing_was_made_and_no_folder_changed(probe):
    tmp = probe["tmp"]
    assert not [made for made in NOT_MADE if (tmp / made).exists()]
    assert sorted(p.name for p in (tmp / "flat").iterdir()) == ["shard-00000.h5"]
    assert sorted(p.name for p in (tmp / "stranger").glob("shard-*")) == [f"shard-0000{i}.h5" for i in (0, 1, 7)]
    assert not (tmp / "nowhere").exists() and (tmp / "lock_dir" / ".generate.lock").is_dir()


def test_a_run_of_several_elevations_gets_its_card(probe):
    """A dataset of two elevations a frame was written whole, and its card (drawn from the first
    elevation, on the run's grid) too: the card's drawing failed after every shard was written."""
    done, out = probe["done"]["elevations"], probe["tmp"] / "elevations"
    assert done.returncode == 0, done.stderr[-3000:]
    assert {"card.png", "README.md", "manifest.json"} <= {p.name for p in out.iterdir()}
    with h5py.File(out / "shard-00000.h5", "r") as f:
        assert f["energyscape"].shape[1] == 2


def test_interrupt_while_a_library_swallows_it_is_raised_after():
    """trimesh catches BaseException around its optional imports: a Ctrl-C then was lost and
    the command ran on; `interrupt_after` holds it and raises it once the block ends."""
    from clitools.errors import interrupt_after

    with pytest.raises(KeyboardInterrupt), interrupt_after():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)
        except BaseException:  # as trimesh's imports do
            pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@pytest.mark.parametrize("delay_s", [0.05, 0.4])
def test_ctrl_c_while_the_command_line_loads_is_one_line(delay_s, tmp_path):
    """Ctrl-C in the first moments (Python starting, the package and its libraries loading):
    exit code 130 and one line; it was a trace, or nothing at all and the render ran on."""
    code, err = ctrl_c_after(["-m", "acoustic_sim", *f"{RENDER} --out {tmp_path}/a.png".split()], delay_s, ROOT)
    assert code == 130 and err.strip().splitlines() == ["interrupted"], err[-3000:]
    assert not (tmp_path / "a.png").exists()


def test_an_import_whose_folder_was_filled_meanwhile_says_to_give_a_new_out(tmp_path, monkeypatch, device):
    """Another import writing the same --out while this one ran: refused without the advice of
    --overwrite (which CHIRP imports refuse), the other's files kept."""
    pytest.importorskip("chirppy")
    from acoustic_sim.config import SimConfig
    from acoustic_sim.formats import chirp

    write_card = chirp.write_card

    def meanwhile(stage, *args, **kwargs):  # the card is written; another import publishes its own
        write_card(stage, *args, **kwargs)
        (tmp_path / "out").mkdir(exist_ok=True)
        (tmp_path / "out" / "README.md").write_text("theirs")

    monkeypatch.setattr(chirp, "write_card", meanwhile)
    with pytest.raises(FileExistsError, match=r"was filled by another process .* give a new --out") as refused:
        chirp.import_chirp(chirp_file(tmp_path / "rec.h5"), tmp_path / "out", SimConfig(), device=device)
    assert "--overwrite" not in str(refused.value) and (tmp_path / "out" / "README.md").read_text() == "theirs"
