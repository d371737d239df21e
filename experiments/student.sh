#!/usr/bin/env bash
# The positive control through the language-model path (issue 29): UnlockLocal with the student annotator
# (experiments/distil.sh builds it: models/smollm2-135m-babyai) beside the oracle, its base model, ppo and
# the shuffled control (experiments/specs/student.yaml).
# 1. `illm collect` 50,000 random-policy UnlockLocal steps (episode seeds from 4,000,000) and 12,000 of the
#    bot's (seeds from 3,000,000; none of them episodes the student was taught), and `illm annotate` every
#    distinct state into one shared cache with each annotator: the student, the oracle and the base model
#    (float32, history 0, action and summary). At history 0 the two hold 4,543 and 4,159 distinct states
#    (`illm data coverage`); on a 2-core CPU the student annotates about 1.5 states/s and the base 1.0, so
#    this step is hours there (interrupt it at will: `illm annotate` keeps every finished chunk and skips
#    what the cache holds) and minutes on a GPU (DEVICE=cuda BATCH_SIZE=256: the base model's 7,463 states
#    in 68 s on an H200);
# 2. `illm experiment` (resumable; JOBS at a time, each run with its own live worker; the base model's
#    runs last);
# 3. `illm probe` the three annotators on UnlockLocal, and
#    `illm report` with the probes: curves, IQM [95% CI] and the quality curve.
# Every step is resumable: collected data and annotated states are kept, finished runs are skipped.
# Usage: bash experiments/student.sh [OUT]   (default results/student; env: JOBS (1), DATA (data/exp-student),
#        ILLM_MODELS (models: the folder holding smollm2-135m-babyai), REPORT (docs/results/student),
#        BASE (1: the base model's bulk annotation and runs; 0: every other run first, the base's later),
#        DEVICE (cpu: where the bulk annotation runs), BATCH_SIZE (8: states per LLM batch in the bulk
#        annotation; 256 on a GPU))
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-results/student}
ILLM=${ILLM:-.venv/bin/illm}
JOBS=${JOBS:-1}
DEVICE=${DEVICE:-cpu}
BATCH_SIZE=${BATCH_SIZE:-8}
DATA=${DATA:-data/exp-student}
export ILLM_MODELS=${ILLM_MODELS:-models}
STUDENT=$ILLM_MODELS/smollm2-135m-babyai
REPORT=${REPORT:-docs/results/student}
BASE=${BASE:-1}
export HF_HUB_OFFLINE=1 TOKENIZERS_PARALLELISM=false
[ -f "$STUDENT/config.json" ] || { echo "no student at $STUDENT: run bash experiments/distil.sh first"; exit 2; }

collect() {  # policy steps seed num_envs (the bot: minigrid's expert with 25% random actions)
  local traj="$DATA/traj-UnlockLocal-$1"
  [ -f "$traj/.done" ] || { rm -rf "$traj"; "$ILLM" collect --env BabyAI-UnlockLocal-v0 --policy "$1" --steps "$2" \
      --num-envs "$4" --seed "$3" --no-raw --out "$traj" >/dev/null && touch "$traj/.done"; }
}
collect random 50000 4000000 16
collect bot 12000 3000000 8
annotators=("--model smollm2-135m-babyai" "--backend oracle")
[ "$BASE" = 1 ] && annotators+=("--model smollm2-135m")
for flags in "${annotators[@]}"; do
  for traj in "$DATA/traj-UnlockLocal-random" "$DATA/traj-UnlockLocal-bot"; do
    # shellcheck disable=SC2086
    "$ILLM" annotate "$traj" --cache "$DATA/ann" $flags --dtype float32 --history 0 --device "$DEVICE" \
        --batch-size "$BATCH_SIZE" --tasks action,summary | tail -n 1
  done
done

only=()
[ "$BASE" = 1 ] || only=(--only ppo --only illm-shuffled --only "illm-annotator=student" --only "illm-annotator=oracle")
"$ILLM" experiment experiments/specs/student.yaml --jobs "$JOBS" --out "$OUT" "${only[@]}"

# the annotators' probes, named as the runs name them (the quality curve pairs a run with the probe of its model):
# 400 states of the bot's episodes (seeds from 0, as distil.sh's), none of them states the student was taught
mkdir -p "$DATA/probes"
for flags in "--model smollm2-135m-babyai" "--backend oracle" "--model smollm2-135m"; do
  f="$DATA/probes/UnlockLocal-${flags##* }.json"
  # shellcheck disable=SC2086
  [ -f "$f" ] || "$ILLM" probe --env BabyAI-UnlockLocal-v0 $flags --dtype float32 --states 400 --out "$f" | tail -n 1
done
"$ILLM" report "$OUT" --every 16384 --final-points 2 --out "$REPORT" --overwrite \
    $(for f in "$DATA"/probes/UnlockLocal-*.json; do echo --probe "$f"; done)
