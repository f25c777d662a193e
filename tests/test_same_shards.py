"""benchmarks/same_shards.py: the identity check of two datasets, variants' subfolders included."""

import subprocess
import sys

import h5py
import numpy as np

from benchmarks import same_shards


def write(folder, variant, values):
    path = folder / variant / "shard-00000.h5"
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["energyscape"] = np.asarray(values, dtype=np.float16)


def check(a, b) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, same_shards.__file__, str(a), str(b)], capture_output=True, text=True)


def test_variant_subfolders_are_compared_and_a_difference_or_nothing_fails(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        write(folder, "v0", [1, 2, 3])
        write(folder, "v1", [4, 5, 6])
    assert set(same_shards.arrays(a)) == {"v0/shard-00000.h5/energyscape", "v1/shard-00000.h5/energyscape"}
    done = check(a, b)
    assert done.returncode == 0 and "2 arrays, identical: True" in done.stdout
    write(b, "v1", [4, 5, 7])  # one value of one variant
    assert check(a, b).returncode == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check(empty, empty).returncode == 1  # no shard found is never "identical"
