#!/usr/bin/env bash
# The device check, for a machine with one NVIDIA GPU: one markdown table of the bridge on the GPU's EGL driver
# (frames/s at 704×1280, its G-buffer codes against Mesa llvmpipe's), a dynamics training step at the paper preset
# (tokens/s, MFU) and a `train wan` step at a reduced size (s/step, peak memory), in under 8 minutes.
# `--dry`: every part at tiny sizes on the CPU. Python: $PYTHON, else the repo's .venv/bin/python.
# Exit 1 when a part failed, 2 when this machine cannot run it (no CUDA build of torch, no GPU).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python="${PYTHON:-$root/.venv/bin/python}"
if ! command -v "$python" >/dev/null; then
    echo "benchmarks/device.sh: no Python at $python: make the venv (bash scripts/bootstrap.sh) or set \$PYTHON" >&2
    exit 2
fi
cd "$root"
PYTHONDONTWRITEBYTECODE=1 exec "$python" benchmarks/bench_device.py "$@"
