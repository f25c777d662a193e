"""No committed file and no shipped checkpoint carries a machine's absolute path.

A machine path is one under the roots where work folders, homes and caches live (see
benchmarks.provenance.MACHINE_PATH). Every text file git tracks is scanned (files with a NUL byte,
such as PNGs and checkpoints, are skipped), and the shipped checkpoint's metadata is walked value
by value and its pickle read as bytes. Each scan is shown to fail on a planted path. The learner
records the paths it is given relative to the working folder; a short training run checks that
its checkpoint, config and summary hold no machine path even when given absolute ones.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import machine_paths, strip_machine_paths, tracked_text_files  # noqa: E402
from learn.config import LearnConfig, TrainConfig  # noqa: E402
from learn.data import DataConfig, recorded_path  # noqa: E402
from learn.models import ModelConfig  # noqa: E402
from learn.train import train  # noqa: E402

CHECKPOINT = ROOT / "learn" / "pretrained" / "polar_unet_k5.pt"
# Planted paths are assembled, so that this file does not hold them itself.
PLANTED = "/" + "/".join(("root", "w14", "runs", "seed0", "best.pt"))
PLANTED_HOME = "/" + "/".join(("home", "someone", "repo", "data", "paper"))
# Not machine paths, assembled too so that no scan of this file mistakes them for one.
NOT_PLANTED = "../../" + "tmp/x and https://x.org/" + "root/a"


def tree_report(root: Path) -> dict[str, list[str]]:
    """{tracked text file (relative): the machine paths in it}, for files that hold any."""
    found = {}
    for path in tracked_text_files(root):
        paths = machine_paths(path.read_bytes().decode())
        if paths:
            found[path.relative_to(root).as_posix()] = paths
    return found


def metadata_strings(value, where: str = "") -> list[tuple[str, str]]:
    """(key path, string) for every string in a checkpoint's metadata (tensors are skipped)."""
    if isinstance(value, str):
        return [(where, value)]
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in metadata_strings(v, f"{where}/{k}")]
    if isinstance(value, list | tuple):
        return [s for i, v in enumerate(value) for s in metadata_strings(v, f"{where}[{i}]")]
    return []


def checkpoint_report(path: Path) -> list[str]:
    """Where a checkpoint holds a machine path: metadata keys, and the raw pickle as a last resort."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    found = [f"{key}: {text}" for key, text in metadata_strings(ckpt) for _ in machine_paths(text)]
    with zipfile.ZipFile(path) as archive:
        for name in archive.namelist():
            if name.endswith(".pkl"):
                found += [f"{name}: {p}" for p in machine_paths(archive.read(name).decode("latin-1"))]
    return found


def test_no_tracked_file_holds_a_machine_path():
    """Every tracked text file is free of machine paths (`python benchmarks/provenance.py paths --fix`
    rewrites them in their relative form)."""
    assert tree_report(ROOT) == {}


def test_tree_scan_fails_on_a_planted_path(tmp_path: Path):
    """In a throw-away repository a planted path in a tracked text file is named with its file; the
    same path in a binary file, in an untracked file, or written relative is not."""
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "metrics.json").write_text(json.dumps({"checkpoint": PLANTED, "data": "data/x"}))
    (tmp_path / "notes.md").write_text(f"trained on `{PLANTED_HOME}`, see {NOT_PLANTED}\n")
    (tmp_path / "clean.md").write_text(strip_machine_paths(f"copied from {PLANTED}")[0] + "\n")
    (tmp_path / "picture.png").write_bytes(b"\x89PNG\x00" + PLANTED.encode())
    subprocess.run(["git", "add", "."], cwd=tmp_path, check=True)
    (tmp_path / "untracked.md").write_text(PLANTED)
    assert tree_report(tmp_path) == {"notes.md": [PLANTED_HOME], "results/metrics.json": [PLANTED]}
    assert (tmp_path / "clean.md").read_text() == "copied from runs/seed0/best.pt\n"


def test_shipped_checkpoint_holds_no_machine_path():
    """The pretrained checkpoint's metadata records its data folder relative (data/paper)."""
    assert checkpoint_report(CHECKPOINT) == []
    ckpt = torch.load(CHECKPOINT, map_location="cpu", weights_only=True)
    assert ckpt["dataset"]["folder"] == "data/paper"


