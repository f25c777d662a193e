#!/usr/bin/env bash
# The multipath sim-to-real study on one GPU: our polar UNet trained on `ablation` (the paper's
# scenarios) and on `randomised` (randomised physics, empty polygon rooms as well), each rendered
# with 0, 1 and 3 secondary bounces (FRAMES per variant, 50,000 by default), seeds 0-2, until
# validation scan F1 (0.10 m) stops improving; then scored on validation episodes of its own
# variant, on `reality` and on `crossengine` (another engine's image sources, which no model
# trains, stops or calibrates on) beside the echo-peak baseline, with paired per-seed differences.
# Phases, so each fits one 10-minute call of the GPU machine; `train` resumes from last.pt:
#
#   bash benchmarks/sim2real_study.sh gen   WORKDIR ablation|randomised|tests
#   bash benchmarks/sim2real_study.sh train WORKDIR SUITE SEED...      # every variant of each seed, side by side
#   bash benchmarks/sim2real_study.sh score WORKDIR SUITE SEED...      # learn sim2real --score-only, then the summary
#   bash benchmarks/learner_converged.sh pack|unpack WORKDIR ...       # carry the runs to the next machine
#
# `tests` makes `reality` (its 1,500 frames) and 1,000 `crossengine` frames (needs pyroomacoustics;
# its image sources run on the CPU cores, our energyscape on GEN_DEVICE). The training recipe is the
# converged K = 5 one of learner_converged.sh (BCE, Adam 1e-3, batch 16, sub-epochs of 12,000
# windows, 2,000 validation windows, patience 4), its steps as CUDA graphs on a GPU (2.3x the eager
# rate of one polar UNet process on an H200; nine processes together trained ~2,300 windows/s
# there). Each training process holds its dataset on the GPU (~10 GB at 50,000 frames): nine fit a
# 139 GB H200, seven an 80 GB H100 (e.g. two seeds of one suite per call).
# Runs train on the windows as simulated (--no-augment), as the committed study did; TAG names a
# second study of the same suite (e.g. TAG=mirror with TRAIN_OPTS="--set augment.mirror=0.5", which
# come after and so win): its runs go to sim2real_SUITE_TAG_seedS.
# Environment: FRAMES (50000), MINUTES (budget per call and run, 8), DEVICE (cuda), GEN_DEVICE,
# WORKERS (generation processes, 8), REALITY_FRAMES (its suite's 1,500), CROSS_FRAMES (1000),
# CROSS_WORKERS (10), EPOCHS (100), PATIENCE (4), TRAIN_OPTS (more `learn train` options, e.g.
# --set augment.mirror=0.5), TAG, VARIANTS (to train and score, e.g. bounces_3; all three by default).
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
STUDY=${TAG:+_$TAG}
GRAPHS=$([[ ${DEVICE:-cuda} == cuda* ]] && echo --cuda-graphs || true)
VARIANTS=${VARIANTS:-bounces_0,bounces_1,bounces_3}
mkdir -p "$W/logs" "$W/runs"
# each call's commit, machine and versions, kept with the logs (learner_converged.sh pack carries them)
python benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device "${DEVICE:-cuda}"
case $phase in
gen)
  what=$1
  GEN=(--workers "${WORKERS:-8}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet)
  case $what in
  ablation | randomised)
    python -m acoustic_sim generate --suite "$what" --variants "$VARIANTS" --frames "${FRAMES:-50000}" \
      --out "$D/$what" "${GEN[@]}"
    ;;
  tests)
    python -m acoustic_sim generate --suite reality ${REALITY_FRAMES:+--frames "$REALITY_FRAMES"} --out "$D/reality" "${GEN[@]}"
    python -m acoustic_sim generate --suite crossengine --frames "${CROSS_FRAMES:-1000}" --out "$D/crossengine" \
      --workers "${CROSS_WORKERS:-10}" --device "${GEN_DEVICE:-cuda:0}" --seed 0 --quiet
    ;;
  *)
    echo "gen what? ablation, randomised or tests, got $what" >&2
    exit 2
    ;;
  esac
  ;;
train)
  suite=$1
  shift
  for s in "$@"; do
    for v in ${VARIANTS//,/ }; do
      python -m learn train --data "$D/$suite/$v" --out "$W/runs/sim2real_${suite}${STUDY}_seed$s/$v" --model polar_unet \
        --frames 5 --seed "$s" --loss bce --lr 1e-3 --batch-size 16 $GRAPHS --no-augment ${TRAIN_OPTS:-} --epochs "${EPOCHS:-100}" \
        --patience "${PATIENCE:-4}" --max-train-windows 12000 --max-val-windows 2000 --max-minutes "${MINUTES:-8}" \
        --resume --device "${DEVICE:-cuda}" --quiet >> "$W/logs/${suite}${STUDY}_${v}_seed$s.log" 2>&1 &
    done
  done
  wait
  ;;
score)
  suite=$1
  shift
  runs=()
  for s in "$@"; do
    run=$W/runs/sim2real_${suite}${STUDY}_seed$s
    python -m learn sim2real --ablation "$D/$suite" --reality "$D/reality" --test "crossengine=$D/crossengine" \
      --out "$run" --score-only --variants "$VARIANTS" --device "${DEVICE:-cuda}" --quiet >> "$W/logs/score_${suite}${STUDY}_seed$s.log" 2>&1
    runs+=("$run")
  done
  if [ ${#runs[@]} -ge 2 ]; then
    python -m learn sim2real-summary "${runs[@]}" --out "$W/runs/sim2real_${suite}${STUDY}_summary" --overwrite
  fi
  ;;
*)
  echo "usage: $0 gen|train|score WORKDIR ..." >&2
  exit 2
  ;;
esac
