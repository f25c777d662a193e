"""Every command that writes keeps one rule for its outputs (`clitools.outputs`), as a user meets it.

Each case runs `python -m acoustic_sim ...` or `python -m learn ...` in its own subprocess (they
start together in a module fixture, as in test_cli_errors.py), in one of four kinds:

- exists: the output is already there: refused without --overwrite, the file unchanged;
- input: the output names an input (the same file, through a symbolic or hard link, a file inside
  an input folder): refused even with --overwrite, every input unchanged;
- full: the disk fills while the output is written (RLIMIT_FSIZE, with SIGXFSZ ignored, so a write
  past the limit fails with EFBIG as a full disk fails with ENOSPC): one error line, nothing
  under the output's name, no temporary file, and the output's folder gone again;
- name: a name that becomes part of a path leaves --out: refused before anything is written.

Every case ends with exit code 2 and one `error:` line without a traceback (a crash, such as
HDF5's segmentation fault after a failed write, fails it). `learn train` keeps its own rules
(tests of the training run folder); `table2` and `sim2real` resume into their folders by design.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

import learn
from clitools.outputs import atomic_output, check_name

PRECIOUS = b"precious: never overwritten\n"

FULL_DISK = """\
import resource, runpy, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of killing
limit = int(sys.argv.pop(1))
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
sys.argv[0] = sys.argv.pop(1)
runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""

PINGS = "{w}/ping-0.bin {w}/ping-1.bin"
MODEL, DATA = "--checkpoint {model}", "{data}"

