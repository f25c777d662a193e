"""Where a benchmark result came from: commit, tree state, machine, device, driver and package versions.

Every writer of results under benchmarks/ passes its record through `write_json` (or `stamp`),
which adds a "provenance" entry, and ends its markdown with `markdown(...)`. tests/test_benchmark_stamp.py
checks that each one does.

The commit and whether the tree was dirty (a tracked file differs from the commit; untracked files
do not count) come from SONAR2LIDAR_COMMIT (and SONAR2LIDAR_DIRTY=0|1) where it is set; otherwise
from whichever of these two is closer to the files actually present (fewer changed files; git on a tie):
- git (`git rev-parse HEAD`, `git status --porcelain --untracked-files=no`);
- `.provenance.json` at the repository root, which `python benchmarks/provenance.py source` writes
  from the git checkout: the commit and the git blob id of every tracked file, so dirtiness is
  checked file by file against that commit wherever the tree is (an edit made after the file was
  written still counts).
The lent GPU machine receives a copy of the working tree, and the `.git` that came with it was
seen naming an older commit than the tree it held (the session's first, 35d2fa3, for a tree at
54cfdaf): git alone would misname the code there. So before a device call run
`python benchmarks/provenance.py source` here and name the file in the call's carry
(`carry: [".provenance.json"]`; git ignores it through the root's `/*.json`), or export
SONAR2LIDAR_COMMIT in the command. Without any of them the commit is "not recorded".

Nothing here imports Warp, torch or CUDA libraries: versions are read from modules the benchmark
already imported, the driver from `nvidia-smi` in a subprocess (loading libcuda here would change
how `generate` starts its workers).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE_FILE = ROOT / ".provenance.json"
NOT_RECORDED = "not recorded"
# Modules whose versions a result depends on, recorded when the benchmark imported them.
PACKAGES = {
    "numpy": "numpy",
    "scipy": "scipy",
    "h5py": "h5py",
    "warp": "warp-lang",
    "torch": "torch",
    "trimesh": "trimesh",
    "open3d": "open3d",
    "embreex": "embreex",
    "pyroomacoustics": "pyroomacoustics",
    "onnxruntime": "onnxruntime",
    "ray": "ray",
}
ALWAYS = ("numpy", "warp")  # the simulator's own: recorded even where only a child process imported them


def _run(cmd: list[str], cwd: Path = ROOT) -> str | None:
    """stdout of `cmd`, or None where the program is missing or fails."""
    try:
        done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def blob_id(data: bytes) -> str:
    """The id git gives a file of these bytes (`git hash-object`)."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def changed_files(blobs: dict[str, str], root: Path = ROOT, left_behind: tuple[str, ...] = ()) -> list[str]:
    """Tracked paths (of `blobs`: path -> blob id at the commit) whose file under `root` differs or
    is gone; gone from a folder of `left_behind` (not shipped with the copy) does not count."""
    changed = []
    for path, blob in sorted(blobs.items()):
        file = root / path
        if file.is_symlink():
            data = os.readlink(file).encode()
        elif file.is_file():
            data = file.read_bytes()
        else:
            if not any(path.startswith(folder.rstrip("/") + "/") for folder in left_behind):
                changed.append(path)
            continue
        if blob_id(data) != blob:
            changed.append(path)
    return changed


def git_source(root: Path = ROOT) -> dict | None:
    """Commit and tracked changes from git, or None where `root` is not the top of a git checkout."""
    top = _run(["git", "rev-parse", "--show-toplevel"], root)
    if top is None or Path(top.strip()).resolve() != root.resolve():  # no checkout, or one around a copy
        return None
    commit = _run(["git", "rev-parse", "HEAD"], root)
    status = _run(["git", "status", "--porcelain", "--untracked-files=no"], root)
    if commit is None or status is None:
        return None
    changed = [line[3:] for line in status.splitlines() if line.strip()]
    return {"commit": commit.strip(), "dirty": bool(changed), "changed_files": changed, "from": "git"}


