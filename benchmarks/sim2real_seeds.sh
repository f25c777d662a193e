#!/usr/bin/env bash
# Repeats the sim-to-real study of benchmarks/learner_study.sh with other seeds: each seed draws
# its own ablation and reality scenes, drives and noise, and seeds training. Two phases so each
# fits one 10-minute call on the GPU machine; the seeds train side by side on the one GPU.
# usage: bash benchmarks/sim2real_seeds.sh gen|train WORKDIR SEED...
set -euo pipefail
phase=$1 W=$2; shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
mkdir -p "$W/logs"
python benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device cuda
for s in "$@"; do
  D=$W/data_seed$s
  if [ "$phase" = gen ]; then
    python -m acoustic_sim generate --suite ablation --frames 4000 --seed "$s" --out "$D/ablation" --workers 8 --device cuda:0 --quiet
    python -m acoustic_sim generate --suite reality --seed "$s" --out "$D/reality" --workers 8 --device cuda:0 --quiet
  else
    python -m learn sim2real --ablation "$D/ablation" --reality "$D/reality" --out "$W/runs/sim2real_seed$s" \
      --model polar_unet --frames 5 --epochs 20 --patience 4 --lr 1e-3 --max-train-windows 3000 --max-minutes 1.2 \
      --seed "$s" --device cuda --quiet --max-val-windows 1000 --no-augment > "$W/logs/sim2real_seed$s.log" 2>&1 &
  fi
done
wait
