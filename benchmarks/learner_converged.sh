#!/usr/bin/env bash
# Converged learner results on one GPU: the `paper` suite at 60,000 frames (~54,000 for training,
# whole episodes held out for validation), each network trained with several seeds side by side
# until validation scan F1 (0.10 m) stops improving for PATIENCE sub-epochs of 12,000 windows,
# then scored on its held-out episodes and on a fresh 1,000-frame drive (suite seed 1000: scenes
# no model saw) beside the echo-peak and empty baselines. Phases, so each fits one 10-minute call
# of the GPU machine; `train` resumes from last.pt, so calling it again continues unfinished runs.
#
#   bash benchmarks/learner_converged.sh gen   WORKDIR
#   bash benchmarks/learner_converged.sh train WORKDIR polar_unet 0 1 2
#   bash benchmarks/learner_converged.sh eval  WORKDIR polar_unet 0 1 2
#
# The pretrained model shipped in learn/pretrained/ is polar_unet seed 0's best.pt without its
# optimizer state (`python -c "from learn.train import strip_checkpoint; strip_checkpoint(A, B)"`).
# Environment: FRAMES (60000), MINUTES (time budget per call and run), DEVICE (cuda), GEN_DEVICE.
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
DEVICE=${DEVICE:-cuda}
mkdir -p "$W/logs" "$W/runs"
case $phase in
gen)
  GEN=(--workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --quiet)
  python -m acoustic_sim generate --suite paper --frames "${FRAMES:-60000}" --seed 0 --out "$D/paper" "${GEN[@]}"
  python -m acoustic_sim generate --suite paper --frames "${DRIVE_FRAMES:-1000}" --seed 1000 --out "$D/drive" "${GEN[@]}"
  ;;
train)
  model=$1
  shift
  if [ "$model" = paper ]; then  # the paper's recipe: MSE, Adam 1e-4, batch 12
    OPTS=(--loss mse --lr 1e-4 --batch-size 12)
  else
    OPTS=(--loss bce --lr 1e-3 --batch-size 16)
  fi
  for s in "$@"; do
    python -m learn train --data "$D/paper" --out "$W/runs/${model}_seed$s" --model "$model" --frames 5 --seed "$s" \
      "${OPTS[@]}" --epochs "${EPOCHS:-100}" --patience "${PATIENCE:-4}" --max-train-windows "${WINDOWS:-12000}" \
      --max-val-windows 2000 --max-minutes "${MINUTES:-8}" --resume --device "$DEVICE" --quiet \
      >> "$W/logs/${model}_seed$s.log" 2>&1 &
  done
  wait
  ;;
eval)
  model=$1
  shift
  # One process: each dataset is read once for all seeds (60,000 frames take a while to load).
  python - "$W" "$model" "$DEVICE" "$@" <<'PY'
import sys

from learn.data import load_frames
from learn.evaluate import evaluate

work, model, device, seeds = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
for data, folder in (("paper", "held_out"), ("drive", "drive")):  # held_out: the episodes validation held out
    frames = load_frames(f"{work}/data/{data}")
    for seed in seeds:
        run = f"{work}/runs/{model}_seed{seed}"
        report = evaluate(f"{run}/best.pt", frames, f"{run}/{folder}", device=device)
        f1 = {k: round(v["all"]["scan_f1"]["mean"], 3) for k, v in report["results"].items()}
        print(f"{run} on {data} ({report['split']}, {report['windows']} windows): scan F1 {f1}", flush=True)
PY
  ;;
*)
  echo "usage: $0 gen|train|eval WORKDIR [MODEL SEED...]" >&2
  exit 2
  ;;
esac
