#!/usr/bin/env bash
# The positive control across a suite of levels (issue 28): ppo, rnd, illm-shuffled, illm-noreward and
# illm with the oracle annotator (noise 0) on the spec's levels, each at the frames ppo needs there to
# leave 0 on some seeds (env_frames, from experiments/specs/suite-calibration.yaml's runs).
# 1. The toolkit's own workflow for the bulk arm: per level, `illm collect` 50,000 random-policy steps
#    and `illm annotate --backend oracle` every distinct state (history 0) into one shared cache,
#    $DATA/ann-bulk, which the bulk arm reads with no live budget (no write-back: it stays as annotated);
# 2. `illm experiment SPEC` (resumable; JOBS at a time);
# 3. `illm report` with the aggregate over levels, the diagnostics and the coverage each arm reached.
# Every step is resumable: collected levels and annotated states are skipped, finished runs too.
# Usage: bash experiments/suite.sh [SPEC] (default experiments/specs/suite-tune.yaml)
#        env: JOBS (2), DATA (data/exp-suite), OUT (results/<spec name>), REPORT (docs/results/<spec name>)
set -euo pipefail
cd "$(dirname "$0")/.."
SPEC=${1:-experiments/specs/suite-tune.yaml}
ILLM=${ILLM:-.venv/bin/illm}
PY=${PY:-.venv/bin/python}
JOBS=${JOBS:-2}
DATA=${DATA:-data/exp-suite}
NAME=$("$PY" -c "import sys, yaml; print(yaml.safe_load(open(sys.argv[1]))['name'])" "$SPEC")
OUT=${OUT:-results/$NAME}
REPORT=${REPORT:-docs/results/$NAME}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false

for env in $("$PY" -c "import sys, yaml; print(' '.join(yaml.safe_load(open(sys.argv[1]))['envs']))" "$SPEC"); do
  traj="$DATA/traj/${env//\//-}"
  [ -f "$traj/.done" ] || { rm -rf "$traj"; "$ILLM" collect --env "$env" --steps 50000 --num-envs 16 --seed 1000 \
      --no-raw --out "$traj" >/dev/null && touch "$traj/.done"; }
  "$ILLM" annotate "$traj" --cache "$DATA/ann-bulk" --backend oracle --history 0 --tasks action,summary >/dev/null
  "$ILLM" data coverage "$traj" --cache "$DATA/ann-bulk" --backend oracle --history 0 | tail -n 2
done

"$ILLM" experiment "$SPEC" --jobs "$JOBS" --out "$OUT"
"$ILLM" report "$OUT" --every 16384 --final-points 2 --out "$REPORT" --overwrite
