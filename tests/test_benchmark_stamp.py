"""Every benchmark result says where it came from: benchmarks/provenance.py and the writers that use it.

The helper is checked against git itself (blob ids, commits, dirty trees) in throw-away
repositories, including a copy without `.git` and a copy whose `.git` names an older commit (as
the lent GPU machine's did). The writers are checked by reading their source: JSON results go
through `write_json`, every module that writes files uses the helper, every study script stamps
its calls; the checker itself is shown to catch planted offenders.
"""

from __future__ import annotations

import ast
import json
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import provenance  # noqa: E402

BENCHMARKS = ROOT / "benchmarks"
WRITES = ("write_text", "write_bytes", "savefig", "dump")
EXEMPT = "# not a result:"


def git(folder: Path, *args: str) -> str:
    env = {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    done = subprocess.run(["git", *args], cwd=folder, capture_output=True, text=True, check=True, env=env)
    return done.stdout.strip()


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    """A git repository of two files in two commits."""
    folder = tmp_path / "repo"
    folder.mkdir()
    git(folder, "init", "-q")
    (folder / "a.txt").write_text("first\n")
    (folder / "sub").mkdir()
    (folder / "sub" / "b.py").write_text("x = 1\n")
    git(folder, "add", ".")
    git(folder, "commit", "-qm", "one")
    (folder / "a.txt").write_text("second\n")
    git(folder, "commit", "-qam", "two")
    return folder


def test_blob_id_is_gits():
    """The blob id of some bytes equals `git hash-object` of a file holding them."""
    data = b"sonar\x00lidar\n" * 7
    got = provenance.blob_id(data)
    want = subprocess.run(["git", "hash-object", "--stdin"], input=data, capture_output=True, check=True)
    assert got == want.stdout.decode().strip()


def test_source_from_git(repo: Path):
    """In a checkout: HEAD's id; clean, then dirty naming the edited file (untracked files do not count)."""
    head = git(repo, "rev-parse", "HEAD")
    (repo / "new.txt").write_text("untracked\n")
    assert provenance.source(repo, environ={}) | {"from": None} == {
        "commit": head,
        "dirty": False,
        "changed_files": [],
        "from": None,
    }
    (repo / "sub" / "b.py").write_text("x = 2\n")
    found = provenance.source(repo, environ={})
    assert (found["commit"], found["dirty"], found["changed_files"], found["from"]) == (head, True, ["sub/b.py"], "git")


def test_source_of_a_copy_without_git(repo: Path, tmp_path: Path):
    """A copy without .git: the source file names the commit, and an edit made after it was written
    (or a deleted file) makes the copy dirty; without the file the commit is not recorded."""
    head = git(repo, "rev-parse", "HEAD")
    provenance.write_source(repo / ".provenance.json", repo)
    copy = tmp_path / "copy"
    shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git"))
    found = provenance.source(copy, environ={})
    assert (found["commit"], found["dirty"], found["changed_files"]) == (head, False, [])
    assert found["from"].startswith(".provenance.json")
    (copy / "a.txt").write_text("edited on the device\n")
    (copy / "sub" / "b.py").unlink()
    found = provenance.source(copy, environ={})
    assert (found["commit"], found["dirty"], found["changed_files"]) == (head, True, ["a.txt", "sub/b.py"])
    (copy / ".provenance.json").unlink()
    assert provenance.source(copy, environ={})["commit"] == provenance.NOT_RECORDED


def test_a_copy_may_go_without_the_folders_it_names(repo: Path, tmp_path: Path):
    """Folders named left behind (results too large to ship) may be absent from the copy without
    making it dirty; a file there that is present but edited still does, and so does a file gone
    from any other folder."""
    provenance.write_source(repo / ".provenance.json", repo, left_behind=("sub",))
    copy = tmp_path / "copy"
    shutil.copytree(repo, copy, ignore=shutil.ignore_patterns(".git", "sub"))
    assert provenance.source(copy, environ={})["dirty"] is False
    (copy / "sub").mkdir()
    (copy / "sub" / "b.py").write_text("x = 3\n")
    assert provenance.source(copy, environ={})["changed_files"] == ["sub/b.py"]
    (copy / "sub" / "b.py").unlink()
    (copy / "a.txt").unlink()
    assert provenance.source(copy, environ={})["changed_files"] == ["a.txt"]


def test_source_prefers_what_matches_the_tree(repo: Path, tmp_path: Path):
    """A copy whose .git still names the first commit while its files are the second's: the source
    file (no changed files) wins over git (one changed file); the environment wins over both."""
    first, second = git(repo, "rev-list", "--reverse", "HEAD").split()
    provenance.write_source(repo / ".provenance.json", repo)
    copy = tmp_path / "copy"
    shutil.copytree(repo, copy)
    git(copy, "reset", "-q", "--soft", first)  # .git at the first commit, files at the second
    assert provenance.git_source(copy)["commit"] == first
    assert provenance.source(copy, environ={})["commit"] == second
    chosen = provenance.source(copy, environ={"SONAR2LIDAR_COMMIT": "abc123", "SONAR2LIDAR_DIRTY": "1"})
    assert (chosen["commit"], chosen["dirty"], chosen["from"]) == ("abc123", True, "SONAR2LIDAR_COMMIT")
    assert provenance.source(copy, environ={"SONAR2LIDAR_COMMIT": "abc123"})["dirty"] == provenance.NOT_RECORDED


def test_source_ignores_a_checkout_around_the_tree(repo: Path):
    """A tree copied into a folder of some other checkout is not that checkout's commit."""
    inner = repo / "copied_tree"
    inner.mkdir()
    assert provenance.git_source(inner) is None


def test_packages_reads_imported_modules():
    """Versions of the modules given (torch with the CUDA it was built for), numpy and warp always."""
    torch = types.SimpleNamespace(__version__="9.9.9", version=types.SimpleNamespace(cuda="13.0"))
    found = provenance.packages({"torch": torch, "h5py": types.SimpleNamespace(__version__="3.1")})
    assert (found["torch"], found["torch_cuda"], found["h5py"]) == ("9.9.9", "13.0", "3.1")
    assert {"python", "numpy", "warp"} <= set(found) and "open3d" not in found


def test_gpus_from_nvidia_smi(monkeypatch):
    """nvidia-smi's answers as seen on a lent H200 (driver 580.159.04, CUDA 13.0) are read into cards,
    driver and CUDA version; without nvidia-smi there are none."""
    answers = {
        "--query-gpu=index,name,memory.total,driver_version": "0, NVIDIA H200, 143771 MiB, 580.159.04\n",
        "": "| NVIDIA-SMI 580.159.04             Driver Version: 580.159.04     CUDA Version: 13.0     |\n",
    }
    monkeypatch.setattr(provenance, "_run", lambda cmd, cwd=None: answers[cmd[1] if len(cmd) > 1 else ""])
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    cards = provenance.gpus()
    assert cards == {
        "gpus": [{"index": 0, "name": "NVIDIA H200", "memory": "143771 MiB", "driver": "580.159.04"}],
        "driver": "580.159.04",
        "cuda_driver": "13.0",
    }
    assert provenance.device_name("cuda:0", cards) == "NVIDIA H200"
    monkeypatch.setattr(provenance, "_run", lambda cmd, cwd=None: None)
    assert provenance.gpus() == {}


def test_device_names(monkeypatch):
    """cuda:i is the i-th visible card; the CPU is named by its model."""
    cards = {"gpus": [{"index": 0, "name": "A"}, {"index": 3, "name": "B"}]}
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert (provenance.device_name("cuda:0", cards), provenance.device_name("cuda", cards)) == ("A", "A")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")
    assert provenance.device_name("cuda:0", cards) == "B"
    assert provenance.device_name("cpu", {}) == provenance.machine()["cpu"]
    assert provenance.device_name(None, cards) == provenance.NOT_RECORDED


def test_write_json_stamps_the_record(tmp_path: Path):
    """The written JSON holds the record and a provenance with this checkout's commit, the device,
    driver fields, the machine and versions; the markdown line names the commit."""
    out = tmp_path / "result.json"
    provenance.write_json(out, {"frames_per_s": 12.5}, device="cpu")
    written = json.loads(out.read_text())
    prov = written["provenance"]
    assert written["frames_per_s"] == 12.5
    assert prov["commit"] == git(ROOT, "rev-parse", "HEAD")
    assert isinstance(prov["dirty"], bool)
    assert prov["device"] == "cpu" and prov["device_name"] == provenance.machine()["cpu"]
    assert {"driver", "cuda_driver", "gpus", "written", "script"} <= set(prov)
    assert prov["machine"]["cores"] >= 1 and prov["packages"]["python"] == sys.version.split()[0]
    assert prov["commit"][:12] in provenance.markdown(prov)


def test_relative_paths(tmp_path: Path, monkeypatch):
    """Recorded paths are relative to the working folder, also when outside it."""
    monkeypatch.chdir(tmp_path)
    assert provenance.relative(tmp_path / "runs" / "a") == "runs/a"
    assert provenance.relative("data/x") == "data/x"
    assert not provenance.relative("/elsewhere/data").startswith("/")


# --- the writers ---------------------------------------------------------------------------------


def writer_problems(source: str) -> list[str]:
    """What keeps a benchmarks module's source from stamping its results: JSON written other than
    through write_json (unless its line says EXEMPT), or files written without the helper."""
    tree = ast.parse(source)
    lines = source.splitlines()
    problems, writes = [], False
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        name = node.func.attr
        writes |= name in WRITES
        json_text = any(
            isinstance(a, ast.Call) and isinstance(a.func, ast.Attribute) and a.func.attr == "dumps" for a in node.args
        )
        raw_json = (name == "write_text" and json_text) or (
            name == "dump" and isinstance(node.func.value, ast.Name) and node.func.value.id == "json"
        )
        if raw_json and EXEMPT not in lines[node.lineno - 1]:
            problems.append(f"line {node.lineno}: JSON written without provenance.write_json")
    uses_helper = any(
        isinstance(node, ast.ImportFrom) and node.module in ("benchmarks.provenance", "provenance")
        for node in ast.walk(tree)
    )
    if writes and not uses_helper:
        problems.append("writes files but never uses benchmarks.provenance")
    return problems


def test_checker_catches_planted_writers():
    """A raw json.dumps into write_text, a json.dump, and a markdown writer without the helper are
    caught; write_json and an exempted scratch file are not."""
    raw = "import json\nfrom benchmarks.provenance import write_json\np.write_text(json.dumps(r))\n"
    dump = "import json\nfrom benchmarks.provenance import write_json\njson.dump(r, f)\n"
    md_only = "p.write_text(text)\n"
    good = "from benchmarks.provenance import write_json\nwrite_json(p, r)\n"
    exempt = f"import json\nfrom benchmarks.provenance import write_json\np.write_text(json.dumps(r))  {EXEMPT} x\n"
    assert writer_problems(raw) == ["line 3: JSON written without provenance.write_json"]
    assert writer_problems(dump) == ["line 3: JSON written without provenance.write_json"]
    assert writer_problems(md_only) == ["writes files but never uses benchmarks.provenance"]
    assert writer_problems(good) == writer_problems(exempt) == []


@pytest.mark.parametrize("module", sorted(p.name for p in BENCHMARKS.glob("*.py")))
def test_every_benchmark_writer_stamps(module):
    """Each module under benchmarks/ that writes files stamps them (provenance.py is the helper)."""
    if module == "provenance.py":
        return
    assert writer_problems((BENCHMARKS / module).read_text()) == []


def test_every_study_script_stamps_its_calls():
    """Each shell script under benchmarks/ writes the provenance of its call beside what it writes."""
    scripts = sorted(BENCHMARKS.glob("*.sh"))
    assert scripts
    missing = [s.name for s in scripts if not re.search(r"python3? benchmarks/provenance\.py write", s.read_text())]
    assert missing == []
