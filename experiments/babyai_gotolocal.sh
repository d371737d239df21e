#!/usr/bin/env bash
# Success-rate curves of ppo, illm-noreward and illm on BabyAI-GoToLocal-v0, 3 seeds, at a
# budget a 2-core CPU machine affords (about 30 minutes with 2 runs side by side, one thread each):
# - targets from the embedded SmolLM2-135M (bf16) with the shared-layout prompts;
# - history 0 (current observation only) so that states repeat and the shared cache pays off;
# - a cache pre-filled from 1,000 random steps, then at most 4 live annotations per rollout,
#   written back to the same cache that all six illm runs share;
# - 60k frames per run (16 envs x 128 steps per rollout).
# Usage: bash experiments/babyai_gotolocal.sh [OUT]   (default data/exp-gotolocal)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/exp-gotolocal}
ILLM=${ILLM:-.venv/bin/illm}
ENV=BabyAI-GoToLocal-v0
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false
mkdir -p "$OUT/runs"

"$ILLM" collect --env $ENV --steps 1000 --num-envs 8 --seed 100 --out "$OUT/traj" --overwrite
"$ILLM" annotate "$OUT/traj" --cache "$OUT/ann" --history 0

for seed in 0 1 2; do
  for method in ppo illm-noreward illm; do
    echo "$method $seed"
  done
done | xargs -P 2 -L 1 bash -c '
  method=$0 seed=$1 run="'"$OUT"'/runs/$method-s$seed"
  [ -f "$run/checkpoint.pt" ] && resume=--resume || resume=
  "'"$ILLM"'" train --env '"$ENV"' --method $method --cache "'"$OUT"'/ann" --history 0 --live-budget 4 \
      --llm-threads 1 --frames 60000 --seed $seed --out "$run" $resume > "$run.log" 2>&1
  echo "done $run"'

"$ILLM" report "$OUT"/runs/* --every 20000
