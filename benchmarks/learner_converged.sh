#!/usr/bin/env bash
# Converged learner results on one GPU: the `paper` suite at 60,000 frames (~54,000 for training,
# whole episodes held out for validation), each network trained with several seeds side by side
# until validation scan F1 (0.10 m) stops improving for PATIENCE sub-epochs of 12,000 windows,
# then scored on its validation episodes (which early stopping read) and on a fresh 1,000-frame drive (suite seed 1000: scenes
# no model saw) beside the echo-peak and empty baselines. Phases, so each fits one 10-minute call
# of the GPU machine; `train` resumes from last.pt, so calling it again continues unfinished runs.
#
#   bash benchmarks/learner_converged.sh gen   WORKDIR
#   bash benchmarks/learner_converged.sh train WORKDIR polar_unet 0 1 2
#   bash benchmarks/learner_converged.sh eval  WORKDIR polar_unet 0 1 2
#   K=1 bash benchmarks/learner_converged.sh train WORKDIR polar_unet 0 1 2   # Table 2's other window lengths
#   bash benchmarks/learner_converged.sh pack  WORKDIR DEST [RUN...]  # -> DEST/state.tgz.part* (<= 15 MiB each)
#   bash benchmarks/learner_converged.sh unpack WORKDIR SRC     # and back, on the next machine
#
# pack/unpack carry unfinished runs from one lent machine to the next (files come back in parts of
# at most 16 MiB): checkpoints without optimizer state (Adam restarts its moments on resume, with a
# warning) and with convolution/linear weights in bfloat16, the precision autocast computes them
# in (batch-norm and bias tensors stay float32); `train` then resumes them. Naming RUNs (folder
# names under WORKDIR/runs) packs only their checkpoints, so finished runs travel without theirs;
# every run's history, reports and logs always travel. A RUN may be nested: sim2real_ablation_seed0
# packs all three of its variants, sim2real_ablation_seed0/bounces_1 one of them. A best.pt that is
# the same checkpoint as last.pt (the last sub-epoch improved) travels once, as last.pt (the paper
# network's are 27 MB).
#
# The pretrained model shipped in learn/pretrained/ is polar_unet seed 0's best.pt without its
# optimizer state (`python -c "from learn.checkpoint import strip_checkpoint; strip_checkpoint(A, B)"`).
# Each training process holds the whole dataset on the GPU (~8-9 GB with 60,000 frames): nine side
# by side ran an 80 GB H100 out of memory; keep to seven at most.
# Environment: K (window length, 5; runs of other K are named MODEL_kK_seedS), FRAMES (60000),
# MINUTES (time budget per call and run), DEVICE (cuda), GEN_DEVICE,
# TRAIN_OPTS (more `learn train` options, e.g. --channels-last). Runs train on the windows as simulated
# (--no-augment), as the shipped model did.
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
DEVICE=${DEVICE:-cuda}
K=${K:-5}
run_name() { if [ "$K" = 5 ]; then echo "${1}_seed$2"; else echo "${1}_k${K}_seed$2"; fi; }
mkdir -p "$W/logs" "$W/runs"
# each call's commit, machine and versions, kept with the logs (pack carries them)
python benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device "$DEVICE"
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
    name=$(run_name "$model" "$s")
    python -m learn train --data "$D/paper" --out "$W/runs/$name" --model "$model" --frames "$K" --seed "$s" \
      "${OPTS[@]}" --no-augment ${TRAIN_OPTS:-} --epochs "${EPOCHS:-100}" --patience "${PATIENCE:-4}" --max-train-windows "${WINDOWS:-12000}" \
      --max-val-windows 2000 --max-minutes "${MINUTES:-8}" --resume --device "$DEVICE" --quiet \
      >> "$W/logs/$name.log" 2>&1 &
  done
  wait
  ;;
eval)
  model=$1
  shift
  # One process: each dataset is read once for all seeds (60,000 frames take a while to load).
  names=()
  for s in "$@"; do names+=("$(run_name "$model" "$s")"); done
  python - "$W" "$DEVICE" "${names[@]}" <<'PY'
import sys

from learn.data import load_frames
from learn.evaluate import evaluate

work, device, names = sys.argv[1], sys.argv[2], sys.argv[3:]
for data, folder in (("paper", "held_out"), ("drive", "drive")):  # held_out: the validation episodes (early stopping read them)
    frames = load_frames(f"{work}/data/{data}")
    for name in names:
        run = f"{work}/runs/{name}"
        report = evaluate(f"{run}/best.pt", frames, f"{run}/{folder}", device=device)
        f1 = {k: round(v["all"]["scan_f1"]["mean"], 3) for k, v in report["results"].items()}
        print(f"{run} on {data} ({report['split']}, {report['windows']} windows): scan F1 {f1}", flush=True)
PY
  ;;
pack)
  dest=$1
  shift
  rm -rf "$W/packed"
  python - "$W" "$@" <<'PY'
import sys
from pathlib import Path

import torch

work, keep = Path(sys.argv[1]), sys.argv[2:]


def kept(run):  # a RUN and every folder below it
    rel = run.relative_to(work / "runs").as_posix()
    return not keep or any(rel == k or rel.startswith(k + "/") for k in keep)


for src in sorted(p for p in [*work.glob("runs/**/*"), *work.glob("logs/*")] if p.is_file()):
    dst = work / "packed" / src.relative_to(work)
    if src.suffix == ".pt" and not kept(src.parent):
        continue
    if src.name == "best.pt" and (src.parent / "last.pt").exists():
        state = torch.load(src.parent / "last.pt", map_location="cpu", weights_only=True)["state"]
        if state["epoch"] == state.get("best_epoch"):  # the same checkpoint: unpack copies it back
            dst.parent.mkdir(parents=True, exist_ok=True)
            (dst.parent / "best_is_last").touch()
            continue
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.suffix != ".pt":
        dst.write_bytes(src.read_bytes())
        continue
    ckpt = torch.load(src, map_location="cpu", weights_only=True)
    ckpt.pop("optimizer", None)
    ckpt["model"] = {k: v.bfloat16() if v.is_floating_point() and v.ndim >= 2 else v for k, v in ckpt["model"].items()}
    torch.save(ckpt, dst)
PY
  mkdir -p "$dest"
  tar -C "$W/packed" -czf - runs logs | split -b 15m - "$dest/state.tgz.part"
  ;;
unpack)
  src=$1
  mkdir -p "$W"
  cat "$src"/state.tgz.part* | tar -C "$W" -xzf -
  find "$W/runs" -name best_is_last | while read -r m; do cp "${m%/*}/last.pt" "${m%/*}/best.pt" && rm "$m"; done
  ;;
*)
  echo "usage: $0 gen|train|eval|pack|unpack WORKDIR [MODEL SEED...]" >&2
  exit 2
  ;;
esac
