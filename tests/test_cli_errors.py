"""Every user error in both command lines ends the way a user can act on: exit code 2, one
`error: ...` line that names the problem, no traceback (the trace only with --debug).

Each case runs `python -m learn ...` or `python -m acoustic_sim ...` in a process of its own, as a
user would (tests/cli_runner.py forks each from one interpreter that made the heavy imports once);
they run two at a time per core in a module fixture, and each parametrised test reads its own result.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import learn

from .cli_runner import run_commands
from .crafted import pickle_payload

CKPT = Path(learn.PRETRAINED_CHECKPOINT)

# (id, package, argv with {placeholders}, words the error line must contain)
CASES = [
    # learn: checkpoints
    ("ckpt-missing", "learn", "evaluate --checkpoint {tmp}/none.pt --data {data} --out {tmp}/e1", "does not exist"),
    ("ckpt-zero-bytes", "learn", "evaluate --checkpoint {zero} --data {data} --out {tmp}/e2", "can read safely"),
    ("ckpt-truncated", "learn", "evaluate --checkpoint {truncated} --data {data} --out {tmp}/e3", "can read safely"),
    ("ckpt-not-torch", "learn", "predict --checkpoint {text} --input {data} --out {pred}", "can read safely"),
    ("ckpt-pickle", "learn", "export --checkpoint {evil} --out {tmp}/m.onnx", "can read safely"),
    ("ckpt-misfit", "learn", "predict --checkpoint {misfit} --input {data} --out {pred}", "do not fit the model"),
    ("ckpt-folder", "learn", "evaluate --checkpoint {tmp} --data {data} --out {tmp}/e4", "is a folder"),
    ("init-from-missing", "learn", "train --data {data} --out {tmp}/t1 --init-from {tmp}/none.pt", "does not exist"),
    # learn: devices
    ("learn-cuda", "learn", "evaluate --checkpoint {ckpt} --data {data} --out {tmp}/e5 --device cuda", "no CUDA GPU"),
    ("learn-cuda-index", "learn", "train --data {data} --out {tmp}/t2 --device cuda:3", "CUDA GPU"),
    (
        "learn-device-name",
        "learn",
        "predict --checkpoint {ckpt} --input {data} --out {pred} --device gpu",
        "not a torch device",
    ),
    # learn: data and folders
    ("data-is-file", "learn", "evaluate --checkpoint {ckpt} --data {ckpt} --out {tmp}/e6", "not a folder"),
    ("data-empty", "learn", "evaluate --checkpoint {ckpt} --data {empty} --out {tmp}/e7", "no shard"),
    ("data-missing", "learn", "train --data {tmp}/nowhere --out {tmp}/t3", "nowhere"),
    ("shard-zero-bytes", "learn", "evaluate --checkpoint {ckpt} --data {zero_shard} --out {tmp}/e8", "shard-00000.h5"),
    ("shard-garbage", "learn", "train --data {garbage_shard} --out {tmp}/t4", "shard-00000.h5"),
    ("train-out-is-file", "learn", "train --data {data} --out {ckpt}", "is a file"),
    ("train-onto-a-run", "learn", "train --data {data} --out {finished}", "--overwrite"),
    ("evaluate-out-is-file", "learn", "evaluate --checkpoint {ckpt} --data {data} --out {text}", "is a file"),
    ("predict-out-unwritable", "learn", "predict --checkpoint {ckpt} --input {data} --out /proc/p.npz", "/proc/p"),
    ("export-out-missing-dir", "learn", "export --checkpoint {ckpt} --out {text}/sub/m.onnx", "Not a directory"),
    ("summary-no-metrics", "learn", "seeds-summary --out {tmp}/s {empty}", "metrics.json"),
    # learn: values
    (
        "threshold-above-1",
        "learn",
        "evaluate --checkpoint {ckpt} --data {data} --threshold 1.5 --out {tmp}/e9",
        "(0, 1]",
    ),
    (
        "threshold-nan",
        "learn",
        "predict --checkpoint {ckpt} --input {data} --out {pred} --threshold nan",
        "(0, 1]",
    ),
    ("lr-nan", "learn", "train --data {data} --out {tmp}/t5 --lr nan", "lr"),
    ("lr-negative", "learn", "train --data {data} --out {tmp}/t6 --lr -1", "lr"),
    ("epochs-zero", "learn", "train --data {data} --out {tmp}/t7 --epochs 0", "epochs"),
    ("batch-zero", "learn", "train --data {data} --out {tmp}/t8 --batch-size 0", "batch_size"),
    ("frames-even", "learn", "train --data {data} --out {tmp}/t9 --frames 4", "odd"),
    ("val-fraction", "learn", "train --data {data} --out {tmp}/t10 --val-fraction 1.5", "fraction"),
    ("max-minutes-nan", "learn", "train --data {data} --out {tmp}/t11 --max-minutes nan", "max_minutes"),
    ("input-complex", "learn", "predict --checkpoint {ckpt} --input {complex} --out {pred}", "real numbers"),
    ("input-nan", "learn", "predict --checkpoint {ckpt} --input {nan} --out {pred}", "NaN"),
    ("input-object", "learn", "predict --checkpoint {ckpt} --input {object} --out {pred}", "pickle"),
    ("input-grid", "learn", "predict --checkpoint {ckpt} --input {small} --out {pred}", "expected"),
    ("input-missing", "learn", "predict --checkpoint {ckpt} --input {tmp}/none.npy --out {pred}", "none.npy"),
    # acoustic_sim generate
    ("suite-unknown", "acoustic_sim", "generate --suite nope --out {tmp}/g1", "unknown suite"),
    ("suite-file-missing", "acoustic_sim", "generate --suite {tmp}/none.toml --out {tmp}/g2", "none.toml"),
    ("suite-file-broken", "acoustic_sim", "generate --suite {broken_json} --out {tmp}/g3", "broken.json"),
    ("suite-file-nan", "acoustic_sim", "generate --suite {nan_suite} --out {tmp}/g4", "speed_m_s"),
    ("shards-zero", "acoustic_sim", "generate --suite tiny --frames 3 --shards 0 --out {tmp}/g5", "shards"),
    ("frames-zero", "acoustic_sim", "generate --suite tiny --frames 0 --out {tmp}/g6", "frames"),
    ("workers-zero", "acoustic_sim", "generate --suite tiny --frames 3 --workers 0 --out {tmp}/g7", "workers"),
    ("gen-out-is-file", "acoustic_sim", "generate --suite tiny --frames 3 --out {ckpt}", "is a file"),
    ("gen-out-foreign", "acoustic_sim", "generate --suite tiny --frames 3 --out {foreign}", "not a dataset folder"),
    ("gen-out-unwritable", "acoustic_sim", "generate --suite tiny --frames 3 --out /proc/g8", "/proc/g8"),
    ("gen-other-settings", "acoustic_sim", "generate --suite tiny --frames 16 --seed 9 --out {data}", "plan"),
    ("gen-cuda", "acoustic_sim", "generate --suite tiny --frames 3 --out {tmp}/g9 --device cuda", "no CUDA GPU"),
    ("gen-device-name", "acoustic_sim", "generate --suite tiny --frames 3 --out {tmp}/g10 --device gpu", "Warp device"),
    # with workers the device is checked in them (the parent must not start CUDA), still before plan.json
    (
        "gen-cuda-workers",
        "acoustic_sim",
        "generate --suite tiny --frames 3 --workers 2 --out {tmp}/g11 --device cuda",
        "no CUDA GPU",
    ),
    # acoustic_sim render
    ("render-mesh-missing", "acoustic_sim", "render --mesh {tmp}/none.obj --out {tmp}/r.png", "none.obj"),
    ("render-mesh-nan", "acoustic_sim", "render --mesh {nan_obj} --out {tmp}/r.png", "non-finite"),
    ("render-mesh-garbage", "acoustic_sim", "render --mesh {text} --out {tmp}/r.png", "notes.txt"),
    ("render-svg-nan", "acoustic_sim", "render --svg {nan_svg} --out {tmp}/r.png", "NaN"),
    ("render-scene-unknown", "acoustic_sim", "render --scene nope --out {tmp}/r.png", "nope"),
    ("render-frame-range", "acoustic_sim", "render --scene box_room --frames 5 --frame 9 --out {tmp}/r.png", "--frame"),
    ("render-cuda", "acoustic_sim", "render --scene box_room --out {tmp}/r.png --device cuda", "no CUDA GPU"),
    ("render-out-unwritable", "acoustic_sim", "render --scene box_room --frames 3 --out /proc/r.png", "/proc/r.png"),
    (
        "render-rays-zero",
        "acoustic_sim",
        "render --scene box_room --frames 3 --sonar --rays 0 --out {tmp}/r.png",
        "ray",
    ),
    ("render-size-short", "acoustic_sim", "render --scene box_room --scene-arg size=[1,1] --out {tmp}/r.png", "size"),
    (
        "render-scene-arg-unknown",
        "acoustic_sim",
        "render --scene box_room --scene-arg colour=red --out {tmp}/r.png",
        "colour",
    ),
    ("render-dt-nan", "acoustic_sim", "render --scene box_room --dt nan --out {tmp}/r.png", "dt"),
    ("render-speed-negative", "acoustic_sim", "render --scene box_room --speed -1 --out {tmp}/r.png", "speed"),
    (
        "render-noise-nan",
        "acoustic_sim",
        "render --scene box_room --lidar-noise gaussian --lidar-noise-m nan --out {tmp}/r.png",
        "noise_m",
    ),
    ("render-bounces", "acoustic_sim", "render --scene box_room --sonar --max-bounces 99 --out {tmp}/r.png", "bounces"),
    ("patience-negative", "learn", "train --data {data} --out {tmp}/t12 --patience -1", "patience"),
    (
        "checkpoint-names-twice",
        "learn",
        "evaluate --checkpoint a={ckpt} --checkpoint a={ckpt} --data {data} --out {tmp}/e10",
        "twice",
    ),
]


def _inputs(tmp: Path, data: Path) -> dict[str, str]:
    """The bad files the cases refer to, written once."""
    files = {"tmp": tmp, "data": data, "ckpt": CKPT, "pred": tmp / "p.npz"}
    (tmp / "zero.pt").write_bytes(b"")
    files["zero"] = tmp / "zero.pt"
    files["truncated"] = tmp / "truncated.pt"
    files["truncated"].write_bytes(CKPT.read_bytes()[: CKPT.stat().st_size // 2])
    files["text"] = tmp / "notes.txt"
    files["text"].write_text("my notes\n")
    files["evil"] = pickle_payload(tmp / "evil.pt", tmp / "code_ran")
    ckpt = torch.load(CKPT, weights_only=True)
    ckpt["model_config"]["width"] = 8
    files["misfit"] = tmp / "misfit.pt"
    torch.save(ckpt, files["misfit"])
    for name in ("empty", "foreign", "zero_shard", "garbage_shard", "finished"):
        (tmp / name).mkdir()
        files[name] = tmp / name
    (tmp / "foreign" / "README.md").write_text("my notes")
    (tmp / "zero_shard" / "shard-00000.h5").write_bytes(b"")
    (tmp / "garbage_shard" / "shard-00000.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 500)
    for name in ("best.pt", "last.pt"):
        (tmp / "finished" / name).write_bytes(CKPT.read_bytes())
    for name, array in {
        "complex": np.zeros((6, 240, 181), np.complex64),
        "nan": np.full((6, 240, 181), np.nan, np.float32),
        "object": np.array([{"a": 1}], dtype=object),
        "small": np.zeros((6, 100, 181), np.float32),
    }.items():
        np.save(tmp / f"{name}.npy", array)
        files[name] = tmp / f"{name}.npy"
    files["broken_json"] = tmp / "broken.json"
    files["broken_json"].write_text('{"name": "x", ')
    files["nan_suite"] = tmp / "nan_suite.json"
    files["nan_suite"].write_text('{"base": "tiny", "name": "nan_suite", "speed_m_s": NaN}')
    files["nan_obj"] = tmp / "nan.obj"
    files["nan_obj"].write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    files["nan_svg"] = tmp / "nan.svg"
    files["nan_svg"].write_text(
        '<svg xmlns="http://www.w3.org/2000/svg" width="600" height="400">'
        '<rect x="0" y="0" width="600" height="NaN"/></svg>'
    )
    return {k: str(v) for k, v in files.items()}


@pytest.fixture(scope="module")
def results(tiny_dataset, tmp_path_factory) -> dict[str, tuple[subprocess.CompletedProcess, Path]]:
    # The commands run side by side: each writes (or is refused) in an --out of its own. Ten of them
    # shared {tmp}/e, and one evaluate once failed on another's half-made output folder.
    tmp = tmp_path_factory.mktemp("cli_errors")
    files = _inputs(tmp, tiny_dataset)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "CUDA_VISIBLE_DEVICES": os.environ.get("CUDA_VISIBLE_DEVICES", "")}
    commands = {name: (package, argv.format(**files).split()) for name, package, argv, _ in CASES}
    done = run_commands(commands, env=env, parallel=2 * (os.cpu_count() or 1))
    return {"done": done, "tmp": tmp}


@pytest.mark.parametrize(("name", "package", "argv", "words"), CASES, ids=[c[0] for c in CASES])
def test_user_error_is_one_line(results, name, package, argv, words):
    done = results["done"][name]
    # ours: "error: ..."; argparse's own (a bad choice or type): "usage: ..." then "prog: error: ..."
    errors = [line for line in done.stderr.splitlines() if "error: " in line]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert len(errors) == 1 and done.stderr.strip().endswith(errors[0]), done.stderr[-3000:]
    assert words in errors[0], errors[0]


def test_the_audit_is_wide_and_no_case_ran_file_code(results):
    assert len(CASES) >= 60 and len({c[0] for c in CASES}) == len(CASES)
    assert not (results["tmp"] / "code_ran").exists()
    refused_runs = [results["tmp"] / f"g{i}" for i in range(1, 12)]  # settings are checked before plan.json
    assert not any(p.exists() for p in refused_runs), [p for p in refused_runs if p.exists()]


def test_debug_shows_the_trace():
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "learn",
            "evaluate",
            "--checkpoint",
            "/nowhere.pt",
            "--data",
            "/",
            "--out",
            "/x",
            "--debug",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode != 0 and "Traceback" in done.stderr and "nowhere.pt" in done.stderr
