#!/usr/bin/env bash
# The recipe study of eval/MODEL_CARD.md: one fixed dataset, one seed, the same steps for every
# run; each run changes one thing from the run before it (eval/experiments/recipe/*.toml).
#
#   eval/experiments/recipe.sh WORK [CONFIG.toml ...]      (default: every recipe/*.toml)
#
# Environment: SQ (the command, default sq-mitsuba), MODELS (procedural spacecraft, catalogue
# seed 0; default 96), VIEWS (images per model, default 40), DEVICE (cpu or cuda; default
# cpu), PARALLEL (runs trained at once, default 1; on a GPU, all), TRAIN_LIMIT (seconds a run
# may train, default: no limit; the evaluation then takes its best.pt so far) or TRAIN_UNTIL
# (a Unix time at which training stops, for a job with a wall-clock limit), LIMIT (val and
# test images evaluated per run, spread evenly; default 160).
# Writes WORK/models, WORK/data, WORK/runs/<config>/{best.pt,log.csv,eval_val,eval_test} and
# WORK/table.md (eval/experiments/recipe_table.py). Every step resumes or is skipped when done.
set -euo pipefail
WORK=$1; shift
HERE=$(cd "$(dirname "$0")" && pwd)
SQ=${SQ:-sq-mitsuba}
MODELS=${MODELS:-96}
VIEWS=${VIEWS:-40}
DEVICE=${DEVICE:-cpu}
PARALLEL=${PARALLEL:-1}
LIMIT=${LIMIT:-160}
CONFIGS=("$@")
[ ${#CONFIGS[@]} -gt 0 ] || CONFIGS=("$HERE"/recipe/*.toml)
mkdir -p "$WORK/runs"

if [ ! -f "$WORK/models/splits.csv" ] || [ "$(wc -l < "$WORK/models/splits.csv")" -lt "$MODELS" ]; then
  $SQ models generate --count "$MODELS" --seed 0 --out "$WORK/models"
fi
# Training resolution, few samples per pixel (the masks' 16 at 256 px are 114 at 96 px).
$SQ dataset render --models "$WORK/models" --out "$WORK/data" --images-per-model "$VIEWS" \
  --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers "${RENDER_WORKERS:-2}" --quiet

train_one() {
  local config=$1 name run resume=""
  name=$(basename "$config" .toml); run=$WORK/runs/$name
  [ -f "$run/last.pt" ] && resume=--resume
  if [ -n "${TRAIN_UNTIL:-}" ]; then TRAIN_LIMIT=$((TRAIN_UNTIL - $(date +%s))); fi
  if [ -n "${TRAIN_LIMIT:-}" ]; then
    timeout --signal=INT "$TRAIN_LIMIT" $SQ train --config "$config" --data "$WORK/data" \
      --out "$run" --set device="$DEVICE" --quiet $resume > "$WORK/runs/$name.log" 2>&1 || true
  else
    $SQ train --config "$config" --data "$WORK/data" --out "$run" --set device="$DEVICE" \
      --quiet $resume > "$WORK/runs/$name.log" 2>&1 || echo "$name: training failed"
  fi
  for split in val test; do
    [ -f "$run/eval_$split/summary.csv" ] || $SQ eval --checkpoint "$run/best.pt" \
      --data "$WORK/data" --split $split --out "$run/eval_$split" --limit "$LIMIT" \
      --no-figures --quiet >> "$WORK/runs/$name.log" 2>&1 || echo "$name: eval $split failed"
  done
}

running=0
for config in "${CONFIGS[@]}"; do
  train_one "$config" &
  running=$((running + 1))
  if [ "$running" -ge "$PARALLEL" ]; then wait -n || true; running=$((running - 1)); fi
done
wait || true  # a failed run shows as "-" in the table and names itself above
names=(); for config in "${CONFIGS[@]}"; do names+=("$(basename "$config" .toml)"); done
python3 "$HERE/recipe_table.py" "$WORK/runs" --names "${names[@]}" | tee "$WORK/table.md"
