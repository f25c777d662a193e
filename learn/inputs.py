"""Files the learner reads are untrusted: each is checked before it is opened or allocated for.

A FIFO or a device (`/dev/urandom`) blocks or never ends a read, so only regular files are opened
(checked with `stat`, which follows links). A header (an HDF5 dataset's shape, a `.npy` header, a
model's config) may claim more than the machine holds: the claim is compared with the memory
available before anything is allocated. Both checks are `clitools.limits`, which the simulator
uses too. JSON that does not parse names its file, line and column.
Every refusal is a ValueError or OSError naming the file (the CLI prints it as one `error:` line).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from clitools.limits import SizeError, check_memory, regular_file
from clitools.limits import format_bytes as size_text

TooLarge = SizeError
"""An input that would need more memory than this machine has available."""


def check_fits(nbytes: float, what: str, advice: str) -> None:
    """Refuse (TooLarge) when `what` needs more than the memory available, before it is allocated.

    Args:
        nbytes: Memory the input needs once read [bytes].
        what: The input and its size in words ("data/x: 1,000,000 frames of 240 x 181").
        advice: What to do instead.
    """
    check_memory(nbytes, what=what, advice=advice)


def read_json(path: str | Path, what: str, advice: str) -> dict:
    """A JSON object from `path` (a regular file); any failure names the file (and the line and
    column of a syntax error) and says `advice`."""
    path = regular_file(path, what)
    check_fits(20 * path.stat().st_size, f"{what} {path} ({size_text(path.stat().st_size)} of JSON)", advice)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{what} {path} is not valid JSON (line {err.lineno}, column {err.colno}: {err.msg}): {advice}"
        ) from None
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path} is not UTF-8 text: {advice}") from None
    except RecursionError:  # brackets nested deeper than the parser's stack
        raise ValueError(f"{what} {path} nests its JSON too deeply to read: {advice}") from None
    if not isinstance(record, dict):
        raise ValueError(f"{what} {path} holds a JSON {type(record).__name__}, not an object: {advice}")
    return record


def npy_header(path: str | Path, what: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of a `.npy` file from its header, checked against the bytes the file holds
    (a header may claim any shape), without reading the array."""
    path = regular_file(path, what)
    with open(path, "rb") as stream:
        try:
            version = np.lib.format.read_magic(stream)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(stream)
        except (ValueError, OSError, SyntaxError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ValueError(f"{what} {path} is not a .npy file ({first}): save the array with numpy.save") from None
        offset = stream.tell()
    if dtype.hasobject:
        raise ValueError(
            f"{what} {path} holds Python objects (dtype {dtype}), which only pickle could load (refused): save a "
            "numeric array"
        )
    claimed = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    held = path.stat().st_size - offset
    if held < claimed:
        raise ValueError(
            f"{what} {path} is truncated: its header says shape {shape} of {dtype} ({size_text(claimed)}), the file "
            f"holds {size_text(held)}: save it again"
        )
    return tuple(shape), dtype
