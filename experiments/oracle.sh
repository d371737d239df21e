#!/usr/bin/env bash
# The positive control (issue 19): iLLM with an annotator that knows the game, the annotator-quality
# curve, and what an LLM of a given quality would buy.
# 1. `illm probe` of every annotator on both levels (history 0, 400 states of the BabyAI bot): the
#    oracle at noise 0, 0.5 and 1 (seconds), SmolLM2-135M and Gemma-3-270M (minutes each);
# 2. `illm experiment experiments/specs/oracle.yaml` (70 runs: ppo, rnd, illm with the oracle at three
#    noise levels, illm-noreward and illm-shuffled, 2 levels, 5 seeds; resumable, JOBS at a time);
# 3. `illm report` with the probes: curves, IQM [95% CI], and the quality curve.
# Every step is resumable: a probe file that exists is kept, finished runs are skipped.
# Usage: bash experiments/oracle.sh [OUT]   (default results/oracle; env: JOBS (2), REPORT (docs/results/oracle))
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-results/oracle}
ILLM=${ILLM:-.venv/bin/illm}
make -s gemma  # its probes load Gemma-3-270M (not part of make install)
JOBS=${JOBS:-2}
REPORT=${REPORT:-docs/results/oracle}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false
PROBES="$REPORT/probes"
mkdir -p "$PROBES"

for level in UnlockLocal GoToLocal; do
  env=BabyAI-$level-v0
  for noise in 0 0.5 1; do
    f="$PROBES/$level-oracle-noise$noise.json"
    [ -f "$f" ] || "$ILLM" probe --env "$env" --backend oracle --oracle-noise "$noise" --states 400 --out "$f" >/dev/null
  done
  for model in smollm2-135m gemma3-270m; do
    f="$PROBES/$level-$model.json"
    [ -f "$f" ] || "$ILLM" probe --env "$env" --model "$model" --states 400 --out "$f" >/dev/null
  done
done

"$ILLM" experiment experiments/specs/oracle.yaml --jobs "$JOBS" --out "$OUT"
"$ILLM" report "$OUT" --every 16384 --final-points 2 --out "$REPORT" --overwrite $(for f in "$PROBES"/*.json; do echo --probe "$f"; done)
