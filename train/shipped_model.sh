#!/usr/bin/env bash
# Reproduces the model shipped in sq_mitsuba/learning/weights/model.pt (see eval/MODEL_CARD.md),
# end to end on a CPU. Every step resumes: run it again after an interruption.
#
#   train/shipped_model.sh [WORK_DIR]      (default: data/shipped)
#
# 256 procedural spacecraft (catalogue seed 0: 228 train models, 28 test models covering all
# 14 archetypes), 32 images each at 128 px under the default space scene, then this project's
# CPU recipe (train/configs/cpu.toml) for 16 epochs, then evaluation on val and test.
set -euo pipefail
WORK=${1:-data/shipped}
SQ=${SQ:-sq-mitsuba}
mkdir -p "$WORK"

# 1. Models (about 1 s each). Skipped once the library is complete.
if [ ! -f "$WORK/models/splits.csv" ] || [ "$(wc -l < "$WORK/models/splits.csv")" -lt 256 ]; then
  $SQ models generate --count 256 --seed 0 --out "$WORK/models"
fi

# 2. Images, masks and labels (resumes by itself).
$SQ dataset render --models "$WORK/models" --out "$WORK/data" --images-per-model 32 \
  --resolution 128 --seed 0 --workers 2

# 3. Training (resumes from last.pt when the run folder holds one).
RESUME=""
[ -f "$WORK/run/last.pt" ] && RESUME="--resume"
$SQ train --config train/configs/cpu.toml --data "$WORK/data" --out "$WORK/run" \
  --set optim.epochs=16 $RESUME

# 4. The inference checkpoint the package ships: half precision, with the trivial baseline.
$SQ export --checkpoint "$WORK/run/best.pt" --data "$WORK/data" \
  --out sq_mitsuba/learning/weights/model.pt

# 5. Evaluation of the shipped file (eval/MODEL_CARD.md): every val and test image, then
#    48 images of each (spread evenly) with test-time refinement; the paper's tables beside.
for SPLIT in val test; do
  $SQ eval --data "$WORK/data" --split $SPLIT --out "$WORK/eval/$SPLIT" --label shipped
  $SQ eval --data "$WORK/data" --split $SPLIT --out "$WORK/eval/${SPLIT}_refined" --refine \
    --limit 48 --label shipped_refined
done
$SQ report "$WORK/eval/val" "$WORK/eval/test" --out "$WORK/eval/report"

# 6. Illumination study on the test models (the README's figure).
$SQ study illumination --models "$WORK/models" --split test --max-models 14 --poses 4 --step 30 \
  --out "$WORK/study" --set render.resolution=128 --set evaluation.refine=false
