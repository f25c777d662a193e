"""Every command's `--help` of both command lines reads as a user needs it: each option and
argument says what it is for, each default is said once, the description has no developer notes,
and the help ends with examples that the real parser accepts. Also the shared pieces in clitools:
the formatter, the examples' round trip and the one-line error of `run_command`."""

from __future__ import annotations

import argparse
import shlex
import subprocess

import pytest

from clitools import HelpFormatter, error_line, example_commands, examples, run_command

DEVELOPER_WORDS = ("handler", "imported", "import ", "module")
"""Words of notes for developers that a command's description should not hold."""


def _parsers() -> dict[str, argparse.ArgumentParser]:
    from acoustic_sim.cli import build_parser as simulator
    from learn.cli import build_parser as learner

    return {"acoustic_sim": simulator(), "learn": learner()}


def _subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def _every_parser() -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(cli, command name or "", parser): each program and each of its commands."""
    found = []
    for cli, parser in _parsers().items():
        found.append((cli, "", parser))
        found += [(cli, name, sub) for name, sub in _subcommands(parser).choices.items()]
    return found


PARSERS = _every_parser()
IDS = [f"{cli} {name}".strip() for cli, name, _ in PARSERS]


def test_both_command_lines_are_walked():
    """The walk finds every command (a missing one would be silently unchecked)."""
    names = {cli: sorted(_subcommands(p).choices) for cli, p in _parsers().items()}
    assert names["acoustic_sim"] == ["calibrate", "export", "generate", "import", "render"]
    assert {"train", "evaluate", "predict", "export", "table2", "sim2real", "table2-summary"} <= set(names["learn"])


@pytest.mark.parametrize("cli", ["acoustic_sim", "learn"])
def test_the_program_help_lists_every_command_with_its_summary(cli):
    parser = _parsers()[cli]
    listed = {a.dest: a.help for a in _subcommands(parser)._choices_actions}
    assert set(listed) == set(_subcommands(parser).choices)
    assert all(listed.values()), [name for name, text in listed.items() if not text]
    text = parser.format_help()
    assert all(f"    {name} " in text or f"    {name}\n" in text for name in listed), text


@pytest.mark.parametrize(("cli", "name", "parser"), PARSERS, ids=IDS)
def test_every_option_has_help_and_says_its_default_once(cli, name, parser):
    formatter = parser._get_formatter()
    assert isinstance(formatter, HelpFormatter)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            continue
        label = "/".join(action.option_strings) or action.dest
        assert action.help, f"python -m {cli} {name}: {label} has no help"
        shown = formatter._expand_help(action)
        assert shown.lower().count("default") <= 1, f"{label}: {shown}"


@pytest.mark.parametrize(("cli", "name", "parser"), PARSERS, ids=IDS)
def test_help_ends_with_examples_the_parser_accepts(cli, name, parser):
    commands = example_commands(parser.epilog)
    assert 1 <= len(commands) <= 2, f"python -m {cli} {name}: {len(commands)} examples"
    assert parser.format_help().rstrip().endswith(parser.epilog.splitlines()[-1].rstrip())
    for command in commands:
        words = shlex.split(command)
        assert words[:3] == ["python", "-m", cli] and (not name or words[3] == name), command
        try:
            args = _parsers()[cli].parse_args(words[3:])  # a fresh parser: the real one
        except SystemExit as exit_:
            raise AssertionError(f"python -m {cli} refuses its own example: {command}") from exit_
        assert args.command == words[3]


@pytest.mark.parametrize(("cli", "name", "parser"), PARSERS, ids=IDS)
def test_descriptions_speak_to_users(cli, name, parser):
    text = (parser.description or "").lower()
    assert text, f"python -m {cli} {name} has no description"
    assert not [w for w in DEVELOPER_WORDS if w in text], text


def test_formatter_adds_a_default_only_where_none_is_said():
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter, epilog=examples("prog --a 1"))
    parser.add_argument("--a", type=int, default=3, help="plain")
    parser.add_argument("--b", type=int, default=3, help="said (default: three)")
    parser.add_argument("--c", default=None, help="unset")
    parser.add_argument("--d", action="store_true", help="a switch")
    shown = {a.dest: parser._get_formatter()._expand_help(a) for a in parser._actions}
    assert shown == {
        "help": "show this help message and exit",
        "a": "plain (default: 3)",
        "b": "said (default: three)",
        "c": "unset",
        "d": "a switch",
    }


def test_examples_wrap_between_options_and_read_back_whole():
    long = "python -m learn train " + " ".join(f"--option-{i} value{i}" for i in range(12))
    epilog = examples(long, "python -m learn export --checkpoint a.pt --out b.onnx")
    lines = epilog.splitlines()
    assert lines[0] == "examples:" and all(len(line) <= 78 for line in lines)
    assert all(line.endswith(" \\") for line in lines[1:-2]) and len(lines) > 3
    assert not any(line.rstrip(" \\").endswith("--option-3") for line in lines)  # never between option and value
    assert example_commands(epilog) == [long, "python -m learn export --checkpoint a.pt --out b.onnx"]
    pasted = subprocess.run(  # as a shell reads the lines when they are pasted
        ["bash", "-c", "printf '%s\\0' " + "\n".join(lines[1:-1])], capture_output=True, text=True, check=True
    )
    assert pasted.stdout.split("\0")[:-1] == shlex.split(long)


def test_run_command_turns_a_user_error_into_one_line(capsys):
    def refuse() -> int:
        raise ValueError("data/x: no shards\nsecond line")

    assert run_command(refuse, ["train"], (ValueError,)) == 2
    assert capsys.readouterr().err == "error: data/x: no shards\n"
    assert run_command(lambda: 0, [], (ValueError,)) == 0
    with pytest.raises(ValueError, match="no shards"):
        run_command(refuse, ["train", "--debug"], (ValueError,))
    with pytest.raises(RuntimeError):  # not a user error: a bug keeps its trace
        run_command(lambda: (_ for _ in ()).throw(RuntimeError("bug")), [], (ValueError,))
    assert error_line(KeyError()) == "KeyError" and error_line(OSError("  disk full  ")) == "disk full"