# (id, kind, package, argv, words of the error line, watched: kind exists: files made before
# (PRECIOUS, or "path>target" a link); input: files that must not change; full: byte limit)
CASES = [
    (
        "render-exists",
        "exists",
        "acoustic_sim",
        "render --scene box_room --frames 3 --out {o}/s.png",
        "--overwrite",
        ["{o}/s.png"],
    ),
    (
        "render-input",
        "input",
        "acoustic_sim",
        "render --svg {svg} --frames 3 --out {svg} --overwrite",
        "input",
        ["{svg}"],
    ),
    ("render-full", "full", "acoustic_sim", "render --scene box_room --frames 3 --out {o}/s.png", "{o}", 20_000),
    (
        "generate-exists",
        "exists",
        "acoustic_sim",
        "generate --suite tiny --frames 3 --out {data}",
        "other settings",
        [],
    ),
    ("generate-input", "input", "acoustic_sim", "generate --suite {suite} --out {suite}", "is a file", ["{suite}"]),
    (
        "generate-full",
        "full",
        "acoustic_sim",
        "generate --suite tiny --frames 2 --shards 1 --set tracer.ray_count=500 --quiet --device cpu --out {o}",
        "{o}/shard-00000.h5",
        30_000,
    ),
    (
        "pdm-exists",
        "exists",
        "acoustic_sim",
        f"import {PINGS} --format pdm --out {{o}}/r.npy",
        "--overwrite",
        ["{o}/r.npy"],
    ),
    (
        "pdm-input",
        "input",
        "acoustic_sim",
        f"import {PINGS} --format pdm --out {{w}}/link.npy --overwrite",
        "input",
        ["{w}/ping-0.bin"],
    ),
    ("pdm-full", "full", "acoustic_sim", f"import {PINGS} --format pdm --out {{o}}/r.npy", "{o}", 50_000),
    (
        "chirp-in-exists",
        "exists",
        "acoustic_sim",
        "import {rec} --format chirp --out {o}",
        "not an empty folder",
        ["{o}/notes.txt"],
    ),
    ("chirp-in-input", "input", "acoustic_sim", "import {rec} --format chirp --out {rec}", "is a file", ["{rec}"]),
    ("chirp-in-full", "full", "acoustic_sim", "import {rec} --format chirp --out {o}", "{o}/shard-00000.h5", 50_000),
    (
        "chirp-exists",
        "exists",
        "acoustic_sim",
        "export {data} --format chirp --out {o}/x.h5",
        "--overwrite",
        ["{o}/x.h5"],
    ),
    (
        "chirp-input",
        "input",
        "acoustic_sim",
        "export {data} --format chirp --out {data}/shard-00000.h5 --overwrite",
        "input",
        ["{data}/shard-00000.h5", "{data}/shard-00001.h5"],
    ),
    ("chirp-full", "full", "acoustic_sim", "export {data} --format chirp --out {o}/x.h5", "{o}/x.h5", 200_000),
    (
        "mcap-exists",
        "exists",
        "acoustic_sim",
        "export {data} --format mcap --out {o}/x.mcap",
        "--overwrite",
        ["{o}/x.mcap"],
    ),
    (
        "mcap-input",
        "input",
        "acoustic_sim",
        "export {data} --format mcap --out {w}/shard.mcap --overwrite",
        "input",
        ["{data}/shard-00001.h5"],
    ),
    ("mcap-full", "full", "acoustic_sim", "export {data} --format mcap --out {o}/x.mcap", "{o}/x.mcap", 50_000),
    (
        "evaluate-exists",
        "exists",
        "learn",
        f"evaluate {MODEL} --data {DATA} --out {{o}}",
        "--overwrite",
        ["{o}/metrics.json"],
    ),
    (
        "evaluate-input",
        "input",
        "learn",
        f"evaluate {MODEL} --data {DATA} --out {{w}}/linked_report --overwrite",
        "input",
        ["{model}"],
    ),
    ("evaluate-full", "full", "learn", f"evaluate {MODEL} --data {DATA} --out {{o}}", "{o}", 5_000),
    (
        "predict-exists",
        "exists",
        "learn",
        f"predict {MODEL} --input {DATA} --out {{o}}/p.npz",
        "--overwrite",
        ["{o}/p.npz"],
    ),
    (
        "predict-input",
        "input",
        "learn",
        f"predict {MODEL} --input {DATA} --out {{o}}/p.npz --png {{model}} --overwrite",
        "input",
        ["{model}"],
    ),
    (
        "predict-full",
        "full",
        "learn",
        f"predict {MODEL} --input {DATA} --out {{o}}/p.npz --png {{o}}/p.png --mcap {{o}}/p.mcap",
        "{o}/p",
        30_000,
    ),
    ("onnx-exists", "exists", "learn", f"export {MODEL} --out {{o}}/m.onnx", "--overwrite", ["{o}/m.onnx"]),
    ("onnx-input", "input", "learn", f"export {MODEL} --out {{w}}/hardlink.onnx --overwrite", "input", ["{model}"]),
    ("onnx-full", "full", "learn", f"export {MODEL} --out {{o}}/m.onnx", "{o}/m.onnx", 5_000),
    ("seeds-exists", "exists", "learn", "seeds-summary {w}/ev_a {w}/ev_b --out {o}", "--overwrite", ["{o}/summary.md"]),
    (
        "seeds-input",
        "input",
        "learn",
        "seeds-summary {w}/ev_a {w}/ev_b --out {w}/linked_summary --overwrite",
        "input",
        ["{w}/ev_a/metrics.json"],
    ),
    ("seeds-full", "full", "learn", "seeds-summary {w}/ev_a {w}/ev_b --out {o}", "{o}", 100),
    (
        "s2r-sum-exists",
        "exists",
        "learn",
        "sim2real-summary {w}/s2r_a {w}/s2r_b --out {o}",
        "--overwrite",
        ["{o}/sim2real.md"],
    ),
    (
        "s2r-sum-input",
        "input",
        "learn",
        "sim2real-summary {w}/s2r_a {w}/s2r_b --out {w}/s2r_a --overwrite",
        "input",
        ["{w}/s2r_a/sim2real.json"],
    ),
    ("s2r-sum-full", "full", "learn", "sim2real-summary {w}/s2r_a {w}/s2r_b --out {o}", "{o}", 100),
    (
        "t2-sum-exists",
        "exists",
        "learn",
        "table2-summary {w}/t2_a {w}/t2_b --out {o}",
        "--overwrite",
        ["{o}/table2.md"],
    ),
    (
        "t2-sum-input",
        "input",
        "learn",
        "table2-summary {w}/t2_a {w}/t2_b --out {w}/t2_b --overwrite",
        "input",
        ["{w}/t2_b/table2.json"],
    ),
    ("t2-sum-full", "full", "learn", "table2-summary {w}/t2_a {w}/t2_b --out {o}", "{o}", 100),
    (
        "table2-input",
        "input",
        "learn",
        "table2 --train {data} --test {w}/cases --out {data}/study",
        "input folder",
        ["{data}"],
    ),
    (
        "sim2real-input",
        "input",
        "learn",
        "sim2real --ablation {w}/abl --reality {data} --out {w}/abl",
        "input folder",
        ["{data}"],
    ),
    (
        "sim2real-name",
        "name",
        "learn",
        "sim2real --ablation {w}/abl --reality {data} --test ../../escape={data} --out {o}",
        "test set name '../../escape'",
        [],
    ),
]
LINKS = {  # made before the cases run: (link, target, kind)
    "{w}/link.npy": ("{w}/ping-0.bin", "symbolic"),
    "{w}/shard.mcap": ("{data}/shard-00001.h5", "symbolic"),
    "{w}/hardlink.onnx": ("{model}", "hard"),
    "{w}/linked_report/metrics.json": ("{model}", "symbolic"),
    "{w}/linked_summary/summary.json": ("{w}/ev_a/metrics.json", "symbolic"),
}


