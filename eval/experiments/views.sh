#!/usr/bin/env bash
# Views per model: the model card's measurement of how many training images per model the
# recipe needs. The same 96 procedural spacecraft (catalogue seed 0: 85 train, 11 test models),
# rendered with VIEWS images each at the training resolution, the shipped recipe
# (recipe/r4_mask.toml) trained for about the same number of steps on each (epochs chosen so
# that epochs x steps per epoch is within 10 % of STEPS), then evaluated: val on its own
# dataset (new views of its training models), test on one shared test set (the VIEWS_TEST
# dataset's, so every run is scored on the same images of the same unknown models).
#
#   eval/experiments/views.sh WORK [VIEWS ...]      (default: 16 40 64)
#
# Environment: SQ (default sq-mitsuba), PYTHON (default python3), STEPS (default 510), LIMIT
# (val and test images per run, spread evenly; default 128), VIEWS_TEST (default 40), DEVICE
# (default cpu).
# Writes WORK/models, WORK/data_<V>, WORK/runs/v<V>/{best.pt,eval_val,eval_test} and
# WORK/table.md (recipe_table.py). Every step resumes or is skipped when done.
set -euo pipefail
WORK=$1; shift
HERE=$(cd "$(dirname "$0")" && pwd)
SQ=${SQ:-sq-mitsuba}
STEPS=${STEPS:-510}
LIMIT=${LIMIT:-128}
VIEWS_TEST=${VIEWS_TEST:-40}
DEVICE=${DEVICE:-cpu}
ALL=("$@")
[ ${#ALL[@]} -gt 0 ] || ALL=(16 40 64)
mkdir -p "$WORK/runs"
if [ ! -f "$WORK/models/splits.csv" ] || [ "$(wc -l < "$WORK/models/splits.csv")" -lt 96 ]; then
  $SQ models generate --count 96 --seed 0 --out "$WORK/models"  # again: finishes a library cut short
fi

render() {  # Images never depend on the count: data_V's first images are every other's.
  $SQ dataset render --models "$WORK/models" --out "$WORK/data_$1" --images-per-model "$1" \
    --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers 2 --quiet
}
render "$VIEWS_TEST"
for V in "${ALL[@]}"; do
  render "$V"
  run=$WORK/runs/v$V
  # Training images per train model: the SPE3R split keeps [0, 0.4 V) and [0.5 V, 0.9 V).
  per_model=$(( (4 * V + 9) / 10 + (9 * V + 9) / 10 - (5 * V + 9) / 10 ))
  train_models=$(grep -c ",train" "$WORK/data_$V/splits.csv")
  per_epoch=$(( (per_model * train_models + 31) / 32 ))
  epochs=$(( (STEPS + per_epoch / 2) / per_epoch )); [ "$epochs" -ge 1 ] || epochs=1
  echo "views $V: $per_model training images per model, $per_epoch steps per epoch, $epochs epochs ($((epochs * per_epoch)) steps)"
  if [ ! -f "$run.trained" ]; then
    resume=""; [ -f "$run/last.pt" ] && resume=--resume
    $SQ train --config "$HERE/recipe/r4_mask.toml" --data "$WORK/data_$V" --out "$run" \
      --set optim.epochs=$epochs --set device="$DEVICE" --quiet $resume
    touch "$run.trained"
  fi
  [ -f "$run/eval_val/summary.csv" ] || $SQ eval --checkpoint "$run/best.pt" \
    --data "$WORK/data_$V" --split val --out "$run/eval_val" --limit "$LIMIT" --no-figures --quiet
  [ -f "$run/eval_test/summary.csv" ] || $SQ eval --checkpoint "$run/best.pt" \
    --data "$WORK/data_$VIEWS_TEST" --split test --out "$run/eval_test" --limit "$LIMIT" \
    --no-figures --quiet
done
${PYTHON:-python3} "$HERE/recipe_table.py" "$WORK/runs" --names "${ALL[@]/#/v}" > "$WORK/table.md"
cat "$WORK/table.md"
