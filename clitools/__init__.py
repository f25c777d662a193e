"""What both command lines (`python -m acoustic_sim`, `python -m learn`) share, in the standard
library alone so that the learner needs nothing of the simulator.

`settings`: one grammar for `--set section.field=value`. `outputs`: how every output is written
(never over an input, never over an existing file without `--overwrite`, whole or not at all).

A setting names a field of a tree of frozen dataclasses by its path from the root
(`tracer.max_bounces=1`, `processing.grid.range_max_m=4`, `train.lr=3e-4`) and gives its value as
text, read as the field's type:

- int: an integer (`3`, `-2`), or a number with an integral value (`1e3`, `2.0`).
- float: any number (`3e-4`, `-2`, `.5`); `nan` and `inf` are read as numbers, so the config
  itself refuses them by name.
- bool: `true` or `false` (any case); `1`, `0`, `yes` and `no` are refused.
- Optional fields (`X | None`, `Literal[None, ...]`): `none` or `null` (any case) is None.
- Literal: one of its choices, bare (`db`) or quoted (`"db"`).
- str: the text as it stands, or unquoted when quoted.
- tuple: a JSON list (`[0, 10]`, nested `[[0, 0, 0], [0.1, 0, 0]]`), each item read as its type.
- A union (`float | tuple[float, ...]`): the first of its types that reads the text.
- A section (a field holding a dataclass) takes the name of a preset, one of its class's public
  classmethods (`lidar=multibeam_64x1024`, `augment=none`).

A setting that cannot be applied raises SettingsError (a ValueError) naming the setting: an unknown
section or field (listing those there are), a value not of the field's type (saying what it
takes), or the config's own refusal of the value.

`errors`: how a command ends on a user's mistake: one `error: ...` line, exit status 2 (`run_command`).
`help`: how `--help` reads: each default said once, examples at the end (`HelpFormatter`, `examples`).
`words`: how counts read in printed lines (`counted(1, "shard")` is `1 shard`).
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