def _tiny_checkpoint(path: Path) -> Path:
    """The pretrained checkpoint's grid and settings around a polar UNet of width 4 (fast)."""
    from learn.models import ModelConfig, build_model

    ckpt = torch.load(learn.PRETRAINED_CHECKPOINT, weights_only=True)
    ckpt["model_config"]["width"] = 4
    torch.manual_seed(0)
    ckpt["model"] = build_model(ModelConfig(**ckpt["model_config"])).state_dict()
    torch.save(ckpt, path)
    return path


def _study_reports(w: Path) -> None:
    """Two runs each of what the summaries read: sim2real.json, metrics.json, table2.json."""
    from learn.report import METRICS
    from learn.studies import SIM2REAL_KEYS, TABLE2_CASES

    rng = np.random.default_rng(0)
    for run in ("a", "b"):
        score = {k: {"mean": float(rng.uniform())} for k, _ in SIM2REAL_KEYS}
        table = {v: {w_: score for w_ in ("in_domain", "reality", "reality_echo_peak")} for v in ("b0", "b3")}
        (w / f"s2r_{run}").mkdir()
        (w / f"s2r_{run}" / "sim2real.json").write_text(json.dumps(table))
        results = {p: {"all": {k: {"mean": float(rng.uniform())} for k, _, _ in METRICS}} for p in ("model", "empty")}
        (w / f"ev_{run}").mkdir()
        report = {"data": "d", "split": "all", "windows": 2, "results": results}
        (w / f"ev_{run}" / "metrics.json").write_text(json.dumps(report))
        rows = ("K = 1", "K = 3", "K = 5", "K = 5 fine-tuned")
        t2 = {r: {c: {"scan_f1": {"mean": float(rng.uniform())}} for c in TABLE2_CASES} for r in rows}
        (w / f"t2_{run}").mkdir()
        (w / f"t2_{run}" / "table2.json").write_text(json.dumps(t2))
        for c in TABLE2_CASES:
            (w / f"t2_{run}" / "k5" / c).mkdir(parents=True)
            peak = {"results": {"echo peak": {"all": {"scan_f1": {"mean": 0.1}}}}}
            (w / f"t2_{run}" / "k5" / c / "metrics.json").write_text(json.dumps(peak))


def _world(w: Path, device: str) -> dict[str, str]:
    """The inputs every case reads: a 10-frame dataset with signals, its CHIRP file, raw PDM
    pings, a small checkpoint, an SVG plan, a suite file, study reports, links into them."""
    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics
    from acoustic_sim.formats.chirp import export_chirp

    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=1000)})
    generate(suite, w / "data", frames=10, shards=2, seed=3, device=device, keep_signals=True, progress=False)
    export_chirp(w / "data", w / "rec.h5")
    rng = np.random.default_rng(0)
    for i in range(2):
        rng.integers(0, 2**32, 30_000, dtype=np.uint32).tofile(w / f"ping-{i}.bin")
    _study_reports(w)
    for name in ("abl", "cases"):
        (w / name).mkdir()
    (w / "abl" / "bounces_0").symlink_to(w / "data", target_is_directory=True)
    places = {"w": str(w), "data": str(w / "data"), "rec": str(w / "rec.h5"), "svg": str(w / "plan.svg")}
    places |= {"model": str(_tiny_checkpoint(w / "model.pt")), "suite": str(w / "suite.json")}
    (w / "plan.svg").write_bytes((Path(__file__).parents[1] / "examples" / "plan.svg").read_bytes())
    (w / "suite.json").write_text('{"base": "tiny", "name": "mine"}')
    for link, (target, kind) in LINKS.items():
        link, target = Path(link.format(**places)), Path(target.format(**places))
        link.parent.mkdir(exist_ok=True)
        if kind == "hard":
            os.link(target, link)
        else:
            link.symlink_to(target)
    return places


def _digest(paths: list[Path]) -> dict[str, str]:
    """sha256 of every file at or under `paths`."""
    files = [f for p in paths for f in ([p] if p.is_file() else sorted(p.rglob("*"))) if f.is_file()]
    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


