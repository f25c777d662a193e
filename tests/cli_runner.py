"""Many command lines of our two CLIs, each run as `python -m PACKAGE ARGV` in a process of its own,
without paying the interpreter's start and the heavy imports (torch, Warp, scenes) once per command.

`run_commands` starts a fresh interpreter (this file) per package, which imports that package's
command line once (learn's: torch; acoustic_sim's: Warp, scenes; neither the other's) and then
forks a child per command; the child runs the package's `__main__` as `python -m` does (runpy,
sys.argv set) with its stdout and stderr in files, and exits as the interpreter would: SystemExit's
code, or the trace and status 1 for any other exception, after the exit handlers. The parents start
nothing of Warp or CUDA, so each command starts them itself, as a user's would. What a command
prints, writes and returns is the same as in a fresh interpreter; only the imports are shared.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

PRELOADED = {"acoustic_sim": ("scenes", "acoustic_sim.datasets.suites", "acoustic_sim.formats.chirp")}
"""Modules a package's commands import once parsed (its parser leaves them out to answer --help fast)."""


def run_commands(
    commands: dict[str, tuple[str, list[str]]], *, env: dict[str, str], parallel: int, timeout: float = 300.0
) -> dict[str, subprocess.CompletedProcess]:
    """Run each {name: (package, argv)} (package `learn` or `acoustic_sim`), the packages side by
    side and each at most `parallel` // 2 commands at a time; {name: CompletedProcess} with its
    returncode, stdout and stderr (a command past `timeout` seconds is killed: returncode -9)."""
    runners = {}
    for package in sorted({package for package, _ in commands.values()}):
        mine = {name: c for name, c in commands.items() if c[0] == package}
        request = {"package": package, "commands": mine, "parallel": max(1, parallel // 2), "timeout": timeout}
        runner = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve())],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        runners[runner] = json.dumps(request)
    results = {}
    for runner, request in runners.items():
        stdout, stderr = runner.communicate(request, timeout=timeout * max(1, len(commands)))
        if runner.returncode != 0:
            raise RuntimeError(f"the command runner failed:\n{stderr[-3000:]}")
        results |= json.loads(stdout)
    return {
        name: subprocess.CompletedProcess([sys.executable, "-m", *commands[name][:1], *commands[name][1]], **r)
        for name, r in results.items()
    }


def _serve() -> None:
    """The runner process: read the request on stdin, fork a child per command, answer on stdout."""
    request = json.loads(sys.stdin.read())
    sys.path[0] = os.getcwd()  # as `python -m` has it (this file's folder is no package root)
    import importlib

    cli = importlib.import_module(f"{request['package']}.cli")  # the heavy imports, once: nothing starts
    cli.build_parser()  # imports what --help needs (learn: torch, models)
    for module in PRELOADED.get(request["package"], ()):  # and what acoustic_sim's commands import after parsing
        importlib.import_module(module)
    import shutil
    import tempfile

    # mkdtemp, not TemporaryDirectory: the children run the exit handlers they inherit, and a
    # TemporaryDirectory's would delete the folder that holds their output.
    folder = Path(tempfile.mkdtemp(prefix="cli_runner_"))
    results, running, queue = {}, {}, list(request["commands"].items())
    try:
        while queue or running:
            while queue and len(running) < request["parallel"]:
                name, (package, argv) = queue.pop(0)
                files = (folder / f"{name}.out", folder / f"{name}.err")
                running[_start(package, argv, files)] = (name, files, time.monotonic())
            for pid, (name, files, started) in list(running.items()):
                finished, status = os.waitpid(pid, os.WNOHANG)
                if not finished and time.monotonic() - started > request["timeout"]:
                    os.kill(pid, 9)
                    finished, status = os.waitpid(pid, 0)
                if finished:
                    del running[pid]
                    results[name] = {
                        "returncode": os.waitstatus_to_exitcode(status),
                        "stdout": files[0].read_text(errors="replace"),
                        "stderr": files[1].read_text(errors="replace"),
                    }
            time.sleep(0.01)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    sys.stdout.write(json.dumps(results))


def _start(package: str, argv: list[str], files: tuple[Path, Path]) -> int:
    """Fork a child that runs `python -m package argv` with stdout and stderr in `files`; its pid."""
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid:
        return pid
    code = 1
    try:
        for fd, path in zip((1, 2), files, strict=True):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)  # the request was read; a command reads nothing
        code = _run_module(package, argv)
    finally:
        os._exit(code)


def _run_module(package: str, argv: list[str]) -> int:
    """What `python -m package argv` does after start-up, and its exit status."""
    import atexit
    import runpy
    import traceback

    sys.argv = [package, *argv]
    try:
        runpy.run_module(package, run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exit_:
        if exit_.code is None or isinstance(exit_.code, int):
            code = exit_.code or 0
        else:
            print(exit_.code, file=sys.stderr)
            code = 1
    except BaseException:
        traceback.print_exc()
        code = 1
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    return code


if __name__ == "__main__":
    _serve()
