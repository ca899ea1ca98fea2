#!/usr/bin/env bash
# The broad recipe for longer, on one GPU machine (issue "a model that generalises beyond its
# generator": "on a GPU, the same recipe for longer"). Everything happens there, in one call:
#
#   (1) a library generated in parallel processes: ARCHETYPES archetype models (seed 0, the
#       shipped model's catalogue), COMPOSED models of the training families and GRAPH
#       free-form part graphs (catalogue seed SEED; the held-out families are never made);
#   (2) VIEWS images of each at 96 px, spp 16, rendered with Mitsuba on the GPU;
#   (3) the half-turn symmetries of every training model, analysed once in all the cores;
#   (4) runs of train/configs/broad_chamfer100_b256.toml side by side on the GPU, each a
#       whole cosine schedule from the shipped model unless said; PAIR says what they differ
#       by. PAIR=schedule (the default): "short" sees SHORT images (R6's and R7's 181,248 on
#       2 CPU cores), "long" LONG_FACTOR times as many: what a longer schedule alone is worth
#       at a fixed library. PAIR=start: both see SHORT images, "shipped" from the shipped
#       model, "imagenet" from the ImageNet encoder at the first stage's learning rate (1e-3 at
#       batch 32, its warm-up of 1,600 images): whether the shipped model's start holds back
#       what the broad library teaches. PAIR=chamfer: both for SHORT images, the Chamfer term
#       weighted 300 and 1,000 instead of the config's 100: whether a heavier shape term fits
#       the library's shapes nearer at scale. PAIR=shards: the runs of SHARD_SETS
#       side by side, each set one of "split" (the library in SHARDS shards, every training
#       model in one; train/shards.sh), "keep" (the archetypes in every shard, the rest split:
#       KEEP='^sc[0-9]{3}_'), one run per shard of SHORT / SHARDS images, or "all" (one run on
#       the whole library for SHORT images): what averaging runs on disjoint parts of one
#       library is worth against one run on all of it at the same compute, and whether the
#       archetypes in every shard hold the in-family figures. The held-out families (`eval`)
#       judge them, on a machine of any kind;
#   (5) OUT_DIR/model_NAME.pt for each run (`sq-mitsuba export`, with the trivial baseline of
#       the library), its log.csv and config.json, and summary.txt. PAIR=shards exports
#       model_SET (shard 0 alone) and model_SET_all (all the shards' runs averaged) per set
#       and model_all, and the logs of shard 0 and of "all": at most 8 files come back from
#       the machine, 64 MiB in all (a model is 12 MB). Exports get EXPORT_SECONDS [150] each,
#       run in parallel (each reads every model's points and runs the network on 256 images).
#
# A run the time limit cuts (TOTAL_SECONDS for the whole script) is exported from its last
# checkpoint (every 50 steps) and said to be cut in summary.txt: its schedule did not finish.
# Measured on one H200 with 16 cores (2026-11-27; ARCHETYPES=96 COMPOSED=1200 GRAPH=600):
# 1,895 models in 63 s, 5,685 images in 89 s, 102 s from the start of training to its first
# step (image cache, symmetries of 1,694 models, CUDA start-up), then 1,476 and 1,705 images/s
# for the two runs side by side; the whole script takes about 9 minutes with a long run of
# about 330,000 images (eval/BENCHMARKS.md).
#
# Usage, from the repository root:  train/gpu_recipe.sh [OUT_DIR]     (default /tmp/sq-gpu-recipe)
#   Without mitsuba installed it unpacks .gpu/site-cpXY.tar.xz (train/gpu_bundle.sh builds it)
#   into /tmp/site. Environment (defaults in brackets): ARCHETYPES [128], COMPOSED [1500],
#   GRAPH [750], SEED [21], VIEWS [3], RENDER_WORKERS [12], PAIR [schedule; or start,
#   chamfer, shards], SHARDS [4], SHARD_SETS [split keep; or all],
#   SHORT [181248], LONG_FACTOR [3] (or LONG, the long run's images seen; PAIR=schedule),
#   TOTAL_SECONDS [540], DEVICE [cuda; cpu dry-runs it, e.g. DEVICE=cpu ARCHETYPES=2
#   COMPOSED=4 GRAPH=2 VIEWS=2 SHORT=512 RENDER_WORKERS=2 train/gpu_recipe.sh /tmp/dry],
#   PYTHON [python3], WORK (folder kept for the library, data and runs; default temporary),
#   INIT [sq_mitsuba/model/weights/model.pt] ("shipped" below: the checkpoint the runs
#   start from; runs G1-G4 of eval/MODEL_CARD.md started from the five-primitive archetype
#   model shipped before, `git show 1f9efc1:sq_mitsuba/model/weights/model.pt > FILE`; G5 put
#   that file in place of the shipped one for the call and left INIT unset, since a lending
#   service that copies the tree and .gpu/ (its 41 MB bundle) may refuse a second 11 MB model).
set -u -o pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
start_model=${INIT:-$repo/sq_mitsuba/model/weights/model.pt}
case $start_model in /*) ;; *) start_model=$PWD/$start_model ;; esac
[ -f "$start_model" ] || { echo "$0: INIT $start_model: no such file" >&2; exit 2; }
source "$repo/train/gpu_stages.sh" sq-gpu-recipe "${1:-}"
left() { echo $(( deadline - SECONDS )); }
config=train/configs/broad_chamfer100_b256.toml
short=${SHORT:-181248}
long=${LONG:-$(( short * ${LONG_FACTOR:-3} ))}
# The runs (checked before any work), each "LABEL IMAGES_SEEN START DATA [KEY=VALUE...]":
# START shipped or imagenet, DATA - (the library's images) or a shard's folder under WORK,
# then config overrides of that run alone. `exports` lists "NAME LABEL..." (OUT/model_NAME.pt
# from those runs, averaged if several) and keep_logs the runs whose log.csv comes back: what
# comes back from the machine is at most 8 files of 16 MiB, 64 MiB in all (a model is 12 MB).
shards=${SHARDS:-4}
case ${PAIR:-schedule} in
  schedule) runs=("long $long shipped -" "short $short shipped -") ;;
  start) runs=("imagenet $short imagenet -" "shipped $short shipped -") ;;
  chamfer) runs=("chamfer1000 $short shipped - loss.weights.chamfer=1000.0"
                 "chamfer300 $short shipped - loss.weights.chamfer=300.0") ;;
  shards)
    [[ $shards =~ ^[0-9]+$ ]] && [ "$shards" -ge 2 ] \
      || { echo "SHARDS: expected a whole number >= 2, got '$shards'" >&2; exit 2; }
    runs=() exports=() keep_logs=()
    for set in ${SHARD_SETS:-split keep}; do
      case $set in
        all) runs+=("all $short shipped -"); exports+=("all all"); keep_logs+=(all) ;;
        split|keep)
          for ((k = 0; k < shards; k++)); do
            runs+=("$set$k $(( short / shards )) shipped $set/shard_$k/data")
          done
          exports+=("$set ${set}0" "${set}_all $(printf "$set%d " $(seq 0 $((shards - 1))))")
          keep_logs+=("${set}0") ;;
        *) echo "SHARD_SETS: expected split, keep or all, got '$set'" >&2; exit 2 ;;
      esac
    done ;;
  *) echo "PAIR: expected schedule, start, chamfer or shards, got '$PAIR'" >&2; exit 2 ;;
esac
if [ "${PAIR:-schedule}" != shards ]; then
  exports=() keep_logs=()
  for spec in "${runs[@]}"; do exports+=("${spec%% *} ${spec%% *}"); keep_logs+=("${spec%% *}"); done
fi
cores=$(nproc)
sq=("$py" -m sq_mitsuba)

source "$repo/train/gpu_site.sh" gpu_recipe
export PYTHONPATH=$repo${PYTHONPATH:+:$PYTHONPATH}
cd "$repo" || exit 2
[ "$device" = cpu ] && export SQ_MITSUBA_VARIANT=llvm_ad_mono
{ nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"; } | tee -a "$summary"
note "gpu_recipe: $cores cores; pair ${PAIR:-schedule}; short $short, long $long images seen; $config"

# (1) The library.
library=$work/models
for spec in "archetypes ${ARCHETYPES:-128} 0 all" "composed ${COMPOSED:-1500} ${SEED:-21} training" \
            "graph ${GRAPH:-750} ${SEED:-21} all"; do
  read -r generator count seed families <<< "$spec"
  [ "$count" -gt 0 ] || continue
  stage "models_$generator" "$(left)" "${sq[@]}" models generate --generator "$generator" --count "$count" \
    --seed "$seed" --families "$families" --points 20000 --out "$library" --workers "$cores" \
    > "$work/models_$generator.txt" 2>&1
  grep -E "written|failed|Error" "$work/models_$generator.txt" | tail -3 | tee -a "$summary"
done

# (2) The images.
data=$work/data
stage render "$(left)" "${sq[@]}" dataset render --models "$library" --out "$data" \
  --images-per-model "${VIEWS:-3}" --resolution 96 --spp 16 --set mask.spp=16 \
  --seed "${SEED:-21}" --workers "${RENDER_WORKERS:-12}" --quiet 2>&1 | grep -v "stage " \
  | tail -3 | tee -a "$summary"
count_images() {  # DATA: its training images (0 when it cannot be read)
  "$py" -c 'import sys
from sq_mitsuba.data.spe3r import Spe3rDataset
print(len(Spe3rDataset(sys.argv[1], "train", image_size=96, num_surface=1, num_occupancy=2)))' \
    "$1" 2>/dev/null || echo 0
}
images=$(count_images "$data")
note "training images: $images"
[ "$images" -gt 0 ] || { note "no training images: stopping"; exit 1; }

# (3) The half-turn symmetries of every training model, analysed once in all the cores into
# the cache every run reads (runs started together would each analyse the same models).
stage symmetries "$(left)" "$py" -c 'import sys
from pathlib import Path
from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.training.data_stream import symmetry_table
root = Path(sys.argv[1])
models = Spe3rDataset(root, "train", image_size=96, num_surface=1, num_occupancy=2).models
print(f"symmetries of {len(symmetry_table(root, models, Path(sys.argv[2])))} models")' \
  "$data" "$work/cache/symmetries" 2>&1 | tail -1 | tee -a "$summary"

# (4) The shards' dataset folders (links into the library's), for PAIR=shards.
if [ "${PAIR:-schedule}" = shards ]; then
  for set in ${SHARD_SETS:-split keep}; do
    case $set in split) keep= ;; keep) keep='^sc[0-9]{3}_' ;; *) continue ;; esac
    KEEP=$keep SPLIT_ONLY=1 "$repo/train/shards.sh" "$data" "$work/$set" "$shards" || exit 2
  done
fi

# (5) The runs side by side. A run on the same data as an earlier one starts once that one's
# first step is logged (its image cache is then there to be read); the others start at once.
batch=$("$py" -c 'import sys
from sq_mitsuba.training.config import load_train_config
print(load_train_config(sys.argv[1]).optim.batch_size)' "$config")
epochs() {  # IMAGES_SEEN DATA_IMAGES: whole epochs of that data nearest the images seen
  "$py" -c "import math; print(max(1, round($1 / (math.ceil($2 / $batch) * $batch))))"
}
train_run() {  # SECONDS LABEL IMAGES_SEEN START DATA DATA_IMAGES [KEY=VALUE...]
  local seconds=$1 label=$2 seen=$3 from=$4 run_data=$5 run_images=$6; shift 6
  local start_args=(--set "init_from=\"$start_model\"") overrides=()
  # From ImageNet: no init_from, and the first stage's rate and warm-up (cpu.toml), not the
  # fine-tune's.
  [ "$from" = imagenet ] && start_args=(--set optim.lr=1e-3 --set optim.warmup_images=1600)
  for pair in "$@"; do overrides+=(--set "$pair"); done
  OMP_NUM_THREADS=$threads timeout -k 10 "$seconds" "${sq[@]}" train --config "$config" --data "$run_data" \
    --out "$work/run_$label" --quiet --set "device=\"$device\"" \
    --set "optim.epochs=$(epochs "$seen" "$run_images")" "${start_args[@]}" \
    "${overrides[@]}" --set "data.cache_dir=\"$work/cache\"" > "$work/train_$label.txt" 2>&1
}
export_seconds=${EXPORT_SECONDS:-150}  # an export reads every model's points and runs 256 images
budget=$(( $(left) - export_seconds - 10 ))  # kept for the exports
note "training budget ${budget} s for ${#runs[@]} runs"
start=$SECONDS
declare -A first_on=() pid_of=()  # data folder -> the first run on it; run -> its process
pids=() labels=()
# Eight runs at once share the cores: torch's own threads per process, a share of them each.
threads=$(( cores / ${#runs[@]} )); [ "$threads" -ge 1 ] || threads=1
for spec in "${runs[@]}"; do
  read -r label seen from run_data sets <<< "$spec"
  [ "$run_data" = - ] && run_data=$data || run_data=$work/$run_data
  if [ -n "${first_on[$run_data]:-}" ]; then
    earlier=${first_on[$run_data]}
    while [ ! -s "$work/run_$earlier/log.csv" ] && kill -0 "${pid_of[$earlier]}" 2>/dev/null; do
      sleep 2
    done
    note "$earlier: first step logged after $((SECONDS - start)) s (cache, start-up)"
  else
    first_on[$run_data]=$label
  fi
  run_images=$images
  [ "$run_data" = "$data" ] || run_images=$(count_images "$run_data")
  note "$label ($from${sets:+ $sets}): $seen images seen on $run_images images"
  # shellcheck disable=SC2086  # the overrides are KEY=VALUE words without spaces
  train_run $(( budget - (SECONDS - start) )) "$label" "$seen" "$from" "$run_data" \
    "$run_images" ${sets:-} &
  pids+=($!) labels+=("$label") pid_of[$label]=$!
done
for i in "${!pids[@]}"; do
  wait "${pids[i]}"; note "stage train_${labels[i]} rc=$? seconds=$((SECONDS - start))"
done

# (6) Each run's log line, then the exports (in parallel) and logs that come back.
for label in "${labels[@]}"; do
  run=$work/run_$label
  [ -f "$run/last.pt" ] || { note "$label: no checkpoint"; tail -5 "$work/train_$label.txt"; continue; }
  "$py" - "$run" "$label" <<'PY' | tee -a "$summary"
import csv
import statistics
import sys
from pathlib import Path

import torch

run, label = Path(sys.argv[1]), sys.argv[2]
state = torch.load(run / "last.pt", map_location="cpu", weights_only=True)
log = list(csv.DictReader((run / "log.csv").open()))
rate = statistics.median(float(r["images_per_s"]) for r in log[3:]) if len(log) > 4 else 0.0
steps = int(log[-1]["step"]) if log else 0
cut = "" if state["step"] >= state["total_steps"] else ", CUT by the time limit"
print(f"{label}: checkpoint at step {state['step']} of {state['total_steps']}{cut}; "
      f"{steps} steps logged, median {rate:.0f} images/s, last loss "
      f"{float(log[-1]['loss']):.4f}" if log else f"{label}: empty log")
PY
done
export_model() {  # NAME LABEL...: OUT/model_NAME.pt, the runs' last states (averaged if several)
  local name=$1 checkpoints=() label; shift
  for label in "$@"; do
    [ -f "$work/run_$label/last.pt" ] || { note "model_$name: $label has no checkpoint"; return 1; }
    checkpoints+=("$work/run_$label/last.pt")
  done
  OMP_NUM_THREADS=$(( cores / ${#exports[@]} > 0 ? cores / ${#exports[@]} : 1 )) \
    stage "export_$name" "$export_seconds" "${sq[@]}" export --checkpoint "${checkpoints[@]}" --data "$data" \
    --out "$out/model_$name.pt" 2>&1 | tail -2
}
for spec in "${exports[@]}"; do
  # shellcheck disable=SC2086  # NAME LABEL... words
  export_model $spec &
done
wait
for label in "${keep_logs[@]}"; do
  [ -f "$work/run_$label/log.csv" ] || continue
  cp "$work/run_$label/log.csv" "$out/log_$label.csv"
  [ "${PAIR:-schedule}" = shards ] || cp "$work/run_$label/config.json" "$out/config_$label.json"
done
tail -n 3 $(for l in "${labels[@]}"; do echo "$work/train_$l.txt"; done) 2>/dev/null
note "gpu_recipe done in $SECONDS s"
