"""benchmarks/sonar_same_job.py without a GPU: revisions are named and exported as git has them,
a child process imports the exported simulator and not the working tree's, and the table reports
medians over rounds with ratios of each revision to every earlier one. The exports read a
two-commit repository made here, so the tests pass in a shallow clone (only HEAD of this one)."""

import argparse
import json
import subprocess
import sys

import pytest

from benchmarks import sonar_same_job

ROOT = sonar_same_job.ROOT
SIMULATOR = ("acoustic_sim/__init__.py", "acoustic_sim/config.py", "scenes/__init__.py")


def git(*args, cwd=ROOT):
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, check=True).stdout


@pytest.fixture
def history(tmp_path):
    """A repository of two commits: the second changes acoustic_sim/config.py and adds
    acoustic_sim/engine/signals.py and clitools/; learn/ (not the simulator) is in both. Returns its folder."""
    repo = tmp_path / "repo"
    files = {
        "acoustic_sim/__init__.py": "from .config import TAPS\n",
        "acoustic_sim/config.py": "TAPS = 8\n",
        "scenes/__init__.py": "",
        "learn/__init__.py": "",
    }
    git("init", "-q", str(repo), cwd=tmp_path)
    later = {
        "acoustic_sim/config.py": "TAPS = 4\n",
        "acoustic_sim/engine/signals.py": "# taps\n",
        "clitools/__init__.py": "",
    }
    for change in ({}, later):
        for path, text in (files | change).items():
            (repo / path).parent.mkdir(parents=True, exist_ok=True)
            (repo / path).write_text(text)
        git("add", "-A", cwd=repo)
        identity = ["-c", "user.name=test", "-c", "user.email=test@example.com", "-c", "commit.gpgsign=false"]
        git(*identity, "commit", "-qm", "a commit", cwd=repo)
    return repo


def test_revisions_keep_their_order_and_names():
    assert list(sonar_same_job.parse_revs(["base=8debdf9", "now=HEAD", "x=a=b"]).items()) == [
        ("base", "8debdf9"),
        ("now", "HEAD"),
        ("x", "a=b"),
    ]


@pytest.mark.parametrize(
    "items", [["base=HEAD"], ["base=HEAD", "base=HEAD~1"], ["base=HEAD", "now"], ["../up=HEAD", "a=b"]]
)
def test_revisions_need_distinct_identifier_names_and_two_at_least(items):
    with pytest.raises(SystemExit):
        sonar_same_job.parse_revs(items)


@pytest.mark.parametrize("rev", ["HEAD", "HEAD~1"])
def test_export_is_the_commits_simulator(tmp_path, history, rev):
    """Each commit's own files (the two differ in config.py), the simulator only, and its full id."""
    commit = sonar_same_job.export(rev, tmp_path / "tree", repo=history)
    assert commit == git("rev-parse", rev, cwd=history).decode().strip()
    for path in SIMULATOR:
        assert (tmp_path / "tree" / path).read_bytes() == git("show", f"{rev}:{path}", cwd=history)
    assert (tmp_path / "tree" / "acoustic_sim/engine/signals.py").exists() == (rev == "HEAD")
    assert (tmp_path / "tree" / "clitools/__init__.py").exists() == (rev == "HEAD")  # where the commit has it
    assert not (tmp_path / "tree" / "learn").exists()  # the simulator only


def test_the_two_commits_differ(history):
    """Keeps the export test meaningful: a copy of one commit would fail it for the other."""
    older, newer = (git("show", f"{rev}:acoustic_sim/config.py", cwd=history) for rev in ("HEAD~1", "HEAD"))
    assert older != newer


def test_export_of_this_repository_by_default(tmp_path):
    """Without `repo`, the benchmark's own repository (HEAD, which a shallow clone has)."""
    commit = sonar_same_job.export("HEAD", tmp_path / "tree")
    assert commit == git("rev-parse", "HEAD").decode().strip()
    for path in SIMULATOR:
        assert (tmp_path / "tree" / path).read_bytes() == git("show", f"HEAD:{path}")
    assert not (tmp_path / "tree" / "learn").exists()


