#!/usr/bin/env bash
# The generalisation measure of eval/MODEL_CARD.md ("Beyond its generator"), for one model:
#
#   eval/experiments/generalisation.sh WORK CHECKPOINT NAME
#
# CHECKPOINT: an inference checkpoint that stores its trivial baseline (`sq-mitsuba export
# --checkpoint RUN/last.pt --data TRAINING_DATA`; the shipped model does), checked first.
#
# (1) Once per WORK, the two test sets (every later call reuses them; nothing is trained on
#     either):
#     - WORK/heldout/data, the leave-family-out set: 100 models of the three held-out
#       families (catalogue seed 7) x 4 images at 256 px (dataset seed 11), 400 images;
#     - WORK/infamily/data, the in-family check: the 21 archetype test models of catalogue
#       seed 0 (the shipped model's test split) x 8 images at 96 px (dataset seed 0, as the
#       broad library renders them: an image's sampling depends only on the dataset seed, the
#       model and its index, so these are the broad library's images of those models).
# (2) Four evaluations of CHECKPOINT into WORK/eval/NAME_{heldout,heldout_refined,infamily,
#     infamily_refined}: the network on every image; the search + refinement from the image
#     alone (no ground truth) on 120 held-out images and 64 in-family ones, spread evenly.
# (3) One line per figure of the model card's table (eval/experiments/generalisation_row.py).
#
# Environment: SQ (the command; default .venv/bin/sq-mitsuba), WORKERS (render processes,
# default 2), REFINED (0 skips the two refined evaluations: the network's figures in a tenth
# of the time), TURNS (the network's rows read from that many turned copies of each image,
# `eval --turns`; default 1), PY (the Python that checks the checkpoint first; default
# .venv/bin/python). Every step is skipped when its output is there, so an
# interrupted call resumes.
set -euo pipefail
[ $# -eq 3 ] || { echo "usage: $0 WORK CHECKPOINT NAME" >&2; exit 2; }
WORK=$1; CHECKPOINT=$2; NAME=$3
HERE=$(cd "$(dirname "$0")" && pwd)
SQ=${SQ:-$HERE/../../.venv/bin/sq-mitsuba}
WORKERS=${WORKERS:-2}
[ -f "$CHECKPOINT" ] || { echo "$0: checkpoint not found: $CHECKPOINT" >&2; exit 2; }
# Before any test set is made: the held-out set has no training images, so every figure is
# set against the trivial baseline the checkpoint stores (`sq-mitsuba export --data`); a
# training run's own checkpoint (RUN/last.pt) stores none.
PY=${PY:-$HERE/../../.venv/bin/python}
"$PY" - "$CHECKPOINT" "$0" <<'CHECK' || exit 2
import sys
from sq_mitsuba.model.checkpoint import checkpoint_baseline, read_checkpoint
path, script = sys.argv[1:]
try:
    baseline = checkpoint_baseline(read_checkpoint(path), path)
except ValueError as error:
    sys.exit(f"{script}: {error}")
if baseline is None:
    sys.exit(f"{script}: {path}: stores no trivial baseline (a training run's checkpoint?); "
             "export it with one first: sq-mitsuba export --checkpoint RUN/last.pt --data "
             "TRAINING_DATA --out MODEL.pt")
CHECK
mkdir -p "$WORK/eval"
rows() { [ -f "$1" ] && [ "$(wc -l < "$1")" -ge "$2" ]; }  # FILE N: a library of N models

heldout=$WORK/heldout
if [ ! -f "$heldout/data/splits.csv" ]; then
  # Complete once splits.csv lists every model (an interrupted batch is run again to finish).
  rows "$heldout/models/splits.csv" 100 || $SQ models generate --generator composed \
    --families held-out --count 100 --seed 7 --points 20000 --out "$heldout/models" \
    --workers "$WORKERS"
  $SQ dataset render --models "$heldout/models" --out "$heldout/data" --images-per-model 4 \
    --resolution 256 --spp 16 --seed 11 --workers "$WORKERS" --quiet
fi

infamily=$WORK/infamily
if [ ! -f "$infamily/data/splits.csv" ]; then
  rows "$infamily/catalogue/splits.csv" 192 || $SQ models generate --count 192 --seed 0 \
    --points 20000 --out "$infamily/catalogue" --workers "$WORKERS"
  # A models folder of the test split alone (links), so only those models are rendered.
  rm -rf "$infamily/models"; mkdir -p "$infamily/models"
  grep ',test$' "$infamily/catalogue/splits.csv" > "$infamily/models/splits.csv"
  cut -d, -f1 "$infamily/models/splits.csv" | while read -r model; do
    ln -s "$infamily/catalogue/$model" "$infamily/models/$model"
  done
  $SQ dataset render --models "$infamily/models" --out "$infamily/data" --images-per-model 8 \
    --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers "$WORKERS" --quiet
fi

run_eval() {  # DATA OUT [eval options...]
  local data=$1 out=$2; shift 2
  [ -f "$out/summary.csv" ] || $SQ eval --checkpoint "$CHECKPOINT" --data "$data" \
    --split test --out "$out" --quiet "$@"
}
run_eval "$heldout/data" "$WORK/eval/${NAME}_heldout" --turns "${TURNS:-1}"
run_eval "$infamily/data" "$WORK/eval/${NAME}_infamily" --turns "${TURNS:-1}"
if [ "${REFINED:-1}" != 0 ]; then
  run_eval "$heldout/data" "$WORK/eval/${NAME}_heldout_refined" --refine --limit 120 \
    --set refine_ground_truth=false
  run_eval "$infamily/data" "$WORK/eval/${NAME}_infamily_refined" --refine --limit 64 \
    --set refine_ground_truth=false
fi
python3 "$HERE/generalisation_row.py" "$WORK/eval" "$NAME"
