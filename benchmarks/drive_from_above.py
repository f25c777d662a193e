"""One whole drive seen from above: the LiDAR truth, each model's scans and the occupancy grid fed by
the first model without memory, every frame's returns placed in the world by its pose, so a person
sees what memory adds (walls kept after they fall silent) and what it costs (ghosts kept too).

    python benchmarks/drive_from_above.py --checkpoint k5=RUN/best.pt --checkpoint memory=RUN2/best.pt \
        --data data/crossengine --episode 3 --out drive.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import provenance, relative  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.data import DataConfig, Windows, level_slice, load_frames  # noqa: E402
from learn.evaluate import ECHO_PEAK_LEVEL, model_predictor, model_windows, plain_windows  # noqa: E402
from learn.grid_baselines import grid_predictors  # noqa: E402
from learn.models import ModelConfig  # noqa: E402
from learn.plots import plot_drive_from_above  # noqa: E402
from learn.scan import LABEL_THRESHOLD, first_return_ranges  # noqa: E402


def ranges_of(predict, windows: Windows, indices: np.ndarray, threshold: float) -> np.ndarray:
    """Each window's predicted scan (len(indices), A) [m], inf = no return."""
    range_m = torch.as_tensor(windows.frames.range_m, device=windows.device)
    with torch.no_grad():
        x, _ = windows.batch(indices)
        image = predict(x).float()[:, 0]
    return first_return_ranges(image, range_m, threshold=threshold).cpu().numpy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", action="append", required=True, help="NAME=PATH, repeated")
    p.add_argument("--data", type=Path, required=True, help="dataset folder with poses")
    p.add_argument("--episode", type=int, default=None, help="episode id (default: the first)")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    frames = load_frames(args.data)
    models = {}
    for item in args.checkpoint:
        name, _, path = item.partition("=")
        models[name] = load_checkpoint(path, args.device)
    first = DataConfig(**next(iter(models.values()))[1]["data_config"])
    windows = Windows(level_slice(frames), plain_windows(first), args.device)  # the grids' and labels': the level slice
    episode = int(windows.episode[0]) if args.episode is None else args.episode
    indices = np.flatnonzero(windows.episode == episode)
    if not len(indices):
        raise SystemExit(f"episode {episode} has no window in {args.data}")
    _, labels = windows.batch(indices)
    range_m = torch.as_tensor(frames.range_m, device=windows.device)
    scans = {"LiDAR truth": first_return_ranges(labels[:, 0], range_m, threshold=LABEL_THRESHOLD).cpu().numpy()}
    feeders = {}
    for name, (model, ckpt) in models.items():
        theirs, threshold = model_windows(frames, ckpt, args.device), float(ckpt["threshold"])
        scans[name] = ranges_of(model_predictor(model), theirs, indices, threshold)
        if not feeders and not ModelConfig(**ckpt["model_config"]).uses_odometry:
            feeders[name] = (model_predictor(model), threshold, theirs)
    for name, images in grid_predictors(windows, indices, feeders, ECHO_PEAK_LEVEL).items():
        if name.removeprefix("occupancy grid (").rstrip(")") in feeders:
            image = images.by_window(indices)[:, 0]
            scans[name] = first_return_ranges(image, range_m, threshold=0.5).cpu().numpy()
    poses = frames.pose[windows.starts[indices] + windows.config.label_offset]
    scenario = frames.scenarios[int(windows.scenario[indices[0]])]
    stamp = provenance(args.device)
    title = (
        f"{relative(args.data)}, episode {episode} ({scenario}, {len(indices)} frames) from above; "
        f"commit {stamp['commit'][:12] if stamp.get('commit') else '?'}, {stamp.get('device_name') or args.device}"
    )
    plot_drive_from_above(scans, poses, frames.azimuth_rad, args.out, title=title)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
