#!/usr/bin/env bash
# Issue 39's study: does memory with odometry read walls a single window cannot? The protocol of
# sim2real_study.sh (randomised suite, 3 secondary bounces, FRAMES frames, seeds 0-2, early stopping
# on validation scan F1, each run's return threshold calibrated on its own validation windows only),
# with the augmentation and row contrast the sim-to-real study chose (aug_contrast), in four arms:
#
#   k5         polar UNet, K = 5, no memory (today's best)
#   memory     polar_memory, K = 5 and HISTORY frames every STRIDE frames before, true odometry
#   drift1     polar_memory trained on odometry with 1 % drift (augment.odometry_drift=0.01)
#   drift5     polar_memory trained on odometry with 5 % drift
#
# Scored by `learn evaluate` (the four side by side, with the echo peak, the empty image and the two
# occupancy grids, fed by echo peaks and by k5) on the held-out episodes of the training data, on
# `reality`, on `crossengine` (another engine; never trained, stopped or calibrated on) and on a
# fresh drive (the paper suite, seed 1000), each with true odometry and with 1 % and 5 % drift
# (models with memory and the grids read the drifting poses). Then memory_study_summary.py.
#
#   bash benchmarks/memory_study.sh gen   WORKDIR                # the training data
#   bash benchmarks/memory_study.sh tests WORKDIR                # the test sets (while training runs)
#   bash benchmarks/memory_study.sh train WORKDIR SEED...      # every arm of each seed, side by side
#   bash benchmarks/memory_study.sh score WORKDIR SEED...
#   bash benchmarks/memory_study.sh pack  WORKDIR DEST          # DEST/study.tgz.part* (cat | tar -xz)
#
# Environment: FRAMES (50000), REALITY_FRAMES (the suite's 1,500), CROSS_FRAMES (1000), FRESH_FRAMES
# (1000), DEVICE (cuda; several GPUs: GPUS=2 spreads the runs over cuda:0..), GEN_DEVICE (cuda:0),
# WORKERS (8), MINUTES (per run, 20), EPOCHS (100), PATIENCE (4), HISTORY (8), STRIDE (3), ARMS
# (k5,memory,drift1,drift5), DRIFTS (0,0.01,0.05), SUBEPOCH (12000), VAL (2000).
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
DEVICE=${DEVICE:-cuda}
ARMS=${ARMS:-k5,memory,drift1,drift5}
mkdir -p "$W/logs" "$W/runs" "$W/scores" "$W/summary"
python benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device "$DEVICE"

arm_options() { # the options that make an arm
  local memory="--model polar_memory --history ${HISTORY:-8} --history-stride ${STRIDE:-3}"
  case $1 in
  k5) echo "--model polar_unet" ;;
  memory) echo "$memory" ;;
  drift1) echo "$memory --set augment.odometry_drift=0.01" ;;
  drift5) echo "$memory --set augment.odometry_drift=0.05" ;;
  *)
    echo "unknown arm $1" >&2
    exit 2
    ;;
  esac
}

case $phase in
gen)
  python -m acoustic_sim generate --suite randomised --variants bounces_3 --frames "${FRAMES:-50000}" --out "$D/randomised" \
    --workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet
  ;;
tests)
  GEN=(--workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet)
  python -m acoustic_sim generate --suite reality ${REALITY_FRAMES:+--frames "$REALITY_FRAMES"} --out "$D/reality" "${GEN[@]}"
  python -m acoustic_sim generate --suite crossengine --frames "${CROSS_FRAMES:-1000}" --out "$D/crossengine" \
    --workers "${CROSS_WORKERS:-10}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet
  python -m acoustic_sim generate --suite paper --frames "${FRESH_FRAMES:-1000}" --out "$D/fresh" \
    --workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --seed 1000 --quiet
  ;;
train)
  graphs=$([[ $DEVICE == cuda* ]] && echo --cuda-graphs || true)
  n=0
  for s in "$@"; do
    for arm in ${ARMS//,/ }; do
      dev=$DEVICE
      [[ -n ${GPUS:-} ]] && dev=cuda:$((n % GPUS))
      n=$((n + 1))
      run=(python -m learn train --data "$D/randomised/bounces_3" --out "$W/runs/seed$s/$arm" $(arm_options "$arm")
        --frames 5 --set model.row_contrast=true --seed "$s" --loss bce --lr 1e-3 --batch-size 16
        --epochs "${EPOCHS:-100}" --patience "${PATIENCE:-4}" --max-train-windows "${SUBEPOCH:-12000}"
        --max-val-windows "${VAL:-2000}" --max-minutes "${MINUTES:-20}" --resume --device "$dev" --quiet)
      # CUDA graphs where they compile; a run they fail for starts again eagerly (same seed, same draws)
      ("${run[@]}" $graphs || "${run[@]}") >> "$W/logs/seed${s}_$arm.log" 2>&1 &
    done
  done
  wait
  ;;
score)
  # every report its own process: the grids run on the CPU cores, the models on the GPU
  for s in "$@"; do
    ckpts=()
    for arm in ${ARMS//,/ }; do ckpts+=(--checkpoint "$arm=$W/runs/seed$s/$arm/best.pt"); done
    for test in validation reality crossengine fresh; do
      data=$D/$test drifts=${DRIFTS:-0 0.01 0.05}
      [[ $test == validation ]] && data=$D/randomised/bounces_3 drifts=0 # its held-out episodes
      for drift in $drifts; do
        python -m learn evaluate "${ckpts[@]}" --data "$data" --out "$W/scores/seed$s/$test/drift$drift" \
          --odometry-drift "$drift" --device "$DEVICE" --quiet --overwrite >> "$W/logs/score_seed${s}_$test.log" 2>&1 &
      done
    done
  done
  memory=() k5=()
  for s in "$@"; do memory+=("$W/runs/seed$s/memory") k5+=("$W/runs/seed$s/k5"); done
  for test in reality crossengine; do
    python benchmarks/memory_horizon.py "${memory[@]}" --test "$test=$D/$test" --out "$W/summary/horizon_$test.md" \
      --device "$DEVICE" >> "$W/logs/horizon.log" 2>&1 &
  done
  for arm in k5 memory; do
    if [[ $arm == memory ]]; then runs=("${memory[@]}"); else runs=("${k5[@]}"); fi
    python benchmarks/recall_by_incidence.py "${runs[@]}" --test "crossengine=$D/crossengine" \
      --out "$W/summary/recall_by_incidence_$arm.md" --device "$DEVICE" >> "$W/logs/recall.log" 2>&1 &
  done
  for test in crossengine reality fresh; do
    python benchmarks/drive_from_above.py --checkpoint "k5=${k5[0]}/best.pt" --checkpoint "memory=${memory[0]}/best.pt" \
      --data "$D/$test" --out "$W/summary/drive_$test.png" --device "$DEVICE" >> "$W/logs/drive.log" 2>&1 &
  done
  wait
  python benchmarks/memory_study_summary.py "$W" --out "$W/summary/memory_study.md"
  ;;
pack)
  bash benchmarks/pack_study.sh "$W" "$1"
  ;;
*)
  echo "usage: $0 gen|train|score|pack WORKDIR ..." >&2
  exit 2
  ;;
esac
