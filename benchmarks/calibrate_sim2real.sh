#!/usr/bin/env bash
# Does calibrating to the user's rooms help sim-to-real (issue 44)? `crossengine` stands in for the
# user's rooms: 10 drives of 100 frames, each in its own room. Each room is calibrated on its drive's
# first CAL_FRAMES frames (20: two seconds), and the models are scored only on windows that start
# after them. Two arms, the same scenes, drives, seeds and recipe; only the physics differs:
#   randomised  `randomised`'s bounces_3 variant, as the study trained on;
#   calibrated  the same, with walls, floor and ceiling R and s spanning the ten rooms' fits (+-5 %),
#               the emitter's directivity fitted (nearest piston), the microphones' mean fitted
#               gains and delays, and the fits' air (calibrate_sim2real.py suite writes the suite).
# Everything the fits do not give (objects, SNR, air temperature, microphone mismatch, emitter
# offset, drives) stays randomised as in `randomised`. The recipe is the study's with `learn train`'s
# default augmentation (its part 4 "aug" arm): polar UNet, K = 5, BCE, Adam 1e-3, batch 16, sub-epochs
# of 12,000 windows, 2,000 validation windows, early stopping on validation scan F1 with patience 4.
#
#   bash benchmarks/calibrate_sim2real.sh fit   WORKDIR           # the recordings and the fits (CPU: ~25 min), then
#   python benchmarks/calibrate_sim2real.py suite FITS --recordings WORKDIR/data/CROSS_signals --out SUITE
#                                                                 # (FITS: WORKDIR/fits, or a copy beside SUITE)
#   bash benchmarks/calibrate_sim2real.sh gen   WORKDIR SUITE     # both training sets, crossengine, reality
#   bash benchmarks/calibrate_sim2real.sh train WORKDIR SEED...   # both arms of each seed, side by side
#   bash benchmarks/calibrate_sim2real.sh score WORKDIR SEED...   # both arms on the same windows, the summary
#   bash benchmarks/calibrate_sim2real.sh pack  WORKDIR DEST      # DEST/study.tgz.part* (cat | tar -xz)
#
# What a fit is told, as a user with a thermometer and the room's floor plan would be: the floor plan
# and height (--scene-from-data), the air's speed of sound (crossengine's engine uses 343.0 m/s: 19.63 C
# here) and that its air absorbs nothing (the engine leaves absorption out; --no-air-absorption), and
# to skip the first 3 ms of each recording (the omnidirectional emitter's direct sound, which lasts
# the 2.5 ms call). First each room's emitter directivity is fitted (knots every 15 degrees,
# specular), then R and s of each class with the emitter as the nearest piston to that fit. With
# FIT=energy the fits are told the emitter is omnidirectional instead (the engine's is) and fit s by
# the echo energy (`calibrate --scattering energy`: the rough walls' diffuse echoes share no phase
# with ours); the suite then simulates an omnidirectional emitter too.
#
# The GPU machine (a lent two-GPU kind; calls back to back, each under 10 minutes): the fits are made
# here first (`fit`, then `calibrate_sim2real.py suite`) and travel with the tree (the suite names
# them by relative paths); then
#   call 1: gen W SUITE (both arms at once, one per GPU), then MINUTES=6 train W 0 1 2
#   call 2: MINUTES=8 train W 0 1 2 (--resume goes on from each run's last epoch)
#   call 3: score W 0 1 2, pack W "$OUT"
# (two H200s, the rough arm: gen 195 s, then MINUTES=5 per call; a run the call's end kills shows as
# "cut off" in the summary until a later train call takes it to its early stop)
# A process left running in the background does not outlive its call.
#
# CROSS=crossengine_rough runs the same study on the rough-wall variant (its fits find each room's s);
# give it its own WORKDIR.
#
# Environment: CROSS (crossengine), FIT (directivity; energy: an omni emitter, s by echo energy),
# FRAMES (50000 per arm), CAL_FRAMES (20), CAL_PINGS (10), KNOTS (6),
# DEVICE (cuda; cpu for a dry run), GPUS (runs spread over cuda:0..GPUS-1; default: all), WORKERS (8 per
# generation), CROSS_FRAMES (1000, as the study's), CROSS_WORKERS (12), REALITY_FRAMES (the suite's 1,500),
# MINUTES (per run and call, 8), EPOCHS (100), PATIENCE (4), SUBEPOCH (12000), VAL (2000).
set -euo pipefail
phase=$1 W=$2
shift 2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
D=$W/data
DEVICE=${DEVICE:-cuda}
CAL_FRAMES=${CAL_FRAMES:-20}
CROSS=${CROSS:-crossengine}
ARMS=(randomised calibrated)
mkdir -p "$W/logs" "$W/runs" "$W/scores" "$W/summary" "$W/fits"
python3 benchmarks/provenance.py write "$W/logs/provenance-$phase-$(date -u +%Y%m%dT%H%M%SZ).json" --device "$DEVICE"
gpus=${GPUS:-$(python3 -c "import torch; print(max(1, torch.cuda.device_count()))")}

