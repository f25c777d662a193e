#!/usr/bin/env bash
# `calibrate --scattering energy` on another engine's rooms: crossengine (smooth walls: s = 0) and
# crossengine_rough (rough walls: s drawn in [0.1, 0.4]), rooms 0 and 1 of seed 0 (the same rooms,
# drives and noise in both), each fitted on its drive's first 20 frames (10 pings) as
# calibrate_sim2real.sh's FIT=energy does, then tabled beside the engine's own values. CPU, ~15 min.
#
#   bash benchmarks/calibrate_energy.sh WORKDIR    # results under $RESULTS (benchmarks/results/calibrate_energy)
set -euo pipefail
W=${1:?usage: $0 WORKDIR}
R=${RESULTS:-benchmarks/results/calibrate_energy}
DEVICE=${DEVICE:-cpu}
mkdir -p "$W" "$R"
python benchmarks/provenance.py write "$R/provenance.json" --device "$DEVICE"
: >"$R/printed.txt"
for suite in crossengine crossengine_rough; do
  python -m acoustic_sim generate --suite "$suite" --frames 200 --signals --seed 0 --device "$DEVICE" --quiet \
    --out "$W/$suite"
  for room in 0 1; do
    # told what calibrate_sim2real.sh tells: the floor plan, 343 m/s (19.63 C), air that absorbs nothing, the
    # direct sound's 3 ms, and an omnidirectional emitter (the engine's)
    python -m acoustic_sim calibrate "$W/$suite" --episode "$room" --scene-from-data --frames 0:20 --pings 10 \
      --skip-ms 3 --no-air-absorption --set sonar.atmosphere.temperature_c=19.6335 --set sonar.emitter_pattern=omni \
      --scattering energy --device "$DEVICE" --overwrite --out "$R/${suite}_room$room.json" | tee -a "$R/printed.txt"
  done
done
python benchmarks/calibrate_energy.py "$W" "$R"
