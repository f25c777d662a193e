#!/usr/bin/env bash
# Issue 40's study: does the array's elevation help a model read walls off another engine's and a
# real-like sensor's echoes? The protocol of sim2real_study.sh and memory_study.sh (randomised suite,
# 3 secondary bounces, FRAMES frames, seeds 0-2, early stopping on validation scan F1, each run's
# return threshold calibrated on its own validation windows only), with the augmentation and row
# contrast the sim-to-real study chose, on one dataset beamformed at ELEVATIONS, in two arms:
#
#   e1   polar UNet, K = 5, the level slice alone (model.elevation_deg=[0]): today's model, which
#        trains bit for bit as on a dataset beamformed at 0 deg only
#   e3   polar UNet, K = 5, the elevations -20, 0 and 20 deg as input channels
#   e5   polar UNet, K = 5, the elevations -20, -10, 0, 10 and 20 deg (ARMS="e1 e3 e5" with
#        ELEVATIONS=[-20,-10,0,10,20]: the e1 and e3 arms read the same frames' rows, bit for bit those
#        of a dataset beamformed at their elevations alone, and each run holds only its rows)
#
# Scored by `learn evaluate` (both arms of a seed side by side, with the echo peak and the empty
# image; no occupancy grids) on the held-out episodes of the training data, on `reality`, on
# `crossengine` and `crossengine_rough` (another engine, specular and rough walls; never trained,
# stopped or calibrated on) and on a fresh drive (the paper suite, seed 1000), every test set
# beamformed at the same ELEVATIONS. Then recall by incidence on both crossengine sets, and
# elevation_study_summary.py.
#
#   bash benchmarks/elevation_study.sh gen   WORKDIR           # the training data
#   bash benchmarks/elevation_study.sh tests WORKDIR           # the test sets (while training runs)
#   bash benchmarks/elevation_study.sh train WORKDIR SEED...   # both arms of each seed, side by side
#   bash benchmarks/elevation_study.sh score WORKDIR SEED...
#   bash benchmarks/elevation_study.sh pack  WORKDIR DEST      # DEST/study.tgz.part* (cat | tar -xz)
#
# On the GPU machine (one H100/H200; calls back to back, each under 10 minutes; the interpreter is python3:
# never link or wrap it under another name): install Warp and pyroomacoustics, copy the repository to
# $HOME (each call brings a fresh working tree), then
#   call 1: gen W (30,000 frames: 45 s), then `tests W & MINUTES=6 train W 0 1 2; wait` (the test sets
#           are made while the runs train, within the call)
#   call 2: MINUTES=6 train W 0 1 2 again (--resume goes on from each run's last epoch)
#   call 3: score W 0 1 2 (2.5 minutes), then pack W "$OUT" (parts of 15 MB; a call returns 64 MB at most)
# A process left running in the background does not outlive its call: the machine stops it when
# the call returns (a nohup'd train phase ended mid-epoch in session 23), so every phase ends
# within its call, and a long training runs in legs.
# A run holds 2.6 GB per elevation it reads of 30,000 frames, on the GPU and in host memory, plus its
# activations and CUDA graphs: six runs of e1 and e3 at 30,000 frames fit one 80 GB H100, but nine of e1,
# e3 and e5 at 20,000 frames (47 GB of frames) filled it (71 GB) and three runs died out of memory
# (session 24): spread nine runs over two GPUs (GPUS=2), or train one arm at a time (ARMS=e3).
#
# Environment: ARMS ("e1 e3"), FRAMES (40000), ELEVATIONS ([-20,0,20]), REALITY_FRAMES (the suite's 1,500),
# CROSS_FRAMES (1000), FRESH_FRAMES (1000), DEVICE (cuda; GPUS=2 spreads runs over cuda:0..),
# GEN_DEVICE (cuda:0), WORKERS (8), CROSS_WORKERS (12), MINUTES (per run, 12), EPOCHS (100),
# PATIENCE (4), SUBEPOCH (12000), VAL (2000).
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
DEVICE=${DEVICE:-cuda}
read -r -a ARMS <<< "${ARMS:-e1 e3}"
ELEVATIONS=${ELEVATIONS:-[-20,0,20]}
BEAMS=(--set "processing.elevation_deg=$ELEVATIONS")
mkdir -p "$W/logs" "$W/runs" "$W/scores" "$W/summary"
python3 benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device "$DEVICE"