@pytest.fixture(scope="module")
def results(request, tmp_path_factory, device):
    """Runs the cases this session selected (`-k chirp-full` runs one), all when none is."""
    items = [i for i in request.session.items if i.originalname == "test_outputs_never_destroy"]
    chosen = {i.callspec.params["name"] for i in items}
    w = tmp_path_factory.mktemp("outputs")
    places = _world(w, device)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    runs = []
    for name, kind, package, argv, _, watched in CASES:
        if chosen and name not in chosen:
            continue
        own = places | {"o": str(w / "cases" / name)}
        if kind == "exists":
            for path in watched:
                Path(path.format(**own)).parent.mkdir(parents=True, exist_ok=True)
                Path(path.format(**own)).write_bytes(PRECIOUS)
        command = [sys.executable, "-m", package, *argv.format(**own).split()]
        if kind == "full":
            command = [sys.executable, "-c", FULL_DISK, str(watched), package, *argv.format(**own).split()]
            # the same command once without the limit, first: it compiles the kernels the case needs
            free = places | {"o": str(w / "warm" / name)}
            runs.append((f"warm {name}", [sys.executable, "-m", package, *argv.format(**free).split()]))
        runs.append((name, command))
    before = _digest([w / "data", w / "rec.h5", w / "model.pt", w / "ping-0.bin", w / "plan.svg", w / "ev_a"])
    before |= _digest([w / "s2r_a", w / "t2_b", w / "suite.json"])

    def run(item):
        name, command = item
        return name, subprocess.run(command, capture_output=True, text=True, timeout=300, env=env, cwd=w)

    full = {name for name, kind, *_ in CASES if kind == "full"}
    with ThreadPoolExecutor(4) as pool:
        # The full-disk cases after the rest: a kernel compiled under their byte limit could not be
        # written (Warp's cache and precompiled header would fail with errors of their own), and
        # their warm-up runs before them have compiled every kernel they need.
        done = dict(pool.map(run, [r for r in runs if r[0] not in full]))
        done |= dict(pool.map(run, [r for r in runs if r[0] in full]))
    return {"done": done, "places": places, "w": w, "before": before}


@pytest.mark.parametrize(("name", "kind", "package", "argv", "words", "watched"), CASES, ids=[c[0] for c in CASES])
def test_outputs_never_destroy(results, name, kind, package, argv, words, watched):
    done, w = results["done"][name], results["w"]
    own = results["places"] | {"o": str(w / "cases" / name)}
    errors = [line for line in done.stderr.splitlines() if "error: " in line]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert len(errors) == 1 and done.stderr.strip().endswith(errors[0]), done.stderr[-3000:]
    assert words.format(**own) in errors[0], errors[0]
    if kind == "exists":
        assert all(Path(p.format(**own)).read_bytes() == PRECIOUS for p in watched)
    if kind == "input":
        now = _digest([Path(p.format(**own)) for p in watched])
        assert now and now == {k: v for k, v in results["before"].items() if k in now}
    if kind in ("full", "name"):  # the output's folder was new: nothing of it may stay
        left = w / "cases" / name
        assert not left.exists() or sorted(p.name for p in left.iterdir()) == ["plan.json"], list(left.iterdir())
    if kind == "name":
        assert not list(w.parent.glob("escape*")) and not (w / "escape").exists()


def test_nothing_else_changed_and_no_temporary_stays(results):
    """After every case: the inputs are as they were, and no temporary file is left anywhere."""
    w = results["w"]
    assert _digest([Path(p) for p in results["before"]]) == results["before"]
    assert not [p for p in w.rglob("*") if ".tmp" in p.name], [p for p in w.rglob("*") if ".tmp" in p.name]
    assert not (w / "data" / "study").exists() and not (w / "abl" / "bounces_0" / "best.pt").exists()


def test_two_writers_of_one_path_keep_their_own_temporaries(tmp_path):
    """Two writers at once: each has its own temporary; the last to finish is the file."""
    out = tmp_path / "o.txt"
    with atomic_output(out, overwrite=True) as first, atomic_output(out, overwrite=True) as second:
        first.write_text("first")
        second.write_text("second")
        assert first != second and first.exists() and second.exists() and not out.exists()
    assert out.read_text() == "first" and sorted(p.name for p in tmp_path.iterdir()) == ["o.txt"]


def test_ctrl_c_or_a_file_that_appears_meanwhile_leaves_no_trace(tmp_path):
    """Ctrl-C while writing removes the temporary and the folder made for it; without
    --overwrite, a file that another process wrote meanwhile is kept, not replaced."""
    with pytest.raises(KeyboardInterrupt), atomic_output(tmp_path / "new" / "o.txt", overwrite=False) as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    out = tmp_path / "o.txt"
    with pytest.raises(FileExistsError, match="exists; replace it with --overwrite"):
        with atomic_output(out, overwrite=False) as tmp:
            tmp.write_text("mine")
            out.write_text("theirs")
    assert out.read_text() == "theirs" and list(tmp_path.iterdir()) == [out]


@pytest.mark.parametrize("name", ["../x", "../../escape", "/abs/x", "a/b", ".hidden", "", "."])
def test_names_that_leave_the_output_folder_are_refused(name):
    with pytest.raises(ValueError, match="must be letters"):
        check_name(name, "--test name")


def test_names_of_one_folder_pass():
    assert [check_name(n, "x") for n in ("crossengine", "bounces_0", "a.b-c")] == ["crossengine", "bounces_0", "a.b-c"]
