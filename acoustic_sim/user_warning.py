"""Warnings shown at the user's line: the first frame outside this package, however deep inside it
the warning is raised (what Python 3.12's `warnings.warn(skip_file_prefixes=...)` does)."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

_PACKAGE = str(Path(__file__).parent)


def warn_user(message: str) -> None:
    """`warnings.warn(message)` (UserWarning) attributed to the nearest caller outside acoustic_sim."""
    level, frame = 1, sys._getframe(1)
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, stacklevel=level + 1)  # + 1: this function's own frame