arm_options() { # the options that make an arm
  case $1 in
  e1) echo "--set model.elevation_deg=[0]" ;;
  e3) echo "--set model.elevation_deg=[-20,0,20]" ;;
  e5) echo "--set model.elevation_deg=[-20,-10,0,10,20]" ;;
  *)
    echo "unknown arm $1" >&2
    exit 2
    ;;
  esac
}

case $phase in
gen)
  python3 -m acoustic_sim generate --suite randomised --variants bounces_3 --frames "${FRAMES:-40000}" \
    --out "$D/randomised" "${BEAMS[@]}" --workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet
  ;;
tests)
  GEN=(--workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --quiet "${BEAMS[@]}")
  CROSS=(--frames "${CROSS_FRAMES:-1000}" --workers "${CROSS_WORKERS:-12}" --device "${GEN_DEVICE:-cuda:0}" --seed 0
    --quiet "${BEAMS[@]}")
  python3 -m acoustic_sim generate --suite crossengine --out "$D/crossengine" "${CROSS[@]}" &
  python3 -m acoustic_sim generate --suite crossengine_rough --out "$D/crossengine_rough" "${CROSS[@]}" &
  python3 -m acoustic_sim generate --suite reality ${REALITY_FRAMES:+--frames "$REALITY_FRAMES"} --out "$D/reality" \
    "${GEN[@]}" --seed 0
  python3 -m acoustic_sim generate --suite paper --frames "${FRESH_FRAMES:-1000}" --out "$D/fresh" "${GEN[@]}" --seed 1000
  wait
  ;;
train)
  graphs=$([[ $DEVICE == cuda* ]] && echo --cuda-graphs || true)
  n=0
  for s in "$@"; do
    for arm in "${ARMS[@]}"; do
      dev=$DEVICE
      [[ -n ${GPUS:-} ]] && dev=cuda:$((n % GPUS))
      n=$((n + 1))
      run=(python3 -m learn train --data "$D/randomised/bounces_3" --out "$W/runs/seed$s/$arm" --model polar_unet
        $(arm_options "$arm") --frames 5 --set model.row_contrast=true --seed "$s" --loss bce --lr 1e-3
        --batch-size 16 --epochs "${EPOCHS:-100}" --patience "${PATIENCE:-4}" --max-train-windows "${SUBEPOCH:-12000}"
        --max-val-windows "${VAL:-2000}" --max-minutes "${MINUTES:-12}" --resume --device "$dev" --quiet)
      # CUDA graphs where they compile; a run they fail for starts again eagerly (same seed, same draws)
      ("${run[@]}" $graphs || "${run[@]}") >> "$W/logs/seed${s}_$arm.log" 2>&1 &
    done
  done
  wait
  ;;
score)
  for s in "$@"; do
    ckpts=()
    for arm in "${ARMS[@]}"; do ckpts+=(--checkpoint "$arm=$W/runs/seed$s/$arm/best.pt"); done
    for test in validation reality crossengine crossengine_rough fresh; do
      data=$D/$test
      [[ $test == validation ]] && data=$D/randomised/bounces_3 # its held-out episodes
      python3 -m learn evaluate "${ckpts[@]}" --data "$data" --out "$W/scores/seed$s/$test" --no-grids \
        --device "$DEVICE" --quiet --overwrite >> "$W/logs/score_seed${s}_$test.log" 2>&1 &
    done
  done
  for arm in "${ARMS[@]}"; do
    runs=()
    for s in "$@"; do runs+=("$W/runs/seed$s/$arm"); done
    for test in crossengine crossengine_rough reality; do
      python3 benchmarks/recall_by_incidence.py "${runs[@]}" --test "$test=$D/$test" \
        --out "$W/summary/recall_by_incidence_${test}_$arm.md" --device "$DEVICE" >> "$W/logs/recall.log" 2>&1 &
    done
  done
  wait
  python3 benchmarks/elevation_study_summary.py "$W" --out "$W/summary/elevation_study.md"
  ;;
pack)
  bash benchmarks/pack_study.sh "$W" "$1"
  ;;
*)
  echo "usage: $0 gen|tests|train|score|pack WORKDIR ..." >&2
  exit 2
  ;;
esac
