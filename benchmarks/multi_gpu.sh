#!/usr/bin/env bash
# Scaling out on the GPUs of one host (a lent nvidia-h200-x2 or larger), in phases that fit one
# 10-minute call each; results under $RESULTS (default benchmarks/results/multi_gpu):
#
#   bash benchmarks/multi_gpu.sh gen   WORKDIR   # paper suite on one GPU and on all: frames/s, identical shards
#   bash benchmarks/multi_gpu.sh ddp   WORKDIR   # bench_learn --ddp: windows/s on 1..N GPUs, efficiency
#   bash benchmarks/multi_gpu.sh train WORKDIR   # one GPU at batch 16 vs N GPUs at 16/N each (same global batch)
#
# Environment: FRAMES (12500), WORKERS (8), EPOCHS (6 sub-epochs of 12,000 windows for `train`).
set -euo pipefail
phase=$1 W=$2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
R=${RESULTS:-benchmarks/results/multi_gpu}
GPUS=$(python -c "import torch; print(torch.cuda.device_count())")
mkdir -p "$W" "$R"
case $phase in
gen)
  GEN=(--suite paper --frames "${FRAMES:-12500}" --seed 0 --workers "${WORKERS:-8}" --quiet)
  python -m acoustic_sim generate "${GEN[@]}" --device cuda:0 --out "$W/one_gpu" | tee "$R/generate_one_gpu.txt"
  python -m acoustic_sim generate "${GEN[@]}" --device auto --out "$W/all_gpus" | tee "$R/generate_${GPUS}_gpus.txt"
  python - "$W/one_gpu" "$W/all_gpus" <<'PY' | tee "$R/generate_identical.txt"
import sys
from pathlib import Path

import h5py
import numpy as np

def arrays(folder):
    out = {}
    for path in sorted(Path(folder).glob("shard-*.h5")):
        with h5py.File(path) as f:
            f.visititems(lambda n, o, p=path: out.__setitem__(f"{p.name}/{n}", o[()]) if isinstance(o, h5py.Dataset) else None)
    return out

one, every = arrays(sys.argv[1]), arrays(sys.argv[2])
same = one.keys() == every.keys() and all(np.array_equal(one[k], every[k]) for k in one)
print(f"{len(one)} arrays in {len(list(Path(sys.argv[1]).glob('shard-*.h5')))} shards; one GPU vs all GPUs identical: {same}")
PY
  ;;
ddp)
  python benchmarks/bench_learn.py --device cuda --ddp --batch 16 --out "$R"
  ;;
train)
  OPTS=(--data "$W/one_gpu" --model polar_unet --loss bce --lr 1e-3 --seed 0 --epochs "${EPOCHS:-6}" --patience 100
    --max-train-windows 12000 --max-val-windows 2000 --device cuda --quiet --overwrite)
  python -m learn train "${OPTS[@]}" --batch-size 16 --out "$W/runs/one_gpu" > "$R/train_one_gpu.log" 2>&1
  torchrun --standalone --nproc_per_node "$GPUS" -m learn train "${OPTS[@]}" --batch-size $((16 / GPUS)) \
    --out "$W/runs/${GPUS}_gpus" > "$R/train_${GPUS}_gpus.log" 2>&1
  grep -h "^epoch" "$R/train_one_gpu.log" "$R/train_${GPUS}_gpus.log"
  cp "$W/runs/one_gpu/history.csv" "$R/history_one_gpu.csv"
  cp "$W/runs/${GPUS}_gpus/history.csv" "$R/history_${GPUS}_gpus.csv"
  ;;
*)
  echo "usage: $0 gen|ddp|train WORKDIR" >&2
  exit 2
  ;;
esac
