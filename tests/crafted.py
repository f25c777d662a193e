"""Crafted files for the safety tests."""

import subprocess
import sys
from pathlib import Path


def pickle_payload(path: Path, marker: Path) -> Path:
    """A .pt file that, if unpickled, runs `touch marker`; written by a separate interpreter so the
    class it pickles does not exist in the test's process. It also looks like a learn checkpoint
    (dataset format 1), so a loader that unpickled it would get past the first checks."""
    code = (
        "import os, torch\n"
        "class P:\n"
        f"    def __reduce__(self): return (os.system, ('touch {marker}',))\n"
        f"torch.save({{'model': P(), 'dataset': {{'format_version': 1}}}}, '{path}')\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    return path
