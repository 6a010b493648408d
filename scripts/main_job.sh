#!/usr/bin/env bash
# The README's main job on the embedded default, on a fresh Linux machine (2 CPU cores are enough):
#   1. set up .venv                        (scripts/setup.sh; cheap when already done)
#   2. generate the embedded-small dataset (python -m openfly_agent.toolchain generate; resumable)
#   3. train the tiny preset               (accelerate launch train.py; resumes an interrupted run)
#   4. evaluate it closed-loop on test_seen and test_unseen next to the random / stop / forward / oracle
#      baselines, print the table, and say where the plots are (python eval.py; resumable)
# Every step picks up where it stopped, so re-running the script after an interruption finishes the job.
# Knobs (environment): DATA, RUN (output folders), TRAIN_MINUTES / TRAIN_STEPS (training stops at the first),
# TRAIN_PROCS (training processes of one torch thread each, data parallel over gloo; 2 uses 2 cores ~1.5-2x
# faster than one 2-thread process, docs/BENCHMARKS.md "Training"; 1 = a single process),
# EVAL_EPISODES (per split, evenly spaced; 0 = all), EVAL_BATCH (lockstep width), THREADS (torch CPU threads
# in eval; 1 never thrashes on a shared machine). Budget on 2 idle cores: set-up ~1 min, data ~2-4 min,
# training TRAIN_MINUTES + ~1 min, evaluation ~4 min (docs/BENCHMARKS.md).
# One experiment = one command: TRAIN_CONFIG picks the training preset (e.g. an ablation of
# configs/train/ablations/), TRAIN_ARGS adds draccus overrides, RUN keeps its outputs apart:
#   RUN=outputs/exp/uniform TRAIN_CONFIG=configs/train/ablations/uniform_history.yaml bash scripts/main_job.sh
# SKIP_SETUP=1 uses an existing environment (VENV) as it is.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -n "${SKIP_SETUP:-}" ] || bash scripts/setup.sh
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
VENV=${VENV:-.venv}
PY="$VENV/bin/python"
DATA=${DATA:-outputs/datasets/embedded-small}
RUN=${RUN:-outputs/main_job}
TRAIN_CONFIG=${TRAIN_CONFIG:-configs/train/tiny.yaml}
TRAIN_ARGS=${TRAIN_ARGS:-}
TRAIN_MINUTES=${TRAIN_MINUTES:-9}
TRAIN_STEPS=${TRAIN_STEPS:-1500}
TRAIN_PROCS=${TRAIN_PROCS:-2}
EVAL_EPISODES=${EVAL_EPISODES:-50}
EVAL_BATCH=${EVAL_BATCH:-16}
THREADS=${THREADS:-1}
start=$(date +%s)
say() { echo "[main_job $(( $(date +%s) - start ))s] $*"; }

say "1/3 dataset: $DATA (configs/toolchain/embedded-small.yaml)"
"$PY" -m openfly_agent.toolchain generate --config configs/toolchain/embedded-small.yaml --output_dir="$DATA"

say "2/3 training $TRAIN_CONFIG into $RUN/train ($TRAIN_MINUTES min or $TRAIN_STEPS steps)"
fresh_eval=false
if [ -f "$RUN/train/.main_job_trained" ]; then
  say "already trained (delete $RUN/train to train again)"
else
  fresh_eval=true  # new weights: earlier evaluation results of the agent no longer apply
  resume=false
  [ -f "$RUN/train/checkpoints/last" ] && resume=true  # an interrupted run continues
  if [ "$TRAIN_PROCS" -gt 1 ]; then
    # the multi-process CPU launcher (configs/accelerate/cpu_2proc.yaml explains the accelerate quirk)
    launcher=(env OMP_NUM_THREADS=1 "$VENV/bin/accelerate" launch --config_file configs/accelerate/cpu_2proc.yaml
      --num_processes "$TRAIN_PROCS")
  else
    launcher=("$VENV/bin/accelerate" launch --cpu --num_processes 1 --num_machines 1 --mixed_precision no
      --dynamo_backend no)
  fi
  "${launcher[@]}" train.py --config_path "$TRAIN_CONFIG" --data.root="$DATA" --output_dir="$RUN/train" \
    --steps="$TRAIN_STEPS" --time_limit_minutes="$TRAIN_MINUTES" --validation.final_max_samples=512 \
    --resume="$resume" $TRAIN_ARGS
  touch "$RUN/train/.main_job_trained"
fi

say "3/3 closed-loop evaluation (test_seen, test_unseen; $EVAL_EPISODES episodes per split, 0 = all)"
episodes=()
[ "$EVAL_EPISODES" -gt 0 ] && episodes=(--max_episodes "$EVAL_EPISODES")
"$PY" eval.py --checkpoint "$RUN/train" --split test_seen test_unseen --sim embedded \
  --baselines random stop forward oracle --dataset_root "$DATA" --output_dir "$RUN/eval" \
  --batch_size "$EVAL_BATCH" --torch_threads "$THREADS" --overwrite="$fresh_eval" ${episodes[@]+"${episodes[@]}"}

say "done. Table: $RUN/eval/summary.md; per-scene tables: $RUN/eval/<policy>/results.md"
say "top-down plots (ground truth vs agent): $RUN/eval/agent/plots/<split>/*.png (baselines: $RUN/eval/<baseline>/plots/)"
