#!/usr/bin/env bash
# Check a machine with one CUDA GPU and no network, in about 8.5 minutes on an H200 (bench/gpu_check.py says what
# runs): the 7B chain at full size, the full fine-tune's first FSDP step, the benches; one table at the end.
#   bash scripts/gpu_check.sh                      # results and logs in outputs/gpu_check
#   python bench/gpu_check.py --plan               # the commands it would run (options: bench/gpu_check.py)
#   bash scripts/gpu_check.sh --suite levers       # the time split and each speed lever alone (about 5.5 min on an H200)
# Without CUDA it exits at once with one line (exit 2). PYTHON picks the interpreter (default: .venv's, else
# python3 on PATH, e.g. a CUDA PyTorch image's with the wheels the table lists).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${PYTHON:-}" ]]; then
  if [[ -x .venv/bin/python ]]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
exec "$PYTHON" bench/gpu_check.py "$@"
