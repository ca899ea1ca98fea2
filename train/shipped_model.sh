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
# alone), then train/configs/shipped_finetune.toml (every weight again, gently): the archetype
# model, $WORK/model_archetypes.pt. Then two broad fine-tunes of it, each on its own library of
# 200 compositional spacecraft of the training families (catalogue seeds 1 and 2, 8 views at
# 96 px; train/configs/broad_parsimony.toml, 14 epochs), exported part way back to the
# archetype model (a quarter the fine-tunes' average, three quarters the start: `export
# --start`; the primitives' existence from the fine-tunes alone: `--keep-existence`), then
# evaluation on val and test. Measured on 2 CPU cores: models 2 min, rendering
# about 12 min, training about 125 min for the archetype model and about 35 min for the broad
# fine-tunes with their libraries (eval/MODEL_CARD.md). DEVICE=cuda trains on a GPU.
# ARCHETYPE_MODEL=PT skips the archetype model's training and starts the broad fine-tunes
# from that file (the archetype model was the shipped model until 2026-11-27:
# `git show 1f9efc1:sq_mitsuba/model/weights/model.pt > PT`). The broad runs resume from
# their last.pt: after changing the archetype model or the broad config, remove
# $WORK/broad_*/run first.
set -euo pipefail
WORK=${1:-data/shipped}
SQ=${SQ:-sq-mitsuba}
DEVICE=${DEVICE:-cpu}
if [ -n "${ARCHETYPE_MODEL:-}" ]; then
  [ -f "$ARCHETYPE_MODEL" ] || { echo "$0: ARCHETYPE_MODEL $ARCHETYPE_MODEL: no such file" >&2; exit 2; }
fi
mkdir -p "$WORK"
if [ -n "${ARCHETYPE_MODEL:-}" ]; then
  cp "$ARCHETYPE_MODEL" "$WORK/model_archetypes.pt.tmp" && mv "$WORK/model_archetypes.pt.tmp" "$WORK/model_archetypes.pt"
fi

# 1. Models (about 1 s each). Skipped once the library is complete.
if [ ! -f "$WORK/models/splits.csv" ] || [ "$(wc -l < "$WORK/models/splits.csv")" -lt 192 ]; then
  $SQ models generate --count 192 --seed 0 --out "$WORK/models"
fi

# 2. Images, masks and labels at the training resolution (resumes by itself).
$SQ dataset render --models "$WORK/models" --out "$WORK/data" --images-per-model 64 \
  --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers 2

if [ -z "${ARCHETYPE_MODEL:-}" ]; then
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

  # 3d. The archetype model: half precision, with the trivial baseline.
  $SQ export --checkpoint "$WORK/run_finetune/best.pt" --data "$WORK/data" \
    --out "$WORK/model_archetypes.pt"
fi

# 4. Two broad fine-tunes of the archetype model, each on a library of its own (different
#    spacecraft: their average reads unseen families nearer than one run on both libraries,
#    eval/MODEL_CARD.md "Averaged weights"), about 17 min each on 2 CPU cores with the library.
for SEED in 1 2; do
  BROAD=$WORK/broad_$SEED
  if [ ! -f "$BROAD/models/splits.csv" ] || [ "$(wc -l < "$BROAD/models/splits.csv")" -lt 200 ]; then
    $SQ models generate --generator composed --families training --count 200 --seed $SEED \
      --points 20000 --out "$BROAD/models" --workers 2
  fi
  $SQ dataset render --models "$BROAD/models" --out "$BROAD/data" --images-per-model 8 \
    --resolution 96 --spp 16 --set mask.spp=16 --seed 0 --workers 2 --quiet
  RESUME=""
  [ -f "$BROAD/run/last.pt" ] && RESUME="--resume"
  $SQ train --config train/configs/broad_parsimony.toml --data "$BROAD/data" \
    --out "$BROAD/run" --set device="$DEVICE" --set optim.epochs=14 \
    --set init_from="\"$WORK/model_archetypes.pt\"" $RESUME
done

MODEL=sq_mitsuba/model/weights/model.pt
# 4b. The inference checkpoint the package ships: a quarter of the way from the archetype model
#     to the fine-tunes' average (eval/experiments/README.md, "Averaged weights and the share
#     of the start"), half precision, with the trivial baseline over the archetype library.
#     Every weight is mixed so but the existence column of the generators' last layer, which
#     is the fine-tunes' average alone: mixed back, the start's existence (0.9 for every
#     primitive) would keep all eight on every image (eval/MODEL_CARD.md, PARS-E).
$SQ export --checkpoint "$WORK/broad_1/run/last.pt" "$WORK/broad_2/run/last.pt" \
  --start "$WORK/model_archetypes.pt" --start-share 0.75 --keep-existence --data "$WORK/data" \
  --out "$MODEL"

# 5. Evaluation of the shipped file (eval/MODEL_CARD.md): val and test, the network alone,
#    with 256 of its predictions ranked against every model's mesh of the split, then with the
#    pose search and refinement; the paper's tables beside.
#    The file is named: without --checkpoint, eval reads the model of the installed package,
#    which is another checkout's when $SQ comes from one.
for SPLIT in val test; do
  $SQ eval --checkpoint "$MODEL" --data "$WORK/data" --split $SPLIT --out "$WORK/eval/$SPLIT" \
    --label shipped --set mesh_ranking=256
  $SQ eval --checkpoint "$MODEL" --data "$WORK/data" --split $SPLIT \
    --out "$WORK/eval/${SPLIT}_refined" --refine --limit 64 --label shipped_refined
done
$SQ report "$WORK/eval/val" "$WORK/eval/test" --out "$WORK/eval/report"
