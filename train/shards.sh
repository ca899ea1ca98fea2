#!/usr/bin/env bash
# A library in K shards, one fine-tune of one start on each, their weights averaged
# (eval/MODEL_CARD.md, "Averaged weights": on the held-out families two such runs, averaged,
# read the shape nearer than one run on both shards with the same compute).
#
#   train/shards.sh DATA OUT K [train options, e.g. --set optim.epochs=14]
#
# (1) OUT/shard_<k>/data: a dataset folder per shard (links into DATA): every K-th training
#     model of DATA in name order, starting at the k-th, and all of DATA's test models. With
#     KEEP (an extended regular expression), the training models whose names match it are in
#     every shard and only the others are split (e.g. KEEP='^sc[0-9]{3}_': the archetypes at
#     the share they have in DATA's training images times K).
# (2) One run per shard into OUT/shard_<k>/run: `train --config CONFIG --set init_from=INIT`
#     and the options given, resumed when the run folder holds last.pt; one shard after
#     another, or with ONLY=k just shard k (one shard per machine, the folders shared).
# (3) Once every shard's run is there: OUT/model.pt, their last states averaged by `export`,
#     its baseline over DATA's training images.
#
# Environment: SQ (the command; default .venv/bin/sq-mitsuba), CONFIG (default
# train/configs/broad_chamfer100.toml), INIT (the common start; default the shipped model),
# ONLY (one shard's index), KEEP (above), SPLIT_ONLY=1 (make the shard folders, then stop:
# train/gpu_recipe.sh trains them side by side). Wrong arguments are one line and exit 2
# before any work.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
SQ=${SQ:-$HERE/../.venv/bin/sq-mitsuba}
CONFIG=${CONFIG:-$HERE/configs/broad_chamfer100.toml}
INIT=${INIT:-$HERE/../sq_mitsuba/model/weights/model.pt}
fail() { echo "$0: $*" >&2; exit 2; }
[ $# -ge 3 ] || fail "usage: $0 DATA OUT K [train options]"
DATA=$(cd "$1" 2>/dev/null && pwd) || fail "DATA $1: not a folder"
OUT=$2; K=$3; shift 3
[ -f "$DATA/splits.csv" ] || fail "DATA $DATA: no splits.csv (not a dataset folder)"
[[ $K =~ ^[0-9]+$ ]] && [ "$K" -ge 2 ] || fail "K: expected a whole number of shards >= 2, got $K"
[ -f "$CONFIG" ] || fail "CONFIG $CONFIG: no such file"
[ -f "$INIT" ] || fail "INIT $INIT: no such file"
mapfile -t MODELS < <(grep ',train$' "$DATA/splits.csv" | cut -d, -f1 | LC_ALL=C sort)
TRAIN=() KEPT=()
for model in "${MODELS[@]}"; do
  if [ -n "${KEEP:-}" ] && [[ $model =~ $KEEP ]]; then KEPT+=("$model"); else TRAIN+=("$model"); fi
done
[ "${#TRAIN[@]}" -ge "$K" ] || fail "K: $K shards of ${#TRAIN[@]} training models${KEEP:+ not matching KEEP}"
if [ -n "${ONLY:-}" ]; then
  [[ $ONLY =~ ^[0-9]+$ ]] && [ "$ONLY" -lt "$K" ] || fail "ONLY: expected a shard index below $K, got $ONLY"
fi

for ((k = 0; k < K; k++)); do
  shard=$OUT/shard_$k/data
  [ -f "$shard/splits.csv" ] && continue
  mkdir -p "$shard.tmp"
  cp "$DATA/camera.json" "$DATA/dataset.json" "$shard.tmp/"
  grep ',test$' "$DATA/splits.csv" > "$shard.tmp/splits.csv" || true
  for model in "${KEPT[@]}"; do echo "$model,train"; done >> "$shard.tmp/splits.csv"
  for ((i = k; i < ${#TRAIN[@]}; i += K)); do echo "${TRAIN[i]},train"; done \
    >> "$shard.tmp/splits.csv"
  cut -d, -f1 "$shard.tmp/splits.csv" | while read -r model; do
    ln -sfn "$DATA/$model" "$shard.tmp/$model"
  done
  mv "$shard.tmp" "$shard"
done
[ "${SPLIT_ONLY:-}" = 1 ] && exit 0

for ((k = 0; k < K; k++)); do
  [ -n "${ONLY:-}" ] && [ "$k" != "$ONLY" ] && continue
  run=$OUT/shard_$k/run
  resume=()
  [ -f "$run/last.pt" ] && resume=(--resume)
  $SQ train --config "$CONFIG" --data "$OUT/shard_$k/data" --out "$run" \
    --set init_from="\"$INIT\"" "${resume[@]}" "$@"
done

runs=()
for ((k = 0; k < K; k++)); do
  [ -f "$OUT/shard_$k/run/last.pt" ] && runs+=("$OUT/shard_$k/run/last.pt")
done
if [ "${#runs[@]}" -eq "$K" ]; then
  $SQ export --checkpoint "${runs[@]}" --data "$DATA" --out "$OUT/model.pt"
else
  echo "$0: ${#runs[@]} of $K shards trained; run the others (ONLY=k) to average them"
fi
