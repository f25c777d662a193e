"""Every code block of README.md runs as written, or is checked as far as CI can check it.

The blocks are taken in README order in one temporary folder that looks like a clone (the repository's
packages, `examples/` and the Makefile linked in), so outputs land there and a later block finds what an
earlier one wrote.

- bash: bash itself expands each block (loops, quotes, line continuations, comments, globs) with
  `python`, `torchrun`, `ray`, `pip`, `make` and `.` replaced by functions that record their arguments; every
  recorded command is then checked, in order. Each `python -m acoustic_sim|learn` command is parsed by
  that CLI's own argparse parser (unknown options, bad choices and wrong types fail) and its `--set`
  values, suite and device names are checked; every input file it names must exist or lie in the output
  of an earlier command. It then runs as written (`python` = this interpreter), unless a rule of
  PARSE_ONLY matches it or one of its inputs comes only from a parse-only command: those are only
  parsed. `pip` and `make` lines are checked against pyproject.toml and the Makefile. What a command
  that ran wrote is checked against what the README says it writes (tests/readme_outputs.py: the
  picture and its settings file, the shards' arrays and frame counts, the MCAP topics, the CHIRP
  round trip within 0.2 %, the scans of `predict`, the ONNX threshold) and its printed lines where
  the README quotes them; a command that runs without such a check fails the test.
- python: runs as written in a subprocess (cwd the temporary folder); the shapes its comments give
  (`ranges = ...  # (50, 1081) metres`) are checked on the values.
- toml: loaded as a suite file, as `generate --suite FILE` loads it (a `[materials]` table alone as a
  mesh's material table); a block whose first line is `# PATH` must equal that file of the repository,
  and that file is loaded (so its relative paths resolve beside it).
- a block without a language is text (the layout).

What ran and what was only parsed (and why) is printed: `pytest tests/test_readme.py -rP`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import os
import re
import shlex
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

import pytest

from tests import readme_outputs

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
LINKED = ("clitools", "acoustic_sim", "scenes", "learn", "examples", "benchmarks", "Makefile", "pyproject.toml")
"""What the temporary folder shares with the repository; everything else the commands write stays there."""

MAX_CPU_FRAMES = 100
"""`generate` runs in the test up to this many frames (the tiny suite's 24 take ~7 s on 2 cores)."""

READER_INPUTS = {"rec/": "the reader's own eRTIS recordings (raw PDM); none ship with the repository"}
"""Inputs that stand for the reader's files: a command naming one is parsed, not run."""

INPUT_DESTS = ("svg", "mesh", "materials", "suite", "recordings", "dataset", "data", "init_from", "checkpoint")
INPUT_DESTS += ("input",)
INPUT_DESTS += ("train", "test", "ablation", "reality", "runs", "reports")
"""argparse destinations that name files or folders a command reads (values may be NAME=PATH)."""

DEVICE = re.compile(r"cpu|auto|cuda(:\d+)?")


@dataclasses.dataclass
class Command:
    """One recorded command: `argv` as the shell passed it; for our CLIs, `cli` and the parsed `args`."""

    argv: list[str]
    cli: str = ""
    args: argparse.Namespace | None = None
    frames: int = 0  # frames a `generate` simulates

    @property
    def text(self) -> str:
        return shlex.join(self.argv)

    @property
    def subcommand(self) -> str:
        return f"{self.cli} {self.args.command}" if self.args else self.argv[0]


PARSE_ONLY: list[tuple[str, Callable[[Command], bool]]] = [
    ("needs an NVIDIA GPU", lambda c: bool(c.args) and str(getattr(c.args, "device", "")).startswith("cuda")),
    ("DDP over several GPUs", lambda c: c.argv[0] == "torchrun"),
    (
        f"simulates more than {MAX_CPU_FRAMES} frames: minutes to hours on a CPU",
        lambda c: c.subcommand == "acoustic_sim generate" and c.frames > MAX_CPU_FRAMES,
    ),
    ("trains models: minutes to hours", lambda c: c.subcommand in ("learn train", "learn table2", "learn sim2real")),
    ("installs packages (the test environment has the extras)", lambda c: c.argv[0] == "pip"),
    ("needs a Ray cluster", lambda c: c.argv[0] == "ray" or bool(getattr(c.args, "ray_address", None))),
    ("make demo takes ~10 minutes, make test is the whole suite", lambda c: c.argv[0] == "make"),
]
"""Commands that cannot run in CI as written: (reason, rule). They are parsed and checked, not run."""


def code_blocks(text: str) -> list[tuple[str, str, int]]:
    """The fenced blocks of a markdown text: (language, code, line number of the fence)."""
    blocks, lines, start = [], text.splitlines(), None
    for number, line in enumerate(lines, 1):
        if line.startswith("```") and start is None:
            start, language, body = number, line[3:].strip(), []
        elif line.startswith("```"):
            blocks.append((language, "\n".join(body) + "\n", start))
            start = None
        elif start is not None:
            body.append(line)
    assert start is None, f"README.md: the code block at line {start} is not closed"
    return blocks


STUBS = r"""
set -euo pipefail
_record() { printf '%s\0' "$#" "$@" >> "$README_LOG"; }
python() { _record python "$@"; }
python3() { _record python "$@"; }
.venv/bin/python() { _record python "$@"; }
torchrun() { _record torchrun "$@"; }
ray() { _record ray "$@"; }
pip() { _record pip "$@"; }
make() { _record make "$@"; }
.() { _record . "$@"; }
source() { _record . "$@"; }
cd() { echo "README blocks run from the repository root: cd is not supported here" >&2; return 1; }
command_not_found_handle() { echo "tests/test_readme.py has no rule for the command $1" >&2; return 127; }
PATH=/nonexistent  # no other program runs: each one needs a rule here
"""


def shell_commands(code: str, cwd: Path) -> list[list[str]]:
    """The commands a bash block runs, expanded by bash with recording stubs (nothing runs)."""
    log = cwd / ".readme_commands"
    log.write_bytes(b"")
    done = subprocess.run(
        ["bash", "-c", STUBS + code],
        cwd=cwd,
        env=os.environ | {"README_LOG": str(log)},
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, f"bash could not expand the block:\n{done.stderr}"
    words, commands = log.read_bytes().decode().split("\0")[:-1], []
    while words:
        count = int(words.pop(0))
        commands.append(words[:count])
        del words[:count]
    log.unlink()
    return commands


def _parse(cli: str, argv: list[str]) -> argparse.Namespace:
    if cli == "acoustic_sim":
        from acoustic_sim.cli import build_parser

        argv = [a for a in argv if a != "--debug"]  # main() takes it anywhere on the line
    else:
        from learn.cli import build_parser
    errors = io.StringIO()
    with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
        try:
            return build_parser().parse_args(argv)
        except SystemExit:
            pass
    raise AssertionError(f"python -m {cli} refuses it:\n{errors.getvalue().strip()}")


def _check_settings(command: Command, cwd: Path) -> None:
    """--set values, devices and suites, as the handlers would read them (nothing is simulated)."""
    args = command.args
    if not DEVICE.fullmatch(str(getattr(args, "device", "cpu"))):
        raise AssertionError(f"--device {args.device!r} is none of cpu, auto, cuda, cuda:N")
    if command.cli == "acoustic_sim":
        from acoustic_sim.config import SimConfig
        from acoustic_sim.settings import apply_settings

        apply_settings(SimConfig(), getattr(args, "set", None) or ())
        if args.command == "generate":
            command.frames = _suite_frames(args, cwd)
    elif hasattr(args, "epochs"):  # the learner's training options
        from learn.cli_training import run_config

        run_config(args)


def _suite_frames(args: argparse.Namespace, cwd: Path) -> int:
    """Frames `generate` would simulate, after loading the suite and choosing its variants."""
    if args.suite in ("crossengine", "crossengine_rough"):
        return args.frames or 1000
    from acoustic_sim.datasets.suites import SUITES, load_suite

    suite = load_suite(args.suite if args.suite in SUITES else cwd / args.suite)
    variants = [v.strip() for v in args.variants.split(",")] if args.variants else list(suite.variants)
    assert set(variants) <= set(suite.variants), f"--variants {args.variants}: the suite has {list(suite.variants)}"
    return (args.frames or suite.frames) * len(variants)


def _paths(args: argparse.Namespace, dest: str) -> list[str]:
    value = getattr(args, dest, None)
    if dest == "suite" and value and not Path(value).suffix:
        return []  # a named suite
    values = value if isinstance(value, list) else [value] if value else []
    return [v.partition("=")[2] if re.match(r"\w+=", v) else v for v in values]


class Walk:
    """The README's commands in order, in one folder; `made` holds what parse-only commands would write."""

    def __init__(self, cwd: Path, *, run: bool = True):
        self.cwd, self.run = cwd, run
        self.made: set[Path] = set()
        self.exported: dict[Path, Path] = {}  # CHIRP files written by an earlier command -> their dataset
        self.report: list[str] = []

    def check(self, argv: list[str]) -> None:
        command = Command(argv)
        if argv[0] == "python" and argv[1:2] == ["-m"] and argv[2:3] in (["acoustic_sim"], ["learn"]):
            command.cli, command.args = argv[2], _parse(argv[2], argv[3:])
        elif argv[0] == "torchrun" and "-m" in argv:
            module = argv.index("-m") + 1
            command.cli, command.args = argv[module], _parse(argv[module], argv[module + 1 :])
        elif argv[0] == "pip":
            self._check_pip(argv[1:])
        elif argv[0] == "make":
            self._check_make(argv[1:])
        elif argv[0] == "ray":
            self._check_ray(argv[1:])
        elif argv[0] == "." and argv[1:] == [".venv/bin/activate"]:
            self.report.append(f"skipped      {command.text}  (the test runs the venv's interpreter already)")
            return
        else:
            raise AssertionError("tests/test_readme.py has no rule for this command")
        if command.args:
            _check_settings(command, self.cwd)
        reasons, unmade = [reason for reason, rule in PARSE_ONLY if rule(command)], []
        for path in (p for dest in INPUT_DESTS for p in _paths(command.args, dest)) if command.args else ():
            if reader := next((why for prefix, why in READER_INPUTS.items() if path.startswith(prefix)), None):
                reasons.append(f"reads {path}: {reader}")
            elif self._made_by_parse_only(path):
                unmade.append(path)
            else:
                assert (self.cwd / path).exists(), f"reads {path}: it neither exists nor is made by an earlier command"
        if unmade:
            reasons.append(f"reads {', '.join(unmade)}, made only by parse-only commands")
        if reasons or not self.run:
            self.report.append(f"parsed only  {command.text}  ({'; '.join(reasons) or 'run=False'})")
            if command.args and getattr(command.args, "out", None):
                self.made.add(Path(os.path.normpath(command.args.out)))
            return
        stdout = self._run([sys.executable, *argv[1:]], command.text)
        self.report.append(f"  checked: {self._outputs(command, stdout)}")

    def _outputs(self, command: Command, stdout: str) -> str:
        """What a command that ran wrote and printed, against the README (tests/readme_outputs.py)."""
        args, out = command.args, readme_outputs
        if command.subcommand == "acoustic_sim render":
            return out.check_render(args, self.cwd, stdout)
        if command.subcommand == "acoustic_sim generate":
            return out.check_generate(args, self.cwd, stdout, command.frames)
        if command.subcommand == "acoustic_sim calibrate":
            return out.check_calibrate(args, self.cwd, stdout)
        if command.subcommand == "acoustic_sim export" and args.format == "mcap":
            return out.check_export_mcap(args, self.cwd)
        if command.subcommand == "acoustic_sim export" and args.format == "chirp":
            self.exported[Path(os.path.normpath(args.out))] = Path(args.dataset)
            return out.check_export_chirp(args, self.cwd)
        if command.subcommand == "acoustic_sim import" and args.format == "chirp":
            source = self.exported.get(Path(os.path.normpath(args.recordings[0])))
            return out.check_import_chirp(args, self.cwd, source)
        if command.subcommand == "learn predict":
            return out.check_predict(args, self.cwd)
        if command.subcommand == "learn evaluate":
            return out.check_evaluate(args, self.cwd, stdout)
        if command.subcommand == "learn export":
            return out.check_onnx(args, self.cwd, stdout)
        raise AssertionError("it ran, but tests/readme_outputs.py has no check of what it writes")

    def _made_by_parse_only(self, path: str) -> bool:
        path = Path(os.path.normpath(path))
        return any(path == out or out in path.parents for out in self.made)

    def _run(self, argv: list[str], text: str, timeout: float = 300) -> str:
        env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        start = time.perf_counter()
        done = subprocess.run(argv, cwd=self.cwd, env=env, capture_output=True, text=True, timeout=timeout)
        assert done.returncode == 0, f"exit code {done.returncode}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        self.report.append(f"ran {time.perf_counter() - start:5.1f} s  {text}")
        return done.stdout

    def _check_pip(self, args: list[str]) -> None:
        extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
        assert args[:1] == ["install"], "only `pip install` is known here"
        for spec in args[1:]:
            if match := re.fullmatch(r"\.\[([\w,-]+)\]", spec):
                assert set(match[1].split(",")) <= extras, f"{spec}: pyproject.toml has the extras {sorted(extras)}"

    def _check_make(self, args: list[str]) -> None:
        makefile = (ROOT / "Makefile").read_text()
        for arg in args:
            name, sep, _ = arg.partition("=")
            pattern = rf"^{re.escape(name)} \?=" if sep else rf"^{re.escape(arg)}:"
            assert re.search(pattern, makefile, re.M), f"the Makefile has no {'variable' if sep else 'target'} {name}"

    @staticmethod
    def _check_ray(args: list[str]) -> None:
        """Ray's own commands, as far as they can be checked without Ray: the two the README uses."""
        if args[:2] == ["get-auth-token", "--generate"]:
            return
        assert args[:1] == ["start"], f"no rule for `ray {shlex.join(args)}` (get-auth-token --generate, start)"
        assert ("--head" in args) != any(a.startswith("--address") for a in args), "ray start: --head or --address"

    def bash(self, code: str) -> None:
        for argv in shell_commands(code, self.cwd):
            try:
                self.check(argv)
            except Exception as err:
                raise AssertionError(f"README command `{shlex.join(argv)}`: {err}") from err

    def python(self, code: str, number: int) -> None:
        script = self.cwd / f"readme_block_{number}.py"
        compile(code, str(script), "exec")
        probed, claims = readme_outputs.shape_probe(code)
        assert claims, f"README.md:{number}: the block comments no shape to check (`x = ...  # (dims)`)"
        script.write_text(probed)
        if self.run:
            stdout = self._run([sys.executable, script.name], f"python block at README.md:{number}")
            self.report.append(f"  checked: {readme_outputs.check_shapes(claims, stdout, number)}")

    def toml(self, code: str, number: int) -> None:
        from acoustic_sim.datasets.suites import load_suite
        from scenes.material_map import read_material_table

        first = code.splitlines()[0]
        if first.startswith("# ") and (ROOT / first[2:]).is_file():
            assert (ROOT / first[2:]).read_text() == code, f"README.md:{number} differs from {first[2:]}"
            path = self.cwd / first[2:]
        else:
            path = self.cwd / f"readme_suite_{number}.toml"
            path.write_text(code)
        if set(tomllib.loads(code)) == {"materials"}:
            table = read_material_table(path)
            self.report.append(f"loaded       toml block at README.md:{number} as a material table: {table}")
            return
        suite = load_suite(path)
        self.report.append(f"loaded       toml block at README.md:{number} as a suite: variants {list(suite.variants)}")


def clone(tmp_path: Path) -> Path:
    for name in LINKED:
        (tmp_path / name).symlink_to(ROOT / name)
    return tmp_path


def walk(text: str, cwd: Path, *, run: bool = True) -> Walk:
    state = Walk(cwd, run=run)
    for language, code, number in code_blocks(text):
        if language == "bash":
            state.bash(code)
        elif language == "python":
            state.python(code, number)
        elif language == "toml":
            state.toml(code, number)
        else:
            assert language == "", f"README.md:{number}: no rule for ```{language} blocks"
    return state


def test_readme_code_blocks_run(tmp_path, capsys):
    """Every block of README.md, in order: ran, parsed only (with its reason) or loaded."""
    state = walk(README.read_text(), clone(tmp_path))
    ran = sum(line.startswith("ran") for line in state.report)
    print("\n".join(["README.md code blocks:", *state.report]))
    assert ran >= 10, "most of the README's CPU commands should run"
    assert sum(line.startswith("  checked: ") for line in state.report) == ran  # each one's outputs
    with capsys.disabled():
        print(f"\nREADME.md: {ran} commands and blocks ran, {len(state.report) - ran} were parsed, loaded or skipped")


@pytest.mark.parametrize(
    ("line", "complaint"),
    [
        ("python -m acoustic_sim generate --suite paper --out d --frmes 10 --device cuda:0", "unrecognized"),
        ("python -m learn train --data data/tiny --out r --model unet3 --device cuda", "invalid choice"),
        ("python -m learn train --data data/tiny --out r --epochs many --device cuda", "invalid int"),
        ("python -m learn train --data data/tiny --out r --set train.pos_weigth=5 --device cuda", "no field"),
        ("python -m acoustic_sim render --set tracer.max_bounce=1 --device cuda:0", "max_bounce"),
        ("python -m acoustic_sim generate --suite examples/nope.toml --out d --device cuda:0", "does not exist"),
        ("python -m learn export --checkpoint runs/x/best.pt --out x.onnx", "runs/x/best.pt"),
        ("python -m acoustic_sim render --mesh examples/building.obj --device gpu", "--device"),
        ('pip install -e ".[rosbag]"', "extras"),
        ("make demoo", "target"),
        ("h5ls data/tiny", "no rule"),
    ],
)
def test_parse_only_commands_still_catch_mistakes(tmp_path, line, complaint):
    """A README line with a mistyped option, choice, type, setting, file or command fails the test even
    where it would only be parsed (on a GPU device): the real parsers and configs check it."""
    with pytest.raises(AssertionError, match=re.escape(complaint)):
        walk(f"```bash\n{line}\n```\n", clone(tmp_path), run=False)
