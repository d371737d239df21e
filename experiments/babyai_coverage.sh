#!/usr/bin/env bash
# ppo against illm on BabyAI-GoToLocal-v0 and BabyAI-UnlockLocal-v0 (sparse reward: find the key,
# open the door), 3 seeds, at a budget a 2-core CPU machine affords, with targets on most steps:
# - history 0 (the current observation), the embedded SmolLM2-135M (bf16), shared-layout prompts;
# - per level, 50,000 random-policy steps, then a frequency-first bulk annotation (the most
#   visited states first, at most ANNOTATE_MINUTES minutes) into one cache every run shares;
# - async live annotation (a worker process on the second core) of the states runs miss;
# - illm with the paper's bonus weights, with CleanRL RND's advantage weights (--bonus-preset rnd),
#   and with smaller bonus weights (illm-small: lambda 0.1, beta 0.05).
# Runs one at a time so that each run's wall-clock time is its own. Every step is resumable: a
# finished collection, annotation or run is skipped, an unfinished run resumes.
# Usage: bash experiments/babyai_coverage.sh [OUT]   (default data/exp-coverage)
#   env: ANNOTATE_MINUTES (20), SEEDS ("0 1 2"), METHODS ("ppo illm illm-rnd illm-small"),
#        LEVELS ("GoToLocal UnlockLocal")
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/exp-coverage}
ILLM=${ILLM:-.venv/bin/illm}
ANNOTATE_MINUTES=${ANNOTATE_MINUTES:-20}
SEEDS=${SEEDS:-"0 1 2"}
METHODS=${METHODS:-"ppo illm illm-rnd illm-small"}
LEVELS=${LEVELS:-"GoToLocal UnlockLocal"}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false
mkdir -p "$OUT/runs" "$OUT/logs"

frames() { case $1 in GoToLocal) echo 100000 ;; UnlockLocal) echo 150000 ;; esac; }

for level in $LEVELS; do
  env=BabyAI-$level-v0 traj="$OUT/traj-${level,,}"
  [ -d "$traj" ] || "$ILLM" collect --env "$env" --steps 50000 --num-envs 16 --seed 100 --out "$traj"
  "$ILLM" annotate "$traj" --cache "$OUT/ann" --history 0 --max-minutes "$ANNOTATE_MINUTES" \
      > "$OUT/logs/annotate-$level.log"
  cat "$OUT/logs/annotate-$level.log"
  "$ILLM" data coverage "$traj" --cache "$OUT/ann" --history 0 | tee "$OUT/logs/coverage-$level.txt"
  for seed in $SEEDS; do
    for method in $METHODS; do
      run="$OUT/runs/$level-$method-s$seed"
      if [ -f "$run/done" ]; then continue; fi
      [ -f "$run/checkpoint.pt" ] && resume=--resume || resume=
      case $method in
        ppo) args=(--method ppo) ;;
        illm) args=(--method illm --cache "$OUT/ann" --history 0 --live-mode async --bonus-preset paper) ;;
        illm-rnd) args=(--method illm --cache "$OUT/ann" --history 0 --live-mode async --bonus-preset rnd) ;;
        illm-small) args=(--method illm --cache "$OUT/ann" --history 0 --live-mode async --lambda-a 0.1 --beta-hc 0.05) ;;
      esac
      start=$(date +%s)
      "$ILLM" train --env "$env" "${args[@]}" --frames "$(frames "$level")" --seed "$seed" --out "$run" $resume \
          2> "$run.err" | tee "$run.log"
      echo "$(( $(date +%s) - start ))" > "$run/done"
    done
  done
done

for level in $LEVELS; do
  echo "== $level (wall-clock seconds per run: $(cat "$OUT"/runs/$level-*/done | tr '\n' ' '))"
  "$ILLM" report "$OUT"/runs/$level-* --every 25000
  for run in "$OUT"/runs/$level-*-s*; do
    [ -d "$run" ] && echo "$(basename "$run"): eval $("$ILLM" eval "$run" --episodes 100 --json \
        | python3 -c 'import json,sys; print(json.load(sys.stdin)[0]["success_rate"])')"
  done
done
