#!/usr/bin/env bash
# One command for a GPU machine: the parallel-in-time Kalman tests and benchmark on the GPU.
#
#   benchmarks/parallel_kalman_gpu.sh [--quick]      (from the repository root or anywhere)
#
# It installs the package with the cuda12 extra into .venv-gpu (unless PYTHON names an
# interpreter that already has it, e.g. a virtual environment built beforehand for a
# machine without network), checks that JAX sees a GPU, runs tests/test_parallel_kalman.py
# there, then benchmarks/parallel_kalman.py, which writes
# benchmarks/results/parallel_kalman[_quick]_gpu.json and rebuilds the Markdown table with
# the CPU numbers already committed beside it.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${PYTHON:-}" ]]; then
    if [[ ! -x .venv-gpu/bin/python ]]; then
        python3 -m venv .venv-gpu
        .venv-gpu/bin/python -m pip install -q --upgrade pip
        .venv-gpu/bin/python -m pip install -q -e ".[cuda12,test]"
    fi
    PYTHON=.venv-gpu/bin/python
fi
PYTHONPATH=src "$PYTHON" - <<'PY'
import jax
backend = jax.default_backend()
if backend not in ("gpu", "cuda"):
    raise SystemExit(f"JAX runs on {backend!r}, not a GPU: install jax[cuda12] on a machine with a CUDA GPU")
print("JAX", jax.__version__, "on", jax.devices())
PY
PYTHONPATH=src "$PYTHON" -m pytest -q tests/test_parallel_kalman.py
PYTHONPATH=src "$PYTHON" benchmarks/parallel_kalman.py "$@"
