#!/usr/bin/env bash
# The training issue's device benchmarks in one run, CPU against CUDA on the same machine: robot-shaped
# segmentation throughput (bench_robot.py throughput), training seconds per step (bench_robot.py
# train) and time to quality (bench_training_budget.py). They need playseg_core, torch, numpy and tqdm
# only, so a GPU machine's own Python runs them from a checkout:
#
#     PY=python3 bash benchmarks/gpu_check.sh        # prints the figures; ~6 minutes on an H100
#
# Every figure names its device; CPU ones use the machine's cores as --threads says.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
export PYTHONPATH="$PWD:$PWD/benchmarks${PYTHONPATH:+:$PYTHONPATH}"
THREADS=${THREADS:-2}
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available() and torch.cuda.get_device_name(0))"
for device in cpu cuda; do
    echo "== segmentation throughput, 96x96 camera + 7-D state/actions, L_max 100 ($device)"
    $PY benchmarks/bench_robot.py throughput --device "$device" --threads 1 --skip-reference
    echo "== PS training, 400 robot-shaped segments, 1 epoch ($device)"
    $PY benchmarks/bench_robot.py train --segments 400 --device "$device" --threads "$THREADS"
done
echo "== time to quality, default budget (cuda)"
$PY benchmarks/bench_training_budget.py --budget default --device cuda --threads "$THREADS"