def tracked_blobs(root: Path = ROOT) -> dict[str, str]:
    """{path: blob id} of every file of the commit at `root` (`git ls-tree -r HEAD`)."""
    listing = _run(["git", "ls-tree", "-r", "-z", "HEAD"], root) or ""
    blobs = {}
    for entry in listing.split("\0"):
        if entry:
            meta, path = entry.split("\t", 1)
            _mode, kind, blob = meta.split()
            if kind == "blob":
                blobs[path] = blob
    return blobs


def write_source(path: Path = SOURCE_FILE, root: Path = ROOT, left_behind: tuple[str, ...] = ()) -> dict:
    """Writes the commit and its files' blob ids for a copy of this tree that has no `.git`, and the
    tracked folders the copy goes without (e.g. committed results, where a copy's size is limited)."""
    source = git_source(root)
    if source is None:
        raise SystemExit(f"{root} is not a git checkout: nothing to record")
    record = {"commit": source["commit"], "written": _now(), "blobs": tracked_blobs(root)}
    record["left_behind"] = list(left_behind)
    path.write_text(json.dumps(record, indent=0))
    return record


def file_source(path: Path = SOURCE_FILE, root: Path = ROOT) -> dict | None:
    """Commit from the file `write_source` wrote; dirty where a tracked file here differs from it."""
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    changed = changed_files(record["blobs"], root, tuple(record.get("left_behind", ())))
    written = record.get("written", "?")
    return {
        "commit": record["commit"],
        "dirty": bool(changed),
        "changed_files": changed,
        "from": f"{path.name} ({written})",
    }


def env_source(environ=os.environ) -> dict | None:
    """Commit from SONAR2LIDAR_COMMIT, dirty from SONAR2LIDAR_DIRTY (0/1)."""
    commit = environ.get("SONAR2LIDAR_COMMIT", "").strip()
    if not commit:
        return None
    dirty = environ.get("SONAR2LIDAR_DIRTY", "").strip().lower()
    flag = {"0": False, "false": False, "no": False, "1": True, "true": True, "yes": True}.get(dirty, NOT_RECORDED)
    return {"commit": commit, "dirty": flag, "changed_files": [], "from": "SONAR2LIDAR_COMMIT"}


def source(root: Path = ROOT, environ=os.environ, source_file: Path | None = None) -> dict:
    """The commit the tree at `root` is, and whether it was dirty (see the module's docstring)."""
    explicit = env_source(environ)
    if explicit:
        return explicit
    found = [s for s in (git_source(root), file_source(source_file or root / SOURCE_FILE.name, root)) if s]
    if not found:
        return {"commit": NOT_RECORDED, "dirty": NOT_RECORDED, "changed_files": [], "from": "nowhere"}
    return min(found, key=lambda s: len(s["changed_files"]))  # min keeps the first (git) on a tie


def gpus() -> dict:
    """NVIDIA GPUs, driver and the CUDA version the driver supports, from nvidia-smi ({} without one)."""
    listing = _run(["nvidia-smi", "--query-gpu=index,name,memory.total,driver_version", "--format=csv,noheader"])
    if not listing:
        return {}
    cards = []
    for line in listing.strip().splitlines():
        index, name, memory, driver = (part.strip() for part in line.split(","))
        cards.append({"index": int(index), "name": name, "memory": memory, "driver": driver})
    header = _run(["nvidia-smi"]) or ""
    cuda = re.search(r"CUDA Version:\s*([\d.]+)", header)
    return {
        "gpus": cards,
        "driver": cards[0]["driver"] if cards else NOT_RECORDED,
        "cuda_driver": cuda.group(1) if cuda else NOT_RECORDED,
    }


def machine() -> dict:
    """CPU model, cores (all, and those this process may use), memory [GiB] and operating system."""
    model = platform.processor() or NOT_RECORDED
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        found = re.search(r"^model name\s*:\s*(.+)$", cpuinfo.read_text(), re.M)
        model = found.group(1).strip() if found else model
    memory = NOT_RECORDED
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        found = re.search(r"^MemTotal:\s*(\d+) kB", meminfo.read_text(), re.M)
        memory = round(int(found.group(1)) / 2**20, 1) if found else memory
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "memory_gib": memory,
        "os": platform.platform(),
    }


