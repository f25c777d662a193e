#!/usr/bin/env bash
# Scaling out on the GPUs of one host (a lent nvidia-h200-x2 or larger), in phases that fit one
# 10-minute call each; results under $RESULTS (default benchmarks/results/multi_gpu):
#
#   bash benchmarks/multi_gpu.sh gen   WORKDIR   # paper suite on one GPU and on all: frames/s, identical shards
#   bash benchmarks/multi_gpu.sh ddp   WORKDIR   # bench_learn --ddp: windows/s on 1..N GPUs, efficiency
#   bash benchmarks/multi_gpu.sh train WORKDIR   # one GPU at batch 16 vs N GPUs at 16/N each (same global batch)
#   bash benchmarks/multi_gpu.sh check WORKDIR   # on ONE GPU: --workers 2 --device auto gives the same shards,
#                                                # torchrun's NCCL path at world size 1 trains as the plain run
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
  python benchmarks/same_shards.py "$W/one_gpu" "$W/all_gpus" | tee "$R/generate_identical.txt"
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
check)
  python -m acoustic_sim generate --suite tiny --out "$W/one" --device cuda:0 --shards 3 --quiet
  python -m acoustic_sim generate --suite tiny --out "$W/two" --device auto --workers 2 --shards 3 --quiet
  python benchmarks/same_shards.py "$W/one" "$W/two" | tee "$R/one_gpu_check.txt"
  OPTS=(--data "$W/one" --model polar_unet --width 4 --frames 3 --epochs 2 --batch-size 2 --loss bce
    --val-fraction 0.5 --device cuda --quiet --overwrite)
  torchrun --standalone --nproc_per_node 1 -m learn train "${OPTS[@]}" --out "$W/ddp" | tee -a "$R/one_gpu_check.txt"
  python -m learn train "${OPTS[@]}" --out "$W/single" | tee -a "$R/one_gpu_check.txt"
  python - "$W" <<'PY' | tee -a "$R/one_gpu_check.txt"
import csv, json, sys
for key in ("train_loss", "val_scan_f1"):
    runs = {k: [r[key] for r in csv.DictReader(open(f"{sys.argv[1]}/{k}/history.csv"))] for k in ("ddp", "single")}
    print(key, runs)
for k in ("ddp", "single"):  # the torchrun run must have joined an NCCL group of one process
    print(k, "process_group", json.load(open(f"{sys.argv[1]}/{k}/config.json"))["process_group"])
PY
  ;;
*)
  echo "usage: $0 gen|ddp|train|check WORKDIR" >&2
  exit 2
  ;;
esac
