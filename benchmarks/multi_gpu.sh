#!/usr/bin/env bash
# Scaling out on the GPUs of one host (a lent nvidia-h200-x2 or larger). Results under $RESULTS
# (default benchmarks/results/multi_gpu), working files under WORKDIR:
#
#   bash benchmarks/multi_gpu.sh gen   WORKDIR  # bench_generate: one GPU vs all (frames/s); one GPU's shards = all GPUs'
#   bash benchmarks/multi_gpu.sh load  WORKDIR  # generate_load: one GPU vs all with CPU and GPU use, two commands
#                                               # at once, blocking waits, py-spy (LOAD_FRAMES: sizes to run,
#                                               # LOAD_SETTINGS, LOAD_SPY=0)
#   bash benchmarks/multi_gpu.sh timeline WORKDIR  # worker_timeline: one run on one GPU and one on all, per worker
#   bash benchmarks/multi_gpu.sh start WORKDIR  # start_costs: a worker's start step by step, 1..12 processes at once
#   bash benchmarks/multi_gpu.sh ray   WORKDIR  # a local Ray cluster (ray start --head) writes one process's shards
#   bash benchmarks/multi_gpu.sh ddp   WORKDIR  # bench_learn --ddp: windows/s on 1..N GPUs, efficiency
#   bash benchmarks/multi_gpu.sh train WORKDIR  # one GPU at the network's batch B (16; paper 12) vs N GPUs at B/N each,
#                                               # seeds 0 and 1 (after gen; TRAIN_MODEL polar_unet or paper,
#                                               # TRAIN_WINDOWS a sub-epoch's, EPOCHS; TRAIN_RUNS "one ddp0 ddp1",
#                                               # a part of them per call: a lent machine's call lasts 10 minutes
#                                               # and ends what it started in the background)
#   bash benchmarks/multi_gpu.sh all   WORKDIR  # the four above in that order
#   bash benchmarks/multi_gpu.sh check WORKDIR  # on ONE GPU: --workers 2 --device auto gives the same shards,
#                                               # torchrun's NCCL path at world size 1 trains as the plain run
#
# Environment: BENCH_FRAMES (75000, per timed run), GEN_WORKERS (5 and 5 per GPU), FRAMES (12500, the
# dataset compared and trained on), RAY_FRAMES (12500), RAY_TASKS_PER_GPU (1 5 1: each a run, the last
# on warm Ray workers), EPOCHS (8 sub-epochs of 12,000 windows), RAY_SITE (a folder holding Ray).
# NVLink multicast stays off.
set -euo pipefail
phase=$1 W=$2
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
R=${RESULTS:-benchmarks/results/multi_gpu}
GPUS=$(python -c "import torch; print(torch.cuda.device_count())")
mkdir -p "$W" "$R"
stamp() { # the phase's start in the log, and its commit, machine and versions beside the results
  echo "== $1 $(date +%T)"
  python benchmarks/provenance.py write "$R/provenance-$1.json" --device cuda
}

gen() {
  stamp gen
  # 4-5 workers a GPU are the best since helper processes (session 26). A run carries ~1-2 s of fixed cost
  # (worker start, first episode, last shards), which 37,500 frames did not amortise on two GPUs: 75,000.
  python benchmarks/bench_generate.py --device cuda:0,auto --suite "${SUITE:-paper}" --frames "${BENCH_FRAMES:-75000}" \
    --workers "${GEN_WORKERS:-5,$((5 * GPUS))}" --modes overlapped --repeats 3 --out "$R"
  GEN=(--suite "${SUITE:-paper}" --frames "${FRAMES:-12500}" --seed 0 --quiet)
  python -m acoustic_sim generate "${GEN[@]}" --workers 8 --device cuda:0 --out "$W/one_gpu" | tee "$R/generate_one_gpu.txt"
  # the identity check needs every GPU busy with several workers, not the fastest count
  python -m acoustic_sim generate "${GEN[@]}" --workers $((8 * GPUS)) --device auto --out "$W/all_gpus" |
    tee "$R/generate_${GPUS}_gpus.txt"
  python benchmarks/same_shards.py "$W/one_gpu" "$W/all_gpus" | tee "$R/generate_identical.txt"
}