def packages(modules=None) -> dict:
    """Python, the installed numpy and Warp (read without importing them), and the version of every
    other package of PACKAGES that `modules` (default: those imported so far) holds."""
    modules = sys.modules if modules is None else modules
    found = {"python": platform.python_version()}
    for module, dist in PACKAGES.items():
        version = getattr(modules[module], "__version__", None) if module in modules else None
        if version is None and (module in modules or module in ALWAYS):
            try:
                version = importlib.metadata.version(dist)
            except importlib.metadata.PackageNotFoundError:
                version = "not installed" if module not in modules else NOT_RECORDED
        if version is not None:
            found[module] = str(version)
    torch = modules.get("torch")
    if torch is not None and getattr(torch, "version", None) is not None:
        found["torch_cuda"] = str(torch.version.cuda)  # the CUDA torch was built for; None for CPU builds
    return found


def device_name(device: str | None, cards: dict) -> str:
    """A readable name for a device string such as "cuda:1" or "cpu"."""
    if device is None:
        return NOT_RECORDED
    if device.startswith("cuda"):
        index = int(device.split(":")[1]) if ":" in device else 0
        names = {card["index"]: card["name"] for card in cards.get("gpus", [])}
        visible = os.environ.get("CUDA_VISIBLE_DEVICES", "")
        if visible and visible.split(",")[index : index + 1]:  # cuda:i is the i-th visible card
            chosen = visible.split(",")[index]
            index = int(chosen) if chosen.isdigit() else index
        return names.get(index, NOT_RECORDED)
    return machine()["cpu"] if device.startswith("cpu") else device


def provenance(device: str | None = None, script: str | None = None) -> dict:
    """Everything a reader needs to place a result: commit, dirty, date, machine, device, driver, packages."""
    cards = gpus()
    where = source()
    return {
        "commit": where["commit"],
        "dirty": where["dirty"],
        "changed_file_count": len(where["changed_files"]),
        "changed_files": where["changed_files"][:20],
        "commit_from": where["from"],
        "written": _now(),
        "script": script or _script(),
        "argv": [strip_machine_paths(arg)[0] for arg in sys.argv[1:]],
        "device": device or NOT_RECORDED,
        "device_name": device_name(device, cards),
        "driver": cards.get("driver", NOT_RECORDED),
        "cuda_driver": cards.get("cuda_driver", NOT_RECORDED),
        "gpus": cards.get("gpus", []),
        "machine": machine(),
        "packages": packages(),
    }


def stamp(record: dict, device: str | None = None) -> dict:
    """`record` with its "provenance" entry (a copy; the record's own keys win over nothing)."""
    return {**record, "provenance": provenance(device)}


def write_json(path: str | Path, record: dict, device: str | None = None) -> dict:
    """Writes `record` stamped with its provenance as JSON at `path`; returns the stamped record."""
    stamped = stamp(record, device)
    Path(path).write_text(json.dumps(stamped, indent=1, default=str) + "\n")
    return stamped


def markdown(prov: dict) -> str:
    """One line for the end of a result's markdown: where and from which code it was measured."""
    commit = prov["commit"][:12] if prov["commit"] != NOT_RECORDED else NOT_RECORDED
    dirty = {True: "with uncommitted changes", False: "clean"}.get(prov["dirty"], "tree state not recorded")
    versions = ", ".join(f"{k} {v}" for k, v in prov["packages"].items())
    on = f"{prov['device_name']} ({prov['device']})" if prov["device"] != NOT_RECORDED else prov["machine"]["cpu"]
    driver = f", driver {prov['driver']} (CUDA {prov['cuda_driver']})" if prov["driver"] != NOT_RECORDED else ""
    return (
        f"Provenance: `{prov['script']}` at commit {commit} ({dirty}) on {on}{driver}, "
        f"{prov['machine']['cores']} cores, {prov['written']}; {versions}."
    )


# A machine's absolute path: one of the roots where work folders, homes and caches live, with at
# least one folder or file below it, not inside a longer path or a URL.
MACHINE_PATH = re.compile(
    r"(?<![\w.~/$-])/(?:root|tmp|work|home|Users|mnt|scratch|opt|srv|media|private|var/tmp|var/folders)"
    r"(?:/[\w.+@%=-]+)+/?"
)


