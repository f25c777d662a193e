"""How both command lines end on a user's mistake: one `error:` line and exit status 2."""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Callable, Iterator, Sequence

USAGE_ERROR = 2
"""The exit status of a user error, as argparse's own for a bad option."""
INTERRUPTED = 130
"""The exit status after Ctrl-C, as a shell reports a process ended by SIGINT."""


def error_line(err: BaseException) -> str:
    """The first line of `err`'s message, or its class name when it has none."""
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def run_command(command: Callable[[], int], argv: Sequence[str], user_errors: tuple[type[BaseException], ...]) -> int:
    """Run `command` (parse the command line and call its handler); a `user_errors` exception
    becomes one `error: ...` line on stderr and USAGE_ERROR, and Ctrl-C one `interrupted: ...`
    line (the interrupt's message says what was kept) and INTERRUPTED, unless `argv` holds
    `--debug` (anywhere on the line), which lets the trace through. Any other exception is a bug
    and keeps its trace.

    Args:
        command: Returns the command's exit status.
        argv: The command line's arguments (without the program name).
        user_errors: Exception classes that mean bad input, files or settings.

    Returns:
        The command's exit status, USAGE_ERROR for a user error, INTERRUPTED after Ctrl-C.
    """
    try:
        return command()
    except user_errors as err:
        if "--debug" in argv:
            raise
        print(f"error: {error_line(err)}", file=sys.stderr)
        return USAGE_ERROR
    except KeyboardInterrupt as err:  # Ctrl-C: one line (what was kept, how to go on), the shell's 130
        if "--debug" in argv:
            raise
        print(f"interrupted: {error_line(err)}" if str(err).strip() else "interrupted", file=sys.stderr)
        return INTERRUPTED


@contextlib.contextmanager
def interrupt_after() -> Iterator[None]:
    """Hold Ctrl-C until the block ends, then raise KeyboardInterrupt: for imports of libraries
    that catch BaseException (trimesh does, around its optional imports), where a Ctrl-C was
    lost and the command ran on. A SIGINT that is ignored (a command started in the background)
    or handled otherwise is left as it is. Main thread only (as any signal handler)."""
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    held = []
    signal.signal(signal.SIGINT, lambda *_: held.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if held:
        raise KeyboardInterrupt