load() {
  stamp load
  # where the second GPU's frames go: the host's CPU, each GPU's use, two commands at once (pair), py-spy
  # where it is installed; at the bench's size and at four times it (a fixed start-up weighs less there)
  # (LOAD_SETTINGS: generate_load's settings; LOAD_SPY=0: no py-spy run)
  local spy=$(command -v py-spy >/dev/null && [ "${LOAD_SPY:-1}" = 1 ] && echo "--spy auto/$((5 * GPUS))" || true)
  for frames in ${LOAD_FRAMES:-75000 300000}; do
    python benchmarks/generate_load.py --suite "${SUITE:-paper}" --frames "$frames" --rounds 2 $spy \
      --settings "${LOAD_SETTINGS:-cuda:0/5,auto/$((5 * GPUS)),auto/$((5 * GPUS))/block,pair/5}" --out "$R/generate_load_$frames"
    spy=""
  done
}

timeline() {
  stamp timeline
  # where each run's time goes, worker by worker (start-up, first episode, steady episodes, last write)
  local frames=${BENCH_FRAMES:-25000} suite=${SUITE:-paper}
  python benchmarks/worker_timeline.py --suite "$suite" --frames "$frames" --workers 5 --device cuda:0 \
    --out "$R/timeline_one_gpu"
  python benchmarks/worker_timeline.py --suite "$suite" --frames "$frames" --workers $((5 * GPUS)) --device auto \
    --out "$R/timeline_${GPUS}_gpus"
}

start_costs() {
  stamp start
  # which step of a worker's start is served one process at a time (it grew ~0.15 s a process on two H200s)
  python benchmarks/start_costs.py --device auto --processes "${START_PROCESSES:-1,2,4,6,8,12}" --out "$R/start_costs"
}

ray_cluster() {
  stamp ray
  export RAY_AUTH_MODE=token # as `ray start` has by default since Ray 2.59; the caller must match
  export PYTHONPATH=${RAY_SITE:+$RAY_SITE:}${PYTHONPATH:-} # Ray installed apart, where it is
  GEN=(--suite paper --frames "${RAY_FRAMES:-12500}" --seed 0 --quiet)
  # the kernel cache filled first (a fresh machine compiles them), so no run below pays for it
  python -m acoustic_sim generate --suite paper --frames 500 --workers 2 --device auto --out "$W/ray_warm" --quiet >/dev/null
  # local workers on every GPU: the shards Ray's must equal, and the rate beside Ray's in the same job
  python -m acoustic_sim generate "${GEN[@]}" --device auto --workers $((5 * GPUS)) --out "$W/ray_reference" |
    tee "$R/generate_ray.txt"
  python -c "import ray; print('ray', ray.__version__)"
  # With the mode set, `ray start` refuses to run without a token (it makes one only when the mode is
  # left to its default), as the first x2 lease found: make one (kept in ~/.ray/auth_token) first.
  python -m ray.scripts.scripts get-auth-token --generate >/dev/null
  python -m ray.scripts.scripts start --head --port 6379 --num-gpus "$GPUS" --disable-usage-stats >"$W/ray_start.log" 2>&1
  trap 'python -m ray.scripts.scripts stop >/dev/null 2>&1 || true' EXIT # also when a step fails
  local run=0
  for n in ${RAY_TASKS_PER_GPU:-1 5 1}; do # one shard task per GPU, or n sharing each
    run=$((run + 1))
    echo "-- Ray, $n task(s) per GPU (run $run)" | tee -a "$R/generate_ray.txt"
    python -m acoustic_sim generate "${GEN[@]}" --device auto --ray-address 127.0.0.1:6379 --ray-tasks-per-gpu "$n" \
      --out "$W/ray_$run" | tee -a "$R/generate_ray.txt"
    python benchmarks/same_shards.py "$W/ray_reference" "$W/ray_$run" | tee -a "$R/generate_ray.txt"
  done
}

