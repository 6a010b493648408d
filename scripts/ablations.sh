#!/usr/bin/env bash
# The ablation table at the recipe budget (docs/experiments/2026-11-26-ablations-on-the-adopted-recipe.md, "The ablation table on the adopted recipe"):
#   1. the recipe itself (configs/recipe/tiny-recipe.yaml: keyframes + token merging, the paper's OpenFly-Agent)
#      into $ROOT/recipe, about 3 h 31 min on the 2-core host of 2026-11-30 (about 2 h 25 min on the
#      faster 2 cores its steps were set on);
#   2. each arm of configs/recipe/ablations/ into $ROOT/<arm>, one change against the recipe. The arms that change
#      only the navigation stage share the recipe's grounding stage (--grounding_from; about 1 h 23 min each),
#      `with_dagger` also starts from the recipe's navigation stage (copied in, so its rounds are the one change),
#      and the two arms without a grounding stage train their navigation stage from random weights;
#   3. the table of every finished run (bench/ablation_table.py) into $ROOT/table.md and $ROOT/table.json, each arm
#      with its agent's paired SR difference from the recipe's on the same episodes (the reference arm, first row).
# All arms: about 10 hours on 2 idle cores (run nothing else meanwhile: the stages are time budgets). Every recipe
# resumes where it stopped, so re-running the script after an interruption finishes the table.
# Knobs (environment): ROOT (default outputs/ablations), ARMS (a subset, e.g. "current_frame no_grounding_loss"),
# VENV (default .venv, set up by scripts/setup.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_child.sh  # stopping the script stops the running stage
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
VENV=${VENV:-.venv}
ROOT=${ROOT:-outputs/ablations}
ARMS=${ARMS:-"current_frame uniform_history uniform_history_merging no_grounding_pretraining no_grounding_loss with_dagger"}
SHARE_GROUNDING="current_frame uniform_history uniform_history_merging with_dagger"
recipe() { child "$VENV/bin/python" -m openfly_agent.recipe "$@"; }
for arm in $ARMS; do  # every arm named exists, before hours of training
  [ -f "configs/recipe/ablations/$arm.yaml" ] || { echo "ablations.sh: no arm $arm (configs/recipe/ablations/$arm.yaml is missing)" >&2; exit 2; }
done

recipe --config_path configs/recipe/tiny-recipe.yaml --output_dir "$ROOT/recipe"
rows=(--run "keyframes_merging=$ROOT/recipe")
for arm in $ARMS; do
  # the agent next to random only: the other baselines do not depend on the arm (the recipe's table has them)
  args=(--config_path "configs/recipe/ablations/$arm.yaml" --output_dir "$ROOT/$arm" "--eval.baselines=[random]")
  case " $SHARE_GROUNDING " in
    *" $arm "*) args+=(--grounding_from "$ROOT/recipe/grounding") ;;
  esac
  if [ "$arm" = with_dagger ] && [ ! -d "$ROOT/$arm/navigation" ]; then
    mkdir -p "$ROOT/$arm"
    cp -r "$ROOT/recipe/navigation" "$ROOT/$arm/navigation"  # with its completion marker: the rounds start from it
  fi
  recipe "${args[@]}"
  rows+=(--run "$arm=$ROOT/$arm")
done
"$VENV/bin/python" bench/ablation_table.py "${rows[@]}" --json "$ROOT/table.json" | tee "$ROOT/table.md"
