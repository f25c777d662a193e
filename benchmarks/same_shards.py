"""Whether two dataset folders hold identical shards: every array of every shard-*.h5, bit for bit,
in the folder and its variants' subfolders (a suite with several physics variants, such as
`randomised`, writes each variant's shards into its own).

python benchmarks/same_shards.py FOLDER_A FOLDER_B   # prints one line; exit 1 if they differ
"""

import sys
from pathlib import Path

import h5py
import numpy as np


def arrays(folder: str) -> dict[str, np.ndarray]:
    out = {}
    root = Path(folder)
    for path in sorted(root.rglob("shard-*.h5")):
        with h5py.File(path) as f:
            for name in _dataset_names(f):
                out[f"{path.relative_to(root).as_posix()}/{name}"] = f[name][()]
    return out


def _dataset_names(group: h5py.Group) -> list[str]:
    names: list[str] = []
    group.visititems(lambda name, item: names.append(name) if isinstance(item, h5py.Dataset) else None)
    return names


if __name__ == "__main__":
    a, b = arrays(sys.argv[1]), arrays(sys.argv[2])
    same = bool(a) and a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    print(f"{sys.argv[1]} vs {sys.argv[2]}: {len(a)} arrays, identical: {same}")
    sys.exit(0 if same else 1)