def test_a_bad_revision_is_one_clear_error(tmp_path, history):
    with pytest.raises(SystemExit, match="no-such-revision"):
        sonar_same_job.export("no-such-revision", tmp_path / "bad", repo=history)


@pytest.mark.parametrize("outer", [None, str(ROOT)])
def test_the_child_imports_the_exported_tree(tmp_path, history, monkeypatch, outer):
    """Run from the working tree (its own acoustic_sim first on sys.path), with or without it on
    PYTHONPATH, the child's simulator comes from the export."""
    sonar_same_job.export("HEAD~1", tmp_path / "tree", repo=history)
    if outer is None:
        monkeypatch.delenv("PYTHONPATH", raising=False)
    else:
        monkeypatch.setenv("PYTHONPATH", outer)
    code = f"from benchmarks.sonar_same_job import load_simulator; print(*load_simulator({str(tmp_path / 'tree')!r}))"
    printed = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    result = {"imported": printed.stdout.split()}
    assert len(result["imported"]) == 2
    assert sonar_same_job.imported_from(result, tmp_path / "tree")
    assert not sonar_same_job.imported_from(
        {"imported": [str(ROOT / "acoustic_sim"), str(ROOT / "scenes")]}, tmp_path / "tree"
    )


def test_table_is_median_of_rounds_with_ratios_to_every_earlier_revision(tmp_path):
    args = argparse.Namespace(device="cpu", bounces=3, pings=256, batches=8, rounds=3, out=str(tmp_path))
    revs = {"base": "8debdf9", "mid": "a1936a1", "now": "HEAD"}
    commits = {name: c * 40 for name, c in zip(revs, "abc", strict=True)}

    def rounds(*rates):
        return [{"20000": {"energyscapes_per_s": r}} for r in rates]

    runs = {"base": rounds(90.0, 100.0, 400.0), "mid": rounds(120.0, 125.0, 130.0), "now": rounds(150.0, 140.0, 160.0)}
    sonar_same_job.write(args, revs, commits, runs, [20000])
    table = (tmp_path / "sonar_same_job_cpu.md").read_text()
    assert "| rays per ping | base | mid | now | mid / base | now / base | now / mid |" in table
    assert "| 20,000 | 100 | 125 | 150 | 1.25x | 1.50x | 1.20x |" in table
    saved = json.loads((tmp_path / "sonar_same_job_cpu.json").read_text())
    assert saved["energyscapes_per_s"]["20000"]["base"]["rounds"] == [90.0, 100.0, 400.0]
    assert saved["revisions"]["now"] == {"rev": "HEAD", "commit": "c" * 40}


@pytest.mark.parametrize("bad", [["--rounds", "0"], ["--rays", "20000,,1"], ["--rays", "0"]])
def test_bad_settings_are_refused_before_any_work(bad, capsys):
    with pytest.raises(SystemExit):
        sonar_same_job.main(["--revs", "a=HEAD", "--revs", "b=HEAD", *bad])
    assert "error" in capsys.readouterr().err


def test_an_exported_folder_stands_for_its_commit(tmp_path, history):
    """On a machine without git, the folder an export wrote (here, with git) is the revision: the
    same files and the commit it recorded; a folder without that record is not taken for one."""
    commit = sonar_same_job.export("HEAD~1", tmp_path / "carried", repo=history)
    again = sonar_same_job.export(str(tmp_path / "carried"), tmp_path / "tree", repo=history)
    assert again == commit
    for path in SIMULATOR:
        assert (tmp_path / "tree" / path).read_bytes() == git("show", f"HEAD~1:{path}", cwd=history)
    (tmp_path / "plain" / "acoustic_sim").mkdir(parents=True)
    with pytest.raises(SystemExit, match="revision"):
        sonar_same_job.export(str(tmp_path / "plain"), tmp_path / "other", repo=history)
