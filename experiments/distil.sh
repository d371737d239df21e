#!/usr/bin/env bash
# Issue 29: the student annotator the docs report, rebuilt by one command (its weights are not in git).
# 1. collect BabyAI UnlockLocal and GoToLocal trajectories: minigrid's expert bot with 25% random actions
#    (episode seeds from 1,000,000 up) and a uniformly random policy (from 2,000,000 up): no episode is one
#    `illm probe` plays (its seeds run from 0);
# 2. annotate every distinct state with the oracle (history 0, tasks action and summary): the teacher;
# 3. `illm distil` SmolLM2-135M on that cache (LoRA rank 16 in the top 15 blocks, merged) into OUT;
# 4. `illm probe` the student and its base on UnlockLocal and GoToLocal (the bot's states of episodes the
#    student was not trained on) and on PickupLoc (a level none of its training states came from).
# Every step is resumable: a dataset or probe file that exists is kept, annotation does what is missing, the
# distillation resumes from its last checkpoint and does nothing once the student is there.
# Usage: bash experiments/distil.sh [OUT]   (default models/smollm2-135m-babyai)
# Environment (defaults: the full-size run, about 30 minutes of fine-tuning on 2 AVX2 cores in float32):
#   DATA (data/distil), BOT_STEPS (12000 per level), RANDOM_STEPS (1000 per level), STATES (1600 lessons; all:
#   every state not held out), HELD_OUT (200), EPOCHS (1), BATCH_SIZE (8 states a step), MAX_TOKENS (256), RANK (16),
#   LAYERS (15: adapters in the top 15 of 30 blocks),
#   BLOCKS (empty: every block; N: the student keeps N of its base's 30 blocks, evenly spaced, LAYERS then
#   defaulting to N),
#   LR (1e-3), LESSONS (visits: drawn as often as the collected trajectories visit their states, the top actions'
#   shares of the visits evened by BALANCE; balance: each distinct state once, the rare actions' states repeated
#   toward equal shares by BALANCE; see `illm distil --help`), BALANCE (visits 0, balance 0.75), MIN_SHARE (0: each
#   top action at least this share of the lessons, the others keeping their proportions), SEED (0: the adapters'
#   initialisation and the lessons' order), TARGET (the
#   ranking's: distribution, or argmax: the teacher's top action only), DTYPE (float32),
#   DEVICE (cpu: where the fine-tuning and the probes run; cuda on a GPU), PROBE_STATES (400), PROBES (probe files:
#   OUT/probes), BASE_PROBES (1: probe the base model too).
# The GPU student the docs report (an H100, 5.5 minutes of training): DEVICE=cuda STATES=all BATCH_SIZE=32
#   TARGET=argmax LESSONS=balance BALANCE=0.5 LAYERS=30 bash experiments/distil.sh   (into models/smollm2-135m-babyai)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-models/smollm2-135m-babyai}
ILLM=${ILLM:-.venv/bin/illm}
DATA=${DATA:-data/distil}
BOT_STEPS=${BOT_STEPS:-12000}
RANDOM_STEPS=${RANDOM_STEPS:-1000}
STATES=${STATES:-1600}
HELD_OUT=${HELD_OUT:-200}
EPOCHS=${EPOCHS:-1}
BATCH_SIZE=${BATCH_SIZE:-8}
MAX_TOKENS=${MAX_TOKENS:-256}
RANK=${RANK:-16}
BLOCKS=${BLOCKS:-}
LAYERS=${LAYERS:-${BLOCKS:-15}}
LR=${LR:-1e-3}
LESSONS=${LESSONS:-visits}
BALANCE=${BALANCE:-$([ "$LESSONS" = balance ] && echo 0.75 || echo 0)}
MIN_SHARE=${MIN_SHARE:-0}
SEED=${SEED:-0}
TARGET=${TARGET:-distribution}
DTYPE=${DTYPE:-float32}
PROBE_STATES=${PROBE_STATES:-400}
PROBES=${PROBES:-$OUT/probes}
BASE_PROBES=${BASE_PROBES:-1}
DEVICE=${DEVICE:-cpu}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false

for level in UnlockLocal GoToLocal; do
  for policy in bot random; do
    steps=$BOT_STEPS seed=1000000; [ "$policy" = random ] && steps=$RANDOM_STEPS seed=2000000
    traj="$DATA/traj-$level-$policy"
    [ -f "$traj/state.json" ] || "$ILLM" collect --env "BabyAI-$level-v0" --policy "$policy" --steps "$steps" \
        --num-envs 8 --seed "$seed" --out "$traj"
    "$ILLM" annotate "$traj" --cache "$DATA/ann-oracle" --backend oracle --history 0 --tasks action,summary
  done
done
"$ILLM" cache info "$DATA/ann-oracle"

cut=(); [ -n "$BLOCKS" ] && cut=(--blocks "$BLOCKS")
lessons=(--states "$STATES"); [ "$STATES" = all ] && lessons=()
weighting=(--balance "$BALANCE" --min-share "$MIN_SHARE")  # LESSONS=balance: the rare actions' states repeated
[ "$LESSONS" = visits ] && weighting+=($(for d in "$DATA"/traj-*; do echo --visits "$d"; done))
time "$ILLM" distil "$DATA/ann-oracle" --student smollm2-135m --out "$OUT" "${lessons[@]}" --held-out "$HELD_OUT" \
    --epochs "$EPOCHS" --batch-size "$BATCH_SIZE" --max-tokens "$MAX_TOKENS" --rank "$RANK" --layers "$LAYERS" "${cut[@]}" "${weighting[@]}" --learning-rate "$LR" --ranking-target "$TARGET" --seed "$SEED" --dtype "$DTYPE" --device "$DEVICE"

mkdir -p "$PROBES"
models=("$OUT")
[ "$BASE_PROBES" = 1 ] && models+=(smollm2-135m)
for level in UnlockLocal GoToLocal PickupLoc; do
  for model in "${models[@]}"; do
    name=$( [ "$model" = "$OUT" ] && echo student || echo "$model" )
    f="$PROBES/$level-$name.json"
    [ -f "$f" ] || "$ILLM" probe --env "BabyAI-$level-v0" --model "$model" --dtype float32 --device "$DEVICE" --states "$PROBE_STATES" \
        --out "$f"
    "${PYTHON:-.venv/bin/python}" -c "import json,sys; d=json.load(open(sys.argv[1])); c=d['calibrations']['sum']; \
print(f\"{sys.argv[2]:>12s} {sys.argv[3]:<14s} agreement {c['agreement']:.3f} (always {d['baselines']['majority_action']}: \
{d['baselines']['majority_agreement']:.3f}, chance {d['baselines']['chance_agreement']:.3f})\")" "$f" "$level" "$name"
  done
done
