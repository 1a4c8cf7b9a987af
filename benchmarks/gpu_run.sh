#!/usr/bin/env bash
# The GPU benchmarks in one go, for a lent GPU machine whose Python already holds torch, numpy,
# OpenCV, scikit-image, scipy and tifffile (pycolmap and rawpy are not needed for these):
#   OUT=/some/folder bash benchmarks/gpu_run.sh [training minutes per model, default 2]
# Writes rendering_gpu.md and training_gpu.md to $OUT; copy them to benchmarks/results/.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="${1:-2}"
ours_flags="${2:-}"   # e.g. "--batch-rays 4096 --steps 100000"
out="${OUT:?set OUT to the folder for the results}"
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || true
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
[ -n "${SKIP_RENDERING:-}" ] || \
    python3 benchmarks/bench_rendering.py --throughput-only --out "$out/rendering_gpu.md"
python3 benchmarks/bench_training.py --device cuda --threads 8 --minutes "$minutes" \
    --work /tmp/bench_training --out "$out/training_gpu.md" --ours-flags="$ours_flags"
