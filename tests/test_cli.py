"""The command line: render and generate, their messages and settings files (what `render` draws:
tests/test_render.py)."""

import re
import subprocess
import sys

import pytest

from acoustic_sim.cli import main


def test_render_reports_bad_input(tmp_path, capsys):
    assert (
        main(["render", "--scene", "box_room", "--frames", "5", "--frame", "9", "--out", str(tmp_path / "x.png")]) == 2
    )
    assert "--frame" in capsys.readouterr().err
    assert (
        main(["render", "--scene", "box_room", "--scene-arg", "size=[0.5,0.5,2]", "--out", str(tmp_path / "y.png")])
        == 2
    )
    assert "no free space" in capsys.readouterr().err


def test_module_entry_point_help():
    done = subprocess.run(
        [sys.executable, "-m", "acoustic_sim", "render", "--help"], capture_output=True, text=True, check=True
    )
    assert "--scene" in done.stdout and "--out" in done.stdout


LOADED = """
import runpy, sys
sys.argv = ["acoustic_sim", *sys.argv[1:]]
try:
    runpy.run_module("acoustic_sim", run_name="__main__")
except SystemExit:
    pass
print("LOADED", *sorted(m for m in ("trimesh", "scipy", "warp", "h5py") if m in sys.modules))
"""


@pytest.mark.parametrize("argv", [["--help"], ["render", "--help"], ["render", "--scene", "offfice"]])
def test_help_and_a_mistyped_option_load_no_scene_or_engine_library(argv):
    """--help and argparse's refusals answer before trimesh, SciPy, Warp or h5py load (~1 s): the
    parser knows the scene builders' names without importing scenes (checked against it below)."""
    done = subprocess.run([sys.executable, "-c", LOADED, *argv], capture_output=True, text=True, timeout=60)
    assert done.stdout.splitlines()[-1] == "LOADED", done.stdout[-300:] + done.stderr[-300:]
    assert ("offfice" in done.stderr) == ("offfice" in argv)


def test_the_parser_lists_every_scene_builder_and_the_suites():
    import scenes
    from acoustic_sim.cli_scene import BUILDER_NAMES
    from acoustic_sim.datasets.suites import SUITES

    assert BUILDER_NAMES == tuple(sorted(scenes.BUILDERS))
    shown = subprocess.run(
        [sys.executable, "-m", "acoustic_sim", "generate", "--help"], capture_output=True, text=True, check=True
    ).stdout
    assert all(f"{name}:" in " ".join(shown.split()) for name in SUITES)


