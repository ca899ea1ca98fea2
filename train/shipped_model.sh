#!/usr/bin/env bash
# Reproduces the model shipped in sq_mitsuba/model/weights/model.pt (see eval/MODEL_CARD.md),
# end to end. Every step resumes: run it again after an interruption.
#
#   train/shipped_model.sh [WORK_DIR]      (default: data/shipped)
#
# 192 procedural spacecraft (catalogue seed 0: 171 train models, 21 test models), 64 images
# each at the training resolution (96 px, 16 spp), then train/configs/shipped.toml (ImageNet
# Lite0 encoder, spatial latents, rotation distribution head, mask head; 24 epochs, 6,672
# steps), then train/configs/shipped_mask.toml (its mask head at full resolution, trained
# alone), then train/configs/shipped_finetune.toml (every weight again, gently), then
# evaluation on val and test. Measured on 2 CPU cores: models 2 min, rendering
# about 12 min, training about 50 min at 80 images/s (eval/MODEL_CARD.md). DEVICE=cuda trains
# on a GPU.
set -euo pipefail
WORK=${1:-data/shipped}
SQ=${SQ:-sq-mitsuba}
DEVICE=${DEVICE:-cpu}
mkdir -p "$WORK"

# 1. Models (about 1 s each). Skipped once the library is complete.
if [ ! -f "$WORK/models/splits.csv" ] || [ "$(wc -l < "$WORK/models/splits.csv")" -lt 192 ]; then
  $SQ models generate --count 192 --seed 0 --out "$WORK/models"
fi

# 2. Images, masks and labels at the training resolution (resumes by itself).
$SQ dataset render --models "$WORK/models" --out "$WORK/data" --images-per-model 64 \
  --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers 2

# 3. Training (resumes from last.pt when the run folder holds one).
RESUME=""
[ -f "$WORK/run/last.pt" ] && RESUME="--resume"
$SQ train --config train/configs/shipped.toml --data "$WORK/data" --out "$WORK/run" \
  --set device="$DEVICE" $RESUME

# 3b. The mask head grown to full resolution and trained alone on top of that network
#     (everything else frozen; 4 epochs, about 8 min on 2 CPU cores), sharing the cache.
RESUME=""
[ -f "$WORK/run_mask/last.pt" ] && RESUME="--resume"
$SQ train --config train/configs/shipped_mask.toml --data "$WORK/data" --out "$WORK/run_mask" \
  --set device="$DEVICE" --set init_from="\"$WORK/run/best.pt\"" \
  --set data.cache_dir="\"$WORK/run/cache\"" $RESUME

# 3c. Every weight trained together again from 3b, with the first stage's losses at a third of
#     its learning rate (16 epochs, about 40 min on 2 CPU cores), sharing the cache.
RESUME=""
[ -f "$WORK/run_finetune/last.pt" ] && RESUME="--resume"
$SQ train --config train/configs/shipped_finetune.toml --data "$WORK/data" \
  --out "$WORK/run_finetune" --set device="$DEVICE" \
  --set init_from="\"$WORK/run_mask/best.pt\"" --set data.cache_dir="\"$WORK/run/cache\"" $RESUME

# 4. The inference checkpoint the package ships: half precision, with the trivial baseline.
$SQ export --checkpoint "$WORK/run_finetune/best.pt" --data "$WORK/data" \
  --out sq_mitsuba/model/weights/model.pt

# 5. Evaluation of the shipped file (eval/MODEL_CARD.md): val and test, the network alone,
#    with 256 of its predictions ranked against every model's mesh of the split, then with the
#    pose search and refinement; the paper's tables beside.
for SPLIT in val test; do
  $SQ eval --data "$WORK/data" --split $SPLIT --out "$WORK/eval/$SPLIT" --label shipped \
    --set mesh_ranking=256
  $SQ eval --data "$WORK/data" --split $SPLIT --out "$WORK/eval/${SPLIT}_refined" --refine \
    --limit 64 --label shipped_refined
done
$SQ report "$WORK/eval/val" "$WORK/eval/test" --out "$WORK/eval/report"