ddp() {
  stamp ddp
  python benchmarks/bench_learn.py --device cuda --ddp --batch 16 --repeats 20 --out "$R"
}

train() {
  stamp train
  [ -f "$W/one_gpu/manifest.json" ] || { echo "train needs the gen phase's $W/one_gpu" >&2; exit 2; }
  # one validation set for every run (--split-seed), so that the seed-to-seed spread is training noise
  local model=${TRAIN_MODEL:-polar_unet}
  # each network's own recipe: ours BCE, Adam 1e-3, batch 16; the paper's MSE, Adam 1e-4, batch 12 (at 1e-3 and 16
  # it learnt no wall in 8,000 windows, session 31), whose first 24,000 windows reach scan F1 ~0.7
  local loss=bce lr=1e-3 batch=16 windows=12000
  [ "$model" = paper ] && loss=mse lr=1e-4 batch=12 windows=6000
  OPTS=(--data "$W/one_gpu" --model "$model" --loss "$loss" --lr "$lr" --epochs "${EPOCHS:-8}" --patience 100 --split-seed 0
    --max-train-windows "${TRAIN_WINDOWS:-$windows}" --max-val-windows 2000 --device cuda --quiet --overwrite)
  ((GPUS >= 1 && batch % GPUS == 0)) || { echo "train needs a GPU count that divides the global batch $batch, got $GPUS" >&2; exit 2; }
  local todo=" ${TRAIN_RUNS:-one ddp0 ddp1} "
  pids=() failed=0
  if [[ $todo == *" one "* ]]; then
    for seed in 0 1; do # one process on one GPU each, side by side
      CUDA_VISIBLE_DEVICES=$((seed % GPUS)) python -m learn train "${OPTS[@]}" --seed $seed --batch-size $batch \
        --out "$W/runs/${model}_one_gpu_seed$seed" >"$R/train_${model}_one_gpu_seed$seed.log" 2>&1 &
      pids+=($!)
    done
    for pid in "${pids[@]}"; do wait "$pid" || failed=1; done # both finish before a failure stops the phase
    ((failed == 0)) || { echo "a one-GPU run failed: $R/train_${model}_one_gpu_seed*.log" >&2; exit 1; }
  fi
  for seed in 0 1; do
    [[ $todo == *" ddp$seed "* ]] || continue
    torchrun --standalone --nproc_per_node "$GPUS" -m learn train "${OPTS[@]}" --seed $seed \
      --batch-size $((batch / GPUS)) --out "$W/runs/${model}_${GPUS}_gpus_seed$seed" >"$R/train_${model}_${GPUS}_gpus_seed$seed.log" 2>&1
  done
  for run in "$W"/runs/"$model"_*; do # each finished run's own record, beside the comparison once all are in
    if [ -f "$run/history.csv" ]; then mkdir -p "$R/runs/${run##*/}" && cp "$run"/{config.json,history.csv,curves.png} "$R/runs/${run##*/}/"; fi
  done
  local runs=("$W/runs/${model}_one_gpu_seed"{0,1} "$W/runs/${model}_${GPUS}_gpus_seed"{0,1})
  for run in "${runs[@]}"; do [ -f "$run/summary.json" ] || { echo "not compared yet: $run has not finished"; return 0; }; done
  python benchmarks/same_global_batch.py "${runs[@]}" --out "$R/same_global_batch_$model"
}

check() {
  stamp check
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
}

case $phase in
gen) gen ;;
load) load ;;
timeline) timeline ;;
start) start_costs ;;
ray) ray_cluster ;;
ddp) ddp ;;
train) train ;;
all) # each phase in its own shell: one that fails is reported and the next still runs
  for p in gen ray ddp train; do bash "$0" "$p" "$W" || echo "== phase $p failed (exit $?)"; done
  echo "== done $(date +%T)"
  ;;
check) check ;;
*)
  echo "usage: $0 gen|load|timeline|start|ray|ddp|train|all|check WORKDIR" >&2
  exit 2
  ;;
esac
