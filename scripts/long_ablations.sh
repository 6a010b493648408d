#!/usr/bin/env bash
# The paper's memory ablation on the long-route benchmark (configs/recipe/long-recipe.yaml, data_cards/embedded-long.md):
#   1. keyframes + token merging (configs/recipe/long-ablations/keyframes_merging.yaml, the full OpenFly-Agent) into
#      $ROOT/keyframes_merging, with the grounding stage the other arms share (24 min measured) and the benchmark
#      generated first when missing;
#   2. the other five arms of configs/recipe/long-ablations/ into $ROOT/<arm>, each from that grounding stage
#      (--grounding_from), with the same navigation steps (5,000) and training seed: current frame only, uniform
#      history, random earlier frames, keyframes without merging, uniform history + merging;
#   3. the table of every finished arm (bench/ablation_table.py) into $ROOT/table.md and $ROOT/table.json, each arm
#      with its agent's paired SR difference from keyframes + merging on the same episodes (the first row), and,
#      when current_frame is among the arms, the same table against current frame only (the paper's OpenVLA
#      baseline) into $ROOT/table-vs-current-frame.md and .json.
# Measured for the first arm on the reference 2-core machine: 24 min grounding, then per arm 35 min navigation and
# 9 min evaluation, about 5 hours for the six; run nothing else meanwhile. Every recipe resumes where it stopped,
# so re-running the script after an interruption finishes the table.
# Knobs (environment): ROOT (default outputs/long-ablations), ARMS (a subset of the five, e.g. "current_frame
# keyframes"), VENV (default .venv, set up by scripts/setup.sh), RECIPE_ARGS (more recipe overrides given to every
# arm, e.g. "--grounding.minutes=300 --navigation.minutes=300" so that a loaded machine cannot stop a stage early).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_child.sh  # stopping the script stops the running stage
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
VENV=${VENV:-.venv}
ROOT=${ROOT:-outputs/long-ablations}
ARMS=${ARMS:-"current_frame uniform_history random_keyframes keyframes uniform_history_merging"}
RECIPE_ARGS=${RECIPE_ARGS:-}
CONFIGS=configs/recipe/long-ablations
# shellcheck disable=SC2086  # RECIPE_ARGS is a list of overrides
recipe() { child "$VENV/bin/python" -m openfly_agent.recipe "$@" $RECIPE_ARGS; }
for arm in $ARMS; do  # every arm named exists, before hours of training
  [ -f "$CONFIGS/$arm.yaml" ] || { echo "long_ablations.sh: no arm $arm ($CONFIGS/$arm.yaml is missing)" >&2; exit 2; }
done

mkdir -p "$ROOT"
recipe --config_path "$CONFIGS/keyframes_merging.yaml" --output_dir "$ROOT/keyframes_merging"
runs=("keyframes_merging=$ROOT/keyframes_merging")  # NAME=FOLDER of each arm, the reference first
for arm in $ARMS; do
  # the agent next to random only: the other baselines do not depend on the arm (the first arm's table has them)
  recipe --config_path "$CONFIGS/$arm.yaml" --output_dir "$ROOT/$arm" "--eval.baselines=[random]" \
    --grounding_from "$ROOT/keyframes_merging/grounding"
  runs+=("$arm=$ROOT/$arm")
done
table() {  # table OUT NAME=FOLDER...: $ROOT/OUT.md and .json, each run paired with the first
  local out=$1 args=() run
  shift
  for run in "$@"; do args+=(--run "$run"); done
  "$VENV/bin/python" bench/ablation_table.py "${args[@]}" --json "$ROOT/$out.json" | tee "$ROOT/$out.md"
}
table table "${runs[@]}"
if [[ " $ARMS " == *" current_frame "* ]]; then  # the same rows against current frame only (the paper's OpenVLA)
  others=()
  for run in "${runs[@]}"; do [[ "$run" == current_frame=* ]] || others+=("$run"); done
  table table-vs-current-frame "current_frame=$ROOT/current_frame" "${others[@]}"
fi