def test_checkpoint_scan_fails_on_a_planted_path(tmp_path: Path):
    """A copy of the checkpoint whose dataset folder is a machine path is reported, by key and in its pickle."""
    ckpt = torch.load(CHECKPOINT, map_location="cpu", weights_only=True)
    ckpt["dataset"]["folder"] = PLANTED_HOME
    planted = tmp_path / "planted.pt"
    torch.save(ckpt, planted)
    by_key, in_pickle = checkpoint_report(planted)  # the pickle's next opcode may run on after the path
    assert by_key == f"/dataset/folder: {PLANTED_HOME}"
    assert in_pickle.startswith(f"planted/data.pkl: {PLANTED_HOME}")


def test_recorded_paths_are_relative(tmp_path: Path, monkeypatch):
    """The learner records a path relative to the working folder, with .. where it lies outside."""
    inside, outside = tmp_path / "work", tmp_path / "elsewhere"
    inside.mkdir()
    monkeypatch.chdir(inside)
    assert recorded_path(inside / "data" / "paper") == "data/paper"
    assert recorded_path("runs/./a") == "runs/a"
    assert recorded_path(outside / "data") == "../elsewhere/data"


def test_training_records_no_machine_path(tiny_dataset, tmp_path: Path, monkeypatch):
    """Trained with absolute --data and --out, the run's checkpoint, config.json and summary.json
    hold them relative to the working folder."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    run = work / "runs" / "a"
    quick = TrainConfig(epochs=1, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=4)
    model = ModelConfig(name="polar_unet", frames=3, width=4)
    recipe = LearnConfig(model=model, data=DataConfig(frames=3), train=quick)
    train(Path(tiny_dataset).absolute(), run, recipe, progress=False)
    folder = os.path.relpath(tiny_dataset, work)
    ckpt = torch.load(run / "best.pt", map_location="cpu", weights_only=True)
    config = json.loads((run / "config.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    assert ckpt["dataset"]["folder"] == config["dataset"]["folder"] == summary["dataset"]["folder"] == folder
    assert summary["out"] == "runs/a"
    assert checkpoint_report(run / "best.pt") == []
    assert machine_paths((run / "config.json").read_text() + (run / "summary.json").read_text()) == []


# --- the README's figures and the results index ---------------------------------------------------

INDEX = ROOT / "benchmarks" / "results" / "README.md"
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def local_links(markdown: Path, root: Path = ROOT) -> list[str]:
    """Repository paths (relative to `root`, normalised) of every markdown link and image in a file,
    without web links and in-page anchors."""
    found = []
    for target in LINK.findall(markdown.read_text()):
        target = target.split("#")[0]
        if not target or "://" in target or target.startswith("mailto:"):
            continue
        found.append(os.path.relpath(os.path.normpath(markdown.parent / target), root))
    return found


def unindexed(readme: Path, index: Path, root: Path = ROOT) -> list[str]:
    """The README's pictures and result files that the index does not link (the index itself aside)."""
    indexed = set(local_links(index, root)) | {os.path.relpath(index, root)}
    figures = [p for p in local_links(readme, root) if p.endswith(".png") or p.startswith("benchmarks/results/")]
    return [p for p in figures if p not in indexed and p.rstrip("/") not in indexed]


def test_readme_and_index_links_resolve():
    """Every link of the README and of the results index names a file or folder of the tree."""
    missing = [
        f"{doc.relative_to(ROOT)} -> {p}"
        for doc in (ROOT / "README.md", INDEX)
        for p in local_links(doc)
        if not (ROOT / p).exists()
    ]
    assert missing == []


def test_every_readme_figure_is_indexed():
    """Each picture of the README and each result file it links has its entry in the index."""
    assert unindexed(ROOT / "README.md", INDEX) == []


def test_index_check_fails_on_a_planted_figure(tmp_path: Path):
    """A README picture and a result link missing from the index are named; indexed ones are not."""
    docs = tmp_path / "docs"
    docs.mkdir()
    readme, index = tmp_path / "README.md", tmp_path / "index.md"
    readme.write_text("![a](docs/a.png) ![b](docs/b.png) [r](benchmarks/results/x.md) [web](https://x.org/c.png)\n")
    index.write_text("[a](docs/a.png)\n")
    assert unindexed(readme, index, tmp_path) == ["docs/b.png", "benchmarks/results/x.md"]
