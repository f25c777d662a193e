#!/usr/bin/env bash
# The learner study behind the superseded results of benchmarks/results/learner_h100/README.md (their
# files are in the history, commit 54cfdaf): generate every suite, time both
# networks, train the paper network and ours side by side, run the Table 2 and sim-to-real
# studies, evaluate. About 10 minutes on one H100; usage: bash benchmarks/learner_study.sh [WORKDIR]
set -euo pipefail
W=${1:-study}; D=$W/data; L=$W/logs; mkdir -p $W/runs $L
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
python benchmarks/provenance.py write "$L/provenance.json" --device cuda
python benchmarks/bench_learn.py --device cuda --out $W/bench
gen() { python -m acoustic_sim generate --suite "$1" --out "$D/$1" --workers 8 --device cuda:0 --quiet "${@:2}"; }
gen paper
# --no-augment: these results predate augmentation as the default (sim2real study, part 4)
C=(--device cuda --quiet --max-val-windows 1000 --no-augment)
# The paper's recipe (MSE, Adam 1e-4, batch 12, early stopping on SSIM) against ours (MSE, lr 1e-3).
python -m learn train --data $D/paper --out $W/runs/paper_k5 --model paper --frames 5 --epochs 40 --patience 6 \
  --max-train-windows 3000 --max-minutes 10.6 "${C[@]}" > $L/paper_k5.log 2>&1 &
python -m learn train --data $D/paper --out $W/runs/unet_k5 --model polar_unet --frames 5 --epochs 40 --patience 6 \
  --lr 1e-3 --max-train-windows 6000 --max-minutes 6.3 "${C[@]}" > $L/unet_k5.log 2>&1 &
gen table2 --frames 1500
gen ablation --frames 4000
gen reality
python -m learn table2 --train $D/paper --test $D/table2 --out $W/runs/table2 --model polar_unet --epochs 20 \
  --patience 4 --lr 1e-3 --max-train-windows 3000 --max-minutes 0.6 "${C[@]}" > $L/table2.log 2>&1 &
python -m learn sim2real --ablation $D/ablation --reality $D/reality --out $W/runs/sim2real --model polar_unet \
  --frames 5 --epochs 20 --patience 4 --lr 1e-3 --max-train-windows 3000 --max-minutes 1.2 "${C[@]}" > $L/sim2real.log 2>&1 &
wait
for m in paper_k5 unet_k5; do
  python -m learn evaluate --checkpoint $W/runs/$m/best.pt --data $D/paper --out $W/runs/$m/eval --device cuda --overwrite
done