def machine_paths(text: str) -> list[str]:
    """Every machine's absolute path in `text` (see MACHINE_PATH), in order."""
    return [m.group(0) for m in MACHINE_PATH.finditer(text)]


def relative_form(path: str) -> str:
    """A machine path without the machine: the root and the work folder under it go (a home's user
    too), so ROOT/w14/runs/a reads `runs/a` (ROOT: root, tmp, work...), home/USER/repo/learn/x.py reads
    `learn/x.py`, and a lone tmp/ce500 reads `ce500`."""
    parts = path.strip("/").split("/")
    drop = 2 if parts[0] in ("home", "Users") or parts[0] == "var" else 1  # /home/<user>, /var/<kind>
    drop += 1 if len(parts) > drop + 1 else 0  # the work folder, where something lies below it
    return "/".join(parts[drop:]) + ("/" if path.endswith("/") else "")


def strip_machine_paths(text: str) -> tuple[str, int]:
    """`text` with every machine path in its relative form, and how many were replaced."""
    return MACHINE_PATH.subn(lambda m: relative_form(m.group(0)), text)


def tracked_text_files(root: Path = ROOT) -> list[Path]:
    """Every file git tracks under `root` that reads as UTF-8 text (no NUL byte: PNGs, checkpoints and
    HDF5 files are skipped)."""
    listing = _run(["git", "ls-files", "-z"], root) or ""
    found = []
    for name in filter(None, listing.split("\0")):
        path = root / name
        if not path.is_file() or path.is_symlink():
            continue
        data = path.read_bytes()
        if b"\0" in data:
            continue
        try:
            data.decode()
        except UnicodeDecodeError:
            continue
        found.append(path)
    return found


def relative(path: str | Path, start: str | Path | None = None) -> str:
    """`path` as a record should hold it: relative to `start` (default: the working folder), never a
    machine's absolute path."""
    return os.path.relpath(Path(path).absolute(), Path(start or os.getcwd()).absolute())


def _script() -> str:
    main = getattr(sys.modules.get("__main__"), "__file__", None)
    if not main:
        return NOT_RECORDED
    try:
        return Path(main).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return Path(main).name


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    src = sub.add_parser(
        "source", help=f"write {SOURCE_FILE.name} (commit, blob ids) for a copy of this tree without .git"
    )
    src.add_argument(
        "--left-behind",
        action="append",
        default=[],
        metavar="FOLDER",
        help="a tracked folder the copy goes without (its files' absence does not make the copy dirty)",
    )
    show = sub.add_parser("show", help="print the provenance of this tree and machine as JSON")
    show.add_argument("--device", default=None, help="the device a result was measured on, e.g. cuda:0")
    write = sub.add_parser("write", help="write the provenance as JSON beside results a shell script made")
    write.add_argument("out", type=Path, help="the JSON file to write, e.g. RESULTS/provenance.json")
    write.add_argument("--device", default=None)
    paths = sub.add_parser("paths", help="list tracked text files that hold a machine's absolute path")
    paths.add_argument("--fix", action="store_true", help="rewrite each such path in its relative form")
    args = parser.parse_args(argv)
    if args.command == "source":
        record = write_source(left_behind=tuple(args.left_behind))
        print(f"{SOURCE_FILE.name}: commit {record['commit']}, {len(record['blobs'])} tracked files")
    elif args.command == "show":
        print(json.dumps(provenance(args.device or None), indent=1))
    elif args.command == "paths":
        total = 0
        for path in tracked_text_files():
            fixed, count = strip_machine_paths(path.read_bytes().decode())  # bytes: line endings kept
            if count:
                total += count
                print(f"{path.relative_to(ROOT)}: {count}")
                if args.fix:
                    path.write_bytes(fixed.encode())
        print(f"{total} machine paths{' rewritten' if args.fix else ''}")
        raise SystemExit(1 if total and not args.fix else 0)
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.out, {"what": "the provenance of the results beside this file"}, args.device or None)
        print(f"provenance -> {args.out}")


if __name__ == "__main__":
    main()
