"""`python -m learn ...`: the command line (learn/cli.py), once PyTorch is known to be installed.

torch is the `[learn]` extra, and every command (and `--help`, whose choices come from the model
registry) imports it; without it the answer is one line on how to install it, not a trace."""

import signal
import sys

INSTALL_HINT = (
    'error: the learner needs PyTorch: pip install "sonar2lidar[learn]" '
    '(in a clone: pip install ".[learn]"; CPU only: first pip install torch==2.13.0 '
    "--index-url https://download.pytorch.org/whl/cpu)"
)


def run() -> int:
    """`learn.cli.main` where torch imports; else the install hint and exit status 2 (a usage error).
    Ctrl-C while torch and the command line are still importing (seconds on a busy machine) ends
    as one after them does: one line and the shell's 130, nothing written yet. It is held until the
    imports end (as `python -m acoustic_sim` does): one landing in the import machinery's weakref
    callbacks was only printed, and the command ran on. A SIGINT that is ignored stays so."""
    held: list[bool] = []
    holding = signal.getsignal(signal.SIGINT) is signal.default_int_handler
    if holding:
        signal.signal(signal.SIGINT, lambda *_: held.append(True))
    try:
        import torch  # noqa: F401

        from .cli import main
    except ModuleNotFoundError as err:
        if err.name != "torch":  # torch is there but one of its own imports is missing: show that
            raise
        print(INSTALL_HINT, file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # raised by a library's own handling
        held.append(True)
    finally:
        if holding:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    return _interrupted_at_start() if held else main()


def _interrupted_at_start() -> int:
    if "--debug" in sys.argv:
        raise KeyboardInterrupt
    print("interrupted: while starting, before anything was read or written", file=sys.stderr)
    return 130  # clitools.INTERRUPTED, not imported: clitools may be what was being imported


sys.exit(run())
