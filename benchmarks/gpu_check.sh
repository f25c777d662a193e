#!/usr/bin/env bash
# What the GPU machine says about one commit: the physics tests on the GPU and the benchmarks, every
# result beside the provenance of the tree that made it (commit, clean or not, device, driver), so a
# figure and a test run always name the code they measured.
#
#   bash benchmarks/gpu_check.sh OUTDIR tests        # the simulation tests with --device cuda:0 (~1 min)
#   bash benchmarks/gpu_check.sh OUTDIR sonar        # bench_sonar at 20k and 100k rays, bench_elevation
#   bash benchmarks/gpu_check.sh OUTDIR lidar        # bench_lidar beside the bare kernel, bench_stream
#   bash benchmarks/gpu_check.sh OUTDIR generate     # bench_generate, paper suite, 4 and 5 workers (the best
#                                                    # counts on 16 cores) beside Sonar.simulate alone
#   bash benchmarks/gpu_check.sh OUTDIR all          # all four (about 9 minutes on an H100: split it
#                                                    # over calls where a call is limited to 10)
#
# On the lent machine: install Warp as ../shared/device/README.md says, `python benchmarks/provenance.py
# source` here before the call and carry .provenance.json (the machine has no git), and give the
# reference office as OFFICE_85K. Results land in OUTDIR/<phase>/ with provenance-<phase>.json;
# OUTDIR/tests/pytest_cuda.txt holds the test run. A phase that fails says so and the others still run;
# the script's status is the first failure's.
set -uo pipefail
OUT=$1
shift
phases=("$@")
[[ ${#phases[@]} -eq 0 || ${phases[0]} == all ]] && phases=(tests sonar lidar generate)
DEVICE=${DEVICE:-cuda:0}
export PYTHONUNBUFFERED=1
# The tests whose kernels run on the --device (the rest of the suite is CPU-only or device-free).
GPU_TESTS=(tests/test_curved_echoes.py tests/test_smooth_mesh.py tests/test_paths.py tests/test_beamform.py
  tests/test_beamform_kernels.py tests/test_record.py tests/test_lidar.py tests/test_pose_checks.py
  tests/test_chirp.py tests/test_crossengine.py tests/test_image_sources_high_order.py tests/test_calibrate.py)
# Always on the CPU, whose kernels the lent machine's Warp build cannot compile: not a GPU result.
CPU_ONLY=(--deselect tests/test_lidar.py::test_cpu_threads_split_the_poses_without_changing_a_range)
status=0

run_phase() {
  local phase=$1 dir=$OUT/$1
  mkdir -p "$dir"
  python3 benchmarks/provenance.py write "$dir/provenance-$phase.json" --device "$DEVICE" > /dev/null
  case $phase in
  tests)
    python3 -m pytest -q --device "$DEVICE" "${GPU_TESTS[@]}" "${CPU_ONLY[@]}" -rs -p no:cacheprovider 2>&1 |
      tee "$dir/pytest_cuda.txt" | tail -5
    ;;
  sonar)
    python3 benchmarks/bench_sonar.py --device "$DEVICE" --out "$dir" &&
      python3 benchmarks/bench_sonar.py --device "$DEVICE" --rays 100000 --out "$dir" &&
      python3 benchmarks/bench_elevation.py --device "$DEVICE" --out "$dir"
    ;;
  lidar)
    bare=()
    [[ -f $HOME/bench/bare_warp_bench.py ]] && bare=(--bare "$HOME/bench/bare_warp_bench.py")
    python3 benchmarks/bench_lidar.py --device "$DEVICE" "${bare[@]}" --out "$dir" &&
      python3 benchmarks/bench_stream.py --device "${DEVICE%%:*}" --out "$dir"
    ;;
  generate)
    python3 benchmarks/bench_generate.py --device "$DEVICE" --suite paper --frames 12500 --workers 4,5 --sonar-alone \
      --modes overlapped --out "$dir"
    ;;
  *)
    echo "unknown phase $phase: tests, sonar, lidar, generate or all" >&2
    return 2
    ;;
  esac
}

for phase in "${phases[@]}"; do
  echo "== $phase"
  run_phase "$phase"
  rc=$?
  if [[ $rc -ne 0 ]]; then
    echo "== $phase failed (status $rc)"
    [[ $status -eq 0 ]] && status=$rc
  fi
done
exit $status
