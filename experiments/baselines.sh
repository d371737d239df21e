#!/usr/bin/env bash
# The exploration baselines against iLLM on one BabyAI Go To level with distractors (the paper's
# Table 1 layout, N = 8: BabyAI-GoToLocal-v0's default), at a budget a 2-core CPU affords:
# ppo, rnd, ngu, apt, ellm, chibit, illm and illm-shuffled (iLLM with each state's targets taken
# from another cached state: the control that tells the LLM's knowledge from curiosity).
# - history 0, the embedded SmolLM2-135M (bf16); a random collection of 30,000 steps and a
#   frequency-first bulk annotation (action, summary and ELLM's goal task, ANNOTATE_MINUTES at
#   most) into one cache the LLM methods share, async live annotation beside each run;
# - every method through the same trainer, budget (FRAMES) and seeds; one run at a time.
# Every step is resumable: finished work is skipped, an unfinished run resumes.
# Usage: bash experiments/baselines.sh [OUT]   (default data/exp-baselines)
#   env: FRAMES (30000), SEEDS ("0 1 2"), METHODS (all eight), ANNOTATE_MINUTES (10),
#        CACHE (OUT/ann: an existing cache of the same setup may be given), ENV (BabyAI-GoToLocal-v0)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/exp-baselines}
ILLM=${ILLM:-.venv/bin/illm}
FRAMES=${FRAMES:-30000}
SEEDS=${SEEDS:-"0 1 2"}
METHODS=${METHODS:-"ppo rnd ngu apt ellm chibit illm illm-shuffled"}
ANNOTATE_MINUTES=${ANNOTATE_MINUTES:-10}
CACHE=${CACHE:-$OUT/ann}
ENV=${ENV:-BabyAI-GoToLocal-v0}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false
mkdir -p "$OUT/runs" "$OUT/logs"

needs_cache() { case $1 in illm|illm-shuffled|ellm) return 0 ;; *) return 1 ;; esac; }
tasks=""
for method in $METHODS; do
  case $method in illm|illm-shuffled) tasks="$tasks action summary" ;; ellm) tasks="$tasks goal" ;; esac
done
tasks=$(echo $tasks | tr ' ' '\n' | sort -u | paste -sd, -)
if [ -n "$tasks" ]; then
  traj="$OUT/traj"
  [ -d "$traj" ] || "$ILLM" collect --env "$ENV" --steps 30000 --num-envs 16 --seed 1000000 --out "$traj"
  "$ILLM" annotate "$traj" --cache "$CACHE" --history 0 --tasks "$tasks" --max-minutes "$ANNOTATE_MINUTES" \
      > "$OUT/logs/annotate.log"
  cat "$OUT/logs/annotate.log"
fi

for seed in $SEEDS; do
  for method in $METHODS; do
    run="$OUT/runs/$method-s$seed"
    if [ -f "$run/done" ]; then continue; fi
    [ -f "$run/checkpoint.pt" ] && resume=--resume || resume=
    args=(--method "$method")
    if needs_cache "$method"; then args+=(--cache "$CACHE" --history 0 --live-mode async); fi
    start=$(date +%s)
    "$ILLM" train --env "$ENV" "${args[@]}" --frames "$FRAMES" --seed "$seed" --out "$run" $resume \
        2> "$run.err" | tee "$run.log"
    echo "$(( $(date +%s) - start ))" > "$run/done"
  done
done

echo "== $ENV, $FRAMES frames (wall-clock seconds per run:"
for run in "$OUT"/runs/*-s*/; do echo "  $(basename "$run") $(cat "$run/done" 2>/dev/null || echo '-')"; done
echo ")"
"$ILLM" report "$OUT"/runs/*-s*/ --every 10000
"$ILLM" eval "$OUT"/runs/*-s*/ --episodes 100
