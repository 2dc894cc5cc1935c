#!/bin/sh
# Issue 30's device checks on one GPU, in under 5 minutes (docs/design/optimiser.md):
# the iteration profile on cpu and cuda, then sample:sim2d from scratch on cuda (1,000 iterations)
# and sample:sim2d-small from scratch on cuda and on the cpu, same seed (their ATEs should agree
# within the seeds' spread). Run from the repository root; results under ${OUT:-runs/cuda-check}.
set -e
out="${OUT:-runs/cuda-check}"
mkdir -p "$out"
export PYTHONPATH=.
python benchmarks/iteration_profile.py --device cpu cuda --iterations 100 --json "$out/iteration_profile.json"
python benchmarks/iteration_profile.py --neighbours --device cuda --json "$out/neighbours.json"
python -m strep_cli.main run sample:sim2d --start scratch --device cuda --out "$out/sim2d-cuda" -q
for device in cuda cpu; do
  python -m strep_cli.main run sample:sim2d-small --start scratch --device "$device" --out "$out/sim2d-small-$device" -q
done
