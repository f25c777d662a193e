"""How both command lines' `--help` reads: each default said once, examples at the end."""

from __future__ import annotations

import argparse
import textwrap

EXAMPLES_HEADING = "examples:"
EXAMPLE_INDENT = "  "


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's formatter with defaults (`(default: 3)`) added only where the option's help does
    not already say its default and there is one worth saying (not None, not an off switch); the
    description and epilog wrapped line by line, so indented lines (examples) stay as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text.lower() or action.default is None or action.default is False:
            return text
        return super()._get_help_string(action)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        lines = []
        for line in text.splitlines():
            if not line.strip() or line.startswith(" "):
                lines.append(indent + line.rstrip())
            else:
                lines.append(
                    textwrap.fill(" ".join(line.split()), width, initial_indent=indent, subsequent_indent=indent)
                )
        return "\n".join(lines)


EXAMPLE_WIDTH = 78
"""Example lines are continued (` \\`) within this many characters, so a terminal does not break them."""
CONTINUED = EXAMPLE_INDENT * 3


def examples(*commands: str) -> str:
    """An epilog of example command lines under an `examples:` heading, each long one continued
    with backslashes between options (as a shell reads it), so that it can be copied as it stands."""
    lines = [EXAMPLES_HEADING]
    for command in commands:
        line = EXAMPLE_INDENT
        for group in _option_groups(command):
            if line.strip() and len(line) + 1 + len(group) + 2 > EXAMPLE_WIDTH:
                lines.append(line + " \\")
                line = CONTINUED
            line += ("" if line.isspace() else " ") + group
        lines.append(line)
    return "\n".join(lines)


def _option_groups(command: str) -> list[str]:
    """The words of `command` with each option joined to its values (`--out x.png`)."""
    groups: list[str] = []
    for word in command.split():
        if groups and groups[-1].startswith("-") and not word.startswith("-"):
            groups[-1] += " " + word
        else:
            groups.append(word)
    return groups


def example_commands(epilog: str | None) -> list[str]:
    """The command lines of an `examples` epilog, continuations joined (the inverse of `examples`)."""
    lines = (epilog or "").splitlines()
    if EXAMPLES_HEADING not in lines:
        return []
    commands, pending = [], ""
    for line in lines[lines.index(EXAMPLES_HEADING) + 1 :]:
        if not line.startswith(EXAMPLE_INDENT) or not line.strip():
            continue
        text = pending + line.strip()
        pending = text[:-1] if text.endswith("\\") else ""
        if not pending:
            commands.append(text)
    return commands
