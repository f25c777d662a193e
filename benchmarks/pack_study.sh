#!/usr/bin/env bash
# What comes back from the GPU machine of a study's WORKDIR: reports, summaries, logs, histories and
# each run's best.pt without its optimizer state (best_weights.pt), in parts of 15 MB under DEST
# (`cat DEST/study.tgz.part* | tar -xz` unpacks them).
#
#   bash benchmarks/pack_study.sh WORKDIR DEST
set -euo pipefail
W=$1 DEST=$2
for ckpt in "$W"/runs/seed*/*/best.pt; do
  python3 -c "import sys; from learn.checkpoint import strip_checkpoint; strip_checkpoint(*sys.argv[1:])" \
    "$ckpt" "${ckpt%.pt}_weights.pt"
done
mkdir -p "$DEST"
python3 benchmarks/provenance.py write "$DEST/provenance-pack.json" --device cpu  # the commit that packed them
tar -czf - -C "$W" --exclude=data --exclude=per_window.csv --exclude=last.pt --exclude=best.pt --exclude=tensorboard . |
  split -b 15M - "$DEST/study.tgz.part"
