"""What both command lines (`python -m acoustic_sim`, `python -m learn`) share, in the standard
library alone so that the learner needs nothing of the simulator.

- `settings`: one grammar for `--set section.field=value` on a tree of frozen dataclasses.
- `outputs`: how every output is written (never over an input, never over an existing file
  without `--overwrite`, whole or not at all).
- `locks`: one process at a time writes a folder (a training run).
- `limits`: input files checked by `stat` before they are opened, sizes checked against the
  memory or disk they would take before anything is allocated.
- `errors`: how a command ends on a user's mistake (one `error:` line, exit 2) or on Ctrl-C.
- `help`: how `--help` reads (each default said once, examples at the end).
- `words`: how counts read in printed lines (`counted(1, "shard")` is `1 shard`).
"""

from .errors import error_line, run_command
from .help import HelpFormatter, example_commands, examples
from .settings import SettingsError, apply_settings, read_value
from .words import counted

__all__ = [
    "HelpFormatter",
    "SettingsError",
    "apply_settings",
    "counted",
    "error_line",
    "example_commands",
    "examples",
    "read_value",
    "run_command",
]