def test_generate_command_and_its_errors(tmp_path, device, capsys):
    """`generate --suite tiny --frames 3` writes one shard and says so; a rerun skips it; bad
    suites, shard counts and a flag the suite cannot take exit with 2 and a message."""
    args = ["generate", "--suite", "tiny", "--frames", "3", "--out", str(tmp_path), "--device", device, "--quiet"]
    assert main(args) == 0
    assert "3 frames in 1 shard under" in capsys.readouterr().out and (tmp_path / "shard-00000.h5").exists()
    assert "3 frames in 1 episode (robot drives), 1 shard," in (tmp_path / "README.md").read_text()  # the card
    assert main(args) == 0
    assert "0 written, 1 already complete" in capsys.readouterr().out
    assert main(["generate", "--suite", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown suite" in capsys.readouterr().err
    assert main(["generate", "--suite", "tiny", "--frames", "3", "--shards", "5", "--out", str(tmp_path / "b")]) == 2
    assert "shards must lie in 1..1" in capsys.readouterr().err
    assert main(["generate", "--suite", "ablation", "--max-bounces", "2", "--out", str(tmp_path / "c")]) == 2
    assert "varies max_bounces" in capsys.readouterr().err
    assert main(["generate", "--suite", "ablation", "--variants", "bounces_9", "--out", str(tmp_path / "d")]) == 2
    assert "has variants ['bounces_0', 'bounces_1', 'bounces_3']" in capsys.readouterr().err


def test_generate_only_the_named_variants(tmp_path, device):
    args = ["generate", "--suite", "ablation", "--variants", "bounces_1", "--frames", "2", "--out", str(tmp_path)]
    assert main([*args, "--device", device, "--quiet"]) == 0
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == ["bounces_1"]


def test_render_writes_its_settings_beside_the_picture(tmp_path, device):
    """PICTURE.json holds the rig as used (a --set and a flag both reach it) and the options."""
    import json

    out = tmp_path / "view.png"
    argv = ["render", "--scene", "box_room", "--frames", "5", "--device", device, "--out", str(out)]
    assert main([*argv, "--set", "lidar.dropout_probability=0.25", "--lidar-noise-m", "0.01"]) == 0
    written = json.loads(out.with_suffix(".json").read_text())
    assert written["picture"] == "view.png" and written["options"]["scene"] == "box_room"
    assert written["sim"]["lidar"]["dropout_probability"] == 0.25 and written["sim"]["lidar"]["noise_m"] == 0.01
    assert set(written["sim"]) == {"lidar", "sonar", "tracer", "processing"}


def test_commands_are_quiet_unless_asked(tmp_path):
    """No Warp banner, module-load lines or missing-driver notice on a CPU run; --verbose shows Warp's lines."""
    command = [sys.executable, "-m", "acoustic_sim", "generate", "--suite", "tiny", "--frames", "3", "--quiet"]
    command += ["--device", "cpu", "--out", str(tmp_path / "q")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, check=True)
    assert "Warp" not in done.stdout + done.stderr and "Module" not in done.stdout + done.stderr
    assert done.stdout.startswith("tiny: 3 frames")
    verbose = [*command[:-1], str(tmp_path / "v"), "--verbose"]
    done = subprocess.run(verbose, capture_output=True, text=True, timeout=300)
    assert "Warp" in done.stdout + done.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")
def test_generate_forks_its_workers_from_a_parent_that_never_starts_warp(tmp_path):
    """`generate --workers 2` in a fresh process: the parent leaves Warp, and so CUDA, to its
    workers, which are forked from it (no second import of the package) and stay quiet."""
    script = (
        "import sys\n"
        "from acoustic_sim.cli import main\n"
        "from acoustic_sim.devices import _warp_runtime\n"
        "code = main(sys.argv[1:])\n"
        "print('parent started warp:', _warp_runtime() is not None)\n"
        "sys.exit(code)\n"
    )
    command = [sys.executable, "-c", script, "generate", "--suite", "tiny", "--frames", "16", "--shards", "2"]
    command += ["--workers", "2", "--device", "cpu", "--quiet", "--out", str(tmp_path / "d")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, check=True)
    assert "16 frames in 2 shards" in done.stdout, done.stdout
    helpers = r"(1 helper process|\d+ helper processes) each|host work in threads"
    assert re.search(rf"summed over 2 forked workers \(({helpers})\)", done.stdout), done.stdout
    assert "parent started warp: False" in done.stdout
    assert "Warp" not in done.stderr and "Module" not in done.stdout + done.stderr, done.stderr


def test_dataset_card_reads_the_rig_as_simulated(tmp_path, device):
    """A suite file based on `paper` with max_bounces 1, and a --set on top: the card says 1 bounce
    and the --set ray count, not the base suite's prose ("3 secondary bounces")."""
    suite = tmp_path / "my_suite.toml"
    suite.write_text('base = "paper"\nframes = 2\nepisode_frames = 2\n[physics]\nmax_bounces = 1\n')
    args = ["generate", "--suite", str(suite), "--out", str(tmp_path / "d"), "--set", "tracer.ray_count=3000"]
    assert main([*args, "--device", device, "--quiet"]) == 0
    card = (tmp_path / "d" / "README.md").read_text()
    assert "| secondary bounces (max_bounces) | 1 |" in card and "| rays per ping | 3,000 |" in card
    assert "3 secondary bounces" not in card and "based on `paper`" in card
    assert card.startswith("# Dataset: my_suite\n")  # the file's name, not its base's