case $phase in
fit)
  rec=$D/${CROSS}_signals
  python3 -m acoustic_sim generate --suite "$CROSS" --frames 1000 --signals --seed 0 --out "$rec" \
    --workers "${CROSS_WORKERS:-2}" --device "${GEN_DEVICE:-cpu}" --quiet
  told=(--scene-from-data --frames "0:$CAL_FRAMES" --pings "${CAL_PINGS:-10}" --skip-ms 3 --no-air-absorption
    --set sonar.atmosphere.temperature_c=19.6335 --device "${GEN_DEVICE:-cpu}" --overwrite)
  if [[ ${FIT:-directivity} == energy ]]; then
    # told also that the engine's source is omnidirectional (it is); s by the echo energy, which another
    # engine's diffuse echoes keep where their phases are not ours
    for room in 0 1 2 3 4 5 6 7 8 9; do
      python3 -m acoustic_sim calibrate "$rec" --episode "$room" "${told[@]}" --scattering energy \
        --set sonar.emitter_pattern=omni --out "$W/fits/surfaces/room$room.json" >> "$W/logs/fit.log" 2>&1
    done
    exit 0
  fi
  for room in 0 1 2 3 4 5 6 7 8 9; do
    python3 -m acoustic_sim calibrate "$rec" --episode "$room" "${told[@]}" --directivity-knots "${KNOTS:-6}" \
      --set tracer.scattering=false --out "$W/fits/directivity/room$room.json" >> "$W/logs/fit.log" 2>&1
    radius=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['directivity']['piston_radius_mm'] / 1e3)" \
      "$W/fits/directivity/room$room.json")
    python3 -m acoustic_sim calibrate "$rec" --episode "$room" "${told[@]}" --scattering \
      --set "sonar.emitter_radius_m=$radius" --out "$W/fits/surfaces/room$room.json" >> "$W/logs/fit.log" 2>&1
  done
  ;;
gen)
  suite=$1
  first=cuda:0 second=cuda:$((1 % gpus))
  [[ $DEVICE == cpu ]] && first=cpu second=cpu # a dry run
  GEN=(--variants bounces_3 --frames "${FRAMES:-50000}" --workers "${WORKERS:-8}" --seed 0 --quiet)
  python3 -m acoustic_sim generate --suite randomised --out "$D/randomised" "${GEN[@]}" --device "$first" &
  python3 -m acoustic_sim generate --suite "$suite" --out "$D/calibrated" "${GEN[@]}" --device "$second" &
  wait
  python3 -m acoustic_sim generate --suite "$CROSS" --frames "${CROSS_FRAMES:-1000}" --out "$D/$CROSS" \
    --workers "${CROSS_WORKERS:-12}" --device "$first" --seed 0 --quiet &
  python3 -m acoustic_sim generate --suite reality ${REALITY_FRAMES:+--frames "$REALITY_FRAMES"} --out "$D/reality" \
    --workers "${WORKERS:-8}" --device "$second" --seed 0 --quiet
  wait
  ;;
train)
  n=0
  for s in "$@"; do
    for arm in "${ARMS[@]}"; do
      dev=$DEVICE
      [[ $DEVICE == cuda ]] && dev=cuda:$(((n + s) % gpus)) # each GPU trains both arms: no arm gets the faster card
      n=$((n + 1))
      graphs=$([[ $dev == cuda* ]] && echo --cuda-graphs || true)
      run=(python3 -m learn train --data "$D/$arm/bounces_3" --out "$W/runs/seed$s/$arm" --model polar_unet --frames 5
        --seed "$s" --loss bce --lr 1e-3 --batch-size 16 --epochs "${EPOCHS:-100}" --patience "${PATIENCE:-4}"
        --max-train-windows "${SUBEPOCH:-12000}" --max-val-windows "${VAL:-2000}" --max-minutes "${MINUTES:-8}"
        --resume --device "$dev" --quiet)
      # CUDA graphs where they compile; a run they fail for starts again eagerly (same seed, same draws)
      ("${run[@]}" $graphs || "${run[@]}") >> "$W/logs/seed${s}_$arm.log" 2>&1 &
    done
  done
  wait
  ;;
score)
  k=0
  next_device() { # the GPUs in turn (each validation set is 50,000 frames on the card: spread them)
    dev=$DEVICE
    [[ $DEVICE == cuda ]] && dev=cuda:$((k % gpus))
    k=$((k + 1))
  }
  for s in "$@"; do
    ckpts=()
    for arm in "${ARMS[@]}"; do ckpts+=(--checkpoint "$arm=$W/runs/seed$s/$arm/best.pt"); done
    # the rooms past their calibration frames: no window holds a ping a fit saw
    next_device
    python3 -m learn evaluate "${ckpts[@]}" --data "$D/$CROSS" --split all --from-frame "$CAL_FRAMES" \
      --out "$W/scores/seed$s/$CROSS" --device "$dev" --quiet --overwrite >> "$W/logs/score_seed$s.log" 2>&1 &
    next_device
    python3 -m learn evaluate "${ckpts[@]}" --data "$D/reality" --split all --out "$W/scores/seed$s/reality" \
      --device "$dev" --quiet --overwrite >> "$W/logs/score_seed$s.log" 2>&1 &
    for arm in "${ARMS[@]}"; do # each arm on its own validation episodes
      next_device
      python3 -m learn evaluate --checkpoint "$W/runs/seed$s/$arm/best.pt" --data "$D/$arm/bounces_3" --split val \
        --no-grids --out "$W/scores/seed$s/validation_$arm" --device "$dev" --quiet --overwrite \
        >> "$W/logs/score_seed$s.log" 2>&1 &
    done
  done
  wait
  python3 benchmarks/calibrate_sim2real.py summary "$W" --test "$CROSS" --out "$W/summary"
  ;;
pack)
  bash benchmarks/pack_study.sh "$W" "$1"
  ;;
*)
  echo "usage: $0 fit|gen|train|score|pack WORKDIR ..." >&2
  exit 2
  ;;
esac
