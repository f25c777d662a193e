"""The dataset folder a run writes into: `plan.json` says which run it holds (a rerun with other
settings is refused, never mixed in), `.generate.lock` keeps one writer at a time, and a shard
counts as done only if it belongs to the plan and passes its checksums (a damaged one is moved
aside and written again). Every engine's datasets share these rules (`generate.make_dataset`)."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import warnings
from pathlib import Path

from clitools.limits import input_file

from .plan import ShardTask
from .shards import FORMAT, FORMAT_VERSION, DatasetError, read_attrs, verify_shard

PLAN_FILE = "plan.json"
PLAN_MAX_BYTES = 16_000_000  # a plan.json holds the suite's JSON: kilobytes; anything this large is not one
LOCK_FILE = ".generate.lock"  # "pid host" of the run writing the folder


def check_plan_file(out: Path, tasks: list[ShardTask], meta: dict) -> None:
    """Write out/plan.json (the plan id and `meta`), or check that an existing one describes the
    same run; a folder with other files and no plan.json is refused, untouched."""
    path = out / PLAN_FILE
    if path.exists() or path.is_symlink():
        old = read_plan(path)
        if old.get("plan_id") != tasks[0].plan_id:
            raise DatasetError(
                f"{out} holds a run with other settings (plan {old.get('plan_id')}, suite {old.get('suite')!r}, "
                f"frames {old.get('frames')}, shards {old.get('shards')}, seed {old.get('seed')}); "
                "rerun with those settings to resume it, or use another --out"
            )
        return
    if out.is_symlink() and not out.exists():
        raise DatasetError(f"--out {out} is a symbolic link to {os.readlink(out)}, which does not exist; give a folder")
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out} is a file; give a folder for the dataset")
    if out.is_dir() and any(out.iterdir()):
        raise DatasetError(
            f"--out {out} holds other files and no {PLAN_FILE}: it is not a dataset folder, and nothing in it "
            "will be overwritten; choose an empty or new folder"
        )
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(PLAN_FILE + ".tmp")
    tmp.write_text(
        json.dumps({"format": FORMAT, "format_version": FORMAT_VERSION, "plan_id": tasks[0].plan_id} | meta, indent=1)
    )
    tmp.replace(path)


def read_plan(path: Path) -> dict:
    """A folder's plan.json, checked to be one: a regular file of a sane size holding a JSON
    object of our format (a FIFO, a list or a truncated file is refused naming it)."""
    advice = f"is {path.parent} a sonar2lidar dataset folder? Choose another --out"
    try:
        input_file(path, what="plan file", max_bytes=PLAN_MAX_BYTES, bound="a plan holds its suite in kilobytes")
        plan = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise DatasetError(f"{path} is not valid JSON ({str(err) or type(err).__name__}); {advice}") from None
    except (OSError, ValueError) as err:
        raise DatasetError(f"{err}; {advice}") from None
    if not isinstance(plan, dict):
        raise DatasetError(f"{path} holds a JSON {type(plan).__name__}, not a plan (an object); {advice}")
    if plan.get("format") != FORMAT:
        raise DatasetError(f"{path} is not a {FORMAT} plan (format {plan.get('format')!r}); {advice}")
    return plan


def forget_plan(out: Path, tasks: list[ShardTask], *, made_folder: bool) -> None:
    """Undo the plan.json a run wrote when it ended before finishing any shard (refused, failed or
    interrupted), with the folders it made and left empty: a folder must not stay locked to
    settings that never made a shard. A finished shard keeps its plan (the run resumes)."""
    if any(Path(t.path).exists() for t in tasks):
        return
    (out / PLAN_FILE).unlink(missing_ok=True)
    for folder in sorted({Path(t.path).parent for t in tasks} - {out}) + ([out] if made_folder else []):
        with contextlib.suppress(OSError):  # not empty: something else is there, keep it
            folder.rmdir()


def remove_temporaries(tasks: list[ShardTask]) -> None:
    """Remove the `.tmp` files of the tasks' shards that stopped workers leave (the lock is ours)."""
    for task in tasks:
        Path(task.path + ".tmp").unlink(missing_ok=True)


@contextlib.contextmanager
def output_lock(out: Path):
    """Hold `out`/.generate.lock while writing, so two runs never write the same shards. A lock
    left by a run that died on this host is taken over; a live one is refused."""
    path = out / LOCK_FILE
    me = f"{os.getpid()} {socket.gethostname()}"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            try:
                pid, _, host = path.read_text(errors="replace").strip().partition(" ")
            except OSError as err:  # a folder or a FIFO by that name: no generate made it
                raise DatasetError(
                    f"{path} is in the way of generate's lock ({err.strerror or err}); remove it and rerun"
                ) from None
            if host != socket.gethostname() or _alive(pid):
                raise DatasetError(
                    f"another generate (pid {pid} on {host or '?'}) is writing {out}; wait for it, or delete "
                    f"{path} if it is no longer running"
                ) from None
            path.unlink(missing_ok=True)  # its writer is gone
    else:
        raise DatasetError(f"could not take the lock {path}")
    with os.fdopen(fd, "w") as f:
        f.write(me)
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def _alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def check_no_strangers(tasks: list[ShardTask]) -> None:
    """Refuse shard-*.h5 files in the run's folders that the plan does not write (a copy, a
    link, another run's shard): readers take every shard of a folder, so they would mix in."""
    planned = {Path(t.path) for t in tasks}
    for folder in sorted({p.parent for p in planned}):
        if strangers := sorted(p.name for p in folder.glob("shard-*.h5") if p not in planned):
            raise DatasetError(
                f"{folder} holds {', '.join(strangers[:3])}{' ...' if len(strangers) > 3 else ''}, which this run's "
                f"plan does not write (it writes {len(planned)} shard(s)); readers would mix it in: move it away"
            )


def is_complete(task: ShardTask) -> bool:
    """Whether the task's shard exists, belongs to this plan and passes its checksums. A shard of
    this plan that fails them is moved aside (`.damaged`) and counted as not done."""
    path = Path(task.path)
    if not path.exists():
        return False
    try:
        attrs = read_attrs(path)
    except DatasetError as err:  # foreign, truncated or of another version: it may be someone's, keep it
        raise DatasetError(f"{err}; generate never replaces it: move it away and rerun to write the shard") from None
    if attrs.get("plan_id") != task.plan_id:
        raise DatasetError(
            f"{path} belongs to another run (plan {attrs.get('plan_id')}, not {task.plan_id}); "
            "use another --out or remove that folder"
        )
    if int(attrs["frame_count"]) != task.frame_count or int(attrs.get("shard", task.shard)) != task.shard:
        raise DatasetError(
            f"{path} holds shard {attrs.get('shard')} of this run ({attrs['frame_count']} frames), not shard "
            f"{task.shard} ({task.frame_count} frames): a copy or a link under another name; remove it and rerun"
        )
    try:
        verify_shard(path)
    except DatasetError as err:
        damaged = path.with_name(path.name + ".damaged")
        os.replace(path, damaged)
        warnings.warn(f"{err}; moved it to {damaged.name} and writing the shard again", stacklevel=2)
        return False
    return True
