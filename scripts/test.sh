#!/usr/bin/env bash
# Set up (cheap when already done) and run the default test suite (no `slow` tests). Extra args go to pytest
# (later options win: `-n 0` runs it in one process, `-n 4` on four workers).
# Two workers (pytest-xdist), each test file on one worker so its module fixtures are built once, and one torch
# thread per process: on 2 cores two tests run at once, where one process with two threads mostly waits on
# Python, process start-up and imports (docs/BENCHMARKS.md, "The test suite").
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
export OMP_NUM_THREADS=1
exec "${VENV:-.venv}/bin/python" -m pytest -m "not slow" -q -n 2 --dist loadfile "$@"
