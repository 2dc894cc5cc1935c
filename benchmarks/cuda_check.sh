#!/bin/sh
# Issue 30's device checks on one GPU, in about 5 minutes (docs/design/optimiser.md). Run from the
# repository root; results, without the maps and
# recordings, in ${OUT:-runs}/cuda-check.tar.gz. Each step has its own time limit and
# its log in the results, so one failing step still leaves the others' figures:
#   smoke       30 iterations of sample:sim2d-small on cuda (stops the script if it fails)
#   profile     benchmarks/iteration_profile.py on cuda: median iteration, sections, launches, syncs
#   neighbours  the nearest-neighbour search methods on cuda
#   sim2d       sample:sim2d from scratch on cuda (1,000 iterations), GPU utilisation sampled
#   small-*     sample:sim2d-small from scratch on cuda and on the cpu, same seed (ATEs should agree
#               within the seeds' spread)
#   scratch20   the 20 simulated 2D trajectories from scratch (strep) on cuda, 4 at a time
dest="${OUT:-runs}"
out="${TMPDIR:-/tmp}/cuda-check"
rm -rf "$out" && mkdir -p "$out" "$dest"
trap 'tar -czf "$dest/cuda-check.tar.gz" --exclude="*.ply" --exclude="*.rrd" --exclude="*.npz" --exclude="*.pt" -C "$out/.." cuda-check' EXIT
export PYTHONPATH=. PYTHONUNBUFFERED=1
step() {  # step NAME SECONDS COMMAND...: run with a limit, log to $out/NAME.log, time it
  name=$1 limit=$2
  shift 2
  t0=$(date +%s)
  timeout "$limit" "$@" >"$out/$name.log" 2>&1
  rc=$?
  echo "$name rc=$rc $(($(date +%s) - t0)) s" | tee -a "$out/steps.txt"
  tail -n 4 "$out/$name.log"
  return $rc
}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
python -c 'import torch; print("torch", torch.__version__, torch.version.cuda)' | tee -a "$out/gpu.txt"
step smoke 90 python -m strep_cli.main run sample:sim2d-small --start scratch --device cuda \
  --iterations 30 --out "$out/smoke" -q || exit 1
step profile 120 python benchmarks/iteration_profile.py --device cuda --iterations 100 --json "$out/iteration_profile.json"
step neighbours 60 python benchmarks/iteration_profile.py --neighbours --device cuda --json "$out/neighbours.json"
nvidia-smi --query-gpu=utilization.gpu --format=csv,noheader,nounits -lms 200 >"$out/sim2d-util.txt" &
smi=$!
step sim2d 120 python -m strep_cli.main run sample:sim2d --start scratch --device cuda --out "$out/sim2d-cuda" -q
kill $smi
for device in cuda cpu; do
  step "small-$device" 120 python -m strep_cli.main run sample:sim2d-small --start scratch --device "$device" \
    --out "$out/sim2d-small-$device" -q
done
step scratch20 240 python benchmarks/from_scratch.py --suites sim2d --methods strep --jobs 4 --out "$out/scratch20"
