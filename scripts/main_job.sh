#!/usr/bin/env bash
# The main job on the embedded default: set up, generate data, train the tiny preset, evaluate, print the table.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
PY="${VENV:-.venv}/bin/python"
"$PY" -m pytest -q tests/test_layering.py
