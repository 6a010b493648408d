#!/usr/bin/env bash
# The README's main job on the embedded default, on a fresh Linux machine (2 CPU cores are enough):
#   1. set up .venv (scripts/setup.sh; cheap when already done)
#   2. the navigation recipe at the main job's budget (configs/recipe/main_job.yaml; openfly_agent/recipe):
#      embedded-small dataset -> referring-expression dataset -> grounding stage -> navigation stage (no DAgger
#      round at this budget) -> closed-loop evaluation on the full test_seen and test_unseen splits next to the
#      random / stop / forward / oracle / box_servo baselines, and the table; the same on the test_unseen split
#      of four more unseen cities (configs/toolchain/embedded-small-unseen-more.yaml)
#   Each training stage runs a fixed number of steps (grounding 1,400, navigation 3,036), so the result does not
#   depend on the machine; the stages' minutes are a guard only, and a stage it stopped is named in the table's
#   header ("navigation: 1,682 of 3,036 steps ...: this machine is slower than the reference; expect lower SR").
# Every stage picks up where it stopped, so re-running the script after an interruption finishes the job; stopping
# the script (Ctrl-C, kill PID) stops the running stage, which saves its checkpoint first (scripts/_child.sh).
# Knobs (environment): RUN (output folder, default outputs/main_job), RECIPE_CONFIG (e.g.
# configs/recipe/tiny-recipe.yaml or an ablation of configs/recipe/ablations/), RECIPE_ARGS (more recipe
# overrides, e.g. "--eval.max_episodes=50"), SKIP_SETUP=1 (use the environment VENV as it is).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_child.sh
[ -n "${SKIP_SETUP:-}" ] || bash scripts/setup.sh
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
VENV=${VENV:-.venv}
RUN=${RUN:-outputs/main_job}
RECIPE_CONFIG=${RECIPE_CONFIG:-configs/recipe/main_job.yaml}
RECIPE_ARGS=${RECIPE_ARGS:-}
start=$(date +%s)
# shellcheck disable=SC2086  # RECIPE_ARGS is a list of overrides
child "$VENV/bin/python" -m openfly_agent.recipe --config_path "$RECIPE_CONFIG" --output_dir "$RUN" $RECIPE_ARGS
echo "[main_job $(( $(date +%s) - start ))s] done. Table: $RUN/summary.md; per-scene tables: $RUN/eval/<policy>/results.md"
for table in "$RUN"/eval-*/summary.md; do
  if [ -f "$table" ]; then echo "more unseen cities (recipe eval.more_cities): $table"; fi
done
echo "top-down plots (ground truth vs agent): $RUN/eval/agent/plots/<split>/*.png (baselines: $RUN/eval/<baseline>/plots/)"
