"""Crafted files and processes for the safety tests."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py


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


def damage_energyscape_chunk(shard: Path) -> None:
    """Flip 16 bytes in the middle of the shard's first energyscape chunk, as a bad disk sector
    would: the file still opens, and only the chunk's checksum can tell."""
    with h5py.File(shard, "r") as f:
        chunk = f["energyscape"].id.get_chunk_info(0)
    raw = bytearray(shard.read_bytes())
    middle = chunk.byte_offset + chunk.size // 2
    raw[middle : middle + 16] = bytes(255 - b for b in raw[middle : middle + 16])
    shard.write_bytes(bytes(raw))


def sigint_as_from_a_terminal() -> None:
    """`preexec_fn` for a child that a test stops with SIGINT: a shell running commands in the
    background (a CI runner, `cmd &`) starts them with SIGINT ignored, and Python then installs no
    KeyboardInterrupt handler, so the child would never see the test's Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def ctrl_c_after(command: list[str], delay_s: float, cwd: Path, *, loaded: str = "") -> tuple[int, str]:
    """Run `command` (`python -m ...` arguments) as a terminal would, press Ctrl-C (SIGINT to its
    process group) after `delay_s` seconds, counted from when the process has mapped a library whose
    file name holds `loaded` if one is given (a moment inside that library's import, however fast the
    machine); its exit status and standard error."""
    import time

    process = subprocess.Popen(
        [sys.executable, *command],
        cwd=cwd,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
        preexec_fn=sigint_as_from_a_terminal,
    )
    maps = Path(f"/proc/{process.pid}/maps")
    while loaded and process.poll() is None:
        try:
            if loaded in maps.read_text():
                break
        except OSError:  # the process is gone: its exit status says why
            break
        time.sleep(0.002)
    time.sleep(delay_s)
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=120)
    return process.returncode, err
