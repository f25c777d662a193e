"""`python -m learn ...`: the command line (learn/cli.py), once PyTorch is known to be installed.

torch is the `[learn]` extra, and every command (and `--help`, whose choices come from the model
registry) imports it; without it the answer is one line on how to install it, not a trace."""

import sys

INSTALL_HINT = (
    'error: the learner needs PyTorch: pip install "sonar2lidar[learn]" '
    '(in a clone: pip install ".[learn]"; CPU only: first pip install torch==2.13.0 '
    "--index-url https://download.pytorch.org/whl/cpu)"
)


def run() -> int:
    """`learn.cli.main` where torch imports; else the install hint and exit status 2 (a usage error)."""
    try:
        import torch  # noqa: F401
    except ModuleNotFoundError as err:
        if err.name != "torch":  # torch is there but one of its own imports is missing: show that
            raise
        print(INSTALL_HINT, file=sys.stderr)
        return 2
    from .cli import main

    return main()


sys.exit(run())
