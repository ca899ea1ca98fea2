#!/usr/bin/env bash
# The broad recipe for longer, on one GPU machine (issue "a model that generalises beyond its
# generator": "on a GPU, the same recipe for longer"). Everything happens there, in one call:
#
#   (1) a library generated in parallel processes: ARCHETYPES archetype models (seed 0, the
#       shipped model's catalogue), COMPOSED models of the training families and GRAPH
#       free-form part graphs (catalogue seed SEED; the held-out families are never made);
#   (2) VIEWS images of each at 96 px, spp 16, rendered with Mitsuba on the GPU;
#   (3) two runs of train/configs/broad_chamfer100_b256.toml on that same data, side by
#       side on the GPU, each a whole cosine schedule; PAIR says which one change they differ
#       by. PAIR=schedule (the default): both from the shipped model, "short" sees SHORT
#       images (R6's and R7's 181,248 on 2 CPU cores), "long" LONG_FACTOR times as many: what
#       a longer schedule alone is worth at a fixed library. PAIR=start: both see SHORT
#       images, "shipped" from the shipped model, "imagenet" from the ImageNet encoder at the
#       first stage's learning rate (1e-3 at batch 32, its warm-up of 1,600 images): whether
#       the shipped model's start holds back what the broad library teaches. PAIR=chamfer:
#       both from the shipped model for SHORT images, the Chamfer term weighted 300 and 1,000
#       instead of the config's 100 (a dose above R7's; G2's "shipped" run is the 100 beside
#       them): whether a heavier shape term fits the library's shapes nearer at scale. The
#       held-out families (`eval`) judge both, on a machine of any kind;
#   (4) OUT_DIR/model_LABEL.pt for each run (`sq-mitsuba export`, with the trivial baseline
#       of that data), its log.csv and config.json, and summary.txt.
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
#   GRAPH [750], SEED [21], VIEWS [3], RENDER_WORKERS [12], PAIR [schedule; or start, chamfer],
#   SHORT [181248], LONG_FACTOR [3] (or LONG, the long run's images seen; PAIR=schedule),
#   TOTAL_SECONDS [540], DEVICE [cuda; cpu dry-runs it, e.g. DEVICE=cpu ARCHETYPES=2
#   COMPOSED=4 GRAPH=2 VIEWS=2 SHORT=512 RENDER_WORKERS=2 train/gpu_recipe.sh /tmp/dry],
#   PYTHON [python3], WORK (folder kept for the library, data and runs; default temporary).
set -u -o pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
source "$repo/train/gpu_stages.sh" sq-gpu-recipe "${1:-}"
left() { echo $(( deadline - SECONDS )); }
config=train/configs/broad_chamfer100_b256.toml
short=${SHORT:-181248}
long=${LONG:-$(( short * ${LONG_FACTOR:-3} ))}
# The two runs (checked before any work), each "LABEL IMAGES_SEEN START [KEY=VALUE...]", START
# shipped or imagenet, then config overrides of that run alone; the first listed starts first.
case ${PAIR:-schedule} in
  schedule) runs=("long $long shipped" "short $short shipped") ;;
  start) runs=("imagenet $short imagenet" "shipped $short shipped") ;;
  chamfer) runs=("chamfer1000 $short shipped loss.weights.chamfer=1000.0"
                 "chamfer300 $short shipped loss.weights.chamfer=300.0") ;;
  *) echo "PAIR: expected schedule, start or chamfer, got '$PAIR'" >&2; exit 2 ;;
esac
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
images=$("$py" -c 'import sys
from sq_mitsuba.data.spe3r import Spe3rDataset
print(len(Spe3rDataset(sys.argv[1], "train", image_size=96, num_surface=1, num_occupancy=2)))' \
  "$data" 2>/dev/null) || images=0
note "training images: $images"
[ "$images" -gt 0 ] || { note "no training images: stopping"; exit 1; }

# (3) Two runs on the same data, side by side: the first starts first and builds the cache,
# the second once the first's step is logged (the cache is then there to be read).
batch=$("$py" -c 'import sys
from sq_mitsuba.training.config import load_train_config
print(load_train_config(sys.argv[1]).optim.batch_size)' "$config")
epochs() { "$py" -c "import math; print(max(1, round($1 / (math.ceil($images / $batch) * $batch))))"; }
train_run() {  # SECONDS LABEL IMAGES_SEEN START [KEY=VALUE...]
  local seconds=$1 label=$2 seen=$3 from=$4; shift 4
  local start_args=(--set 'init_from="sq_mitsuba/model/weights/model.pt"') overrides=()
  # From ImageNet: no init_from, and the first stage's rate and warm-up (cpu.toml), not the
  # fine-tune's.
  [ "$from" = imagenet ] && start_args=(--set optim.lr=1e-3 --set optim.warmup_images=1600)
  for pair in "$@"; do overrides+=(--set "$pair"); done
  timeout -k 10 "$seconds" "${sq[@]}" train --config "$config" --data "$data" \
    --out "$work/run_$label" --quiet --set "device=\"$device\"" \
    --set "optim.epochs=$(epochs "$seen")" "${start_args[@]}" "${overrides[@]}" \
    --set "data.cache_dir=\"$work/cache\"" > "$work/train_$label.txt" 2>&1
}
read -r first first_seen first_start first_sets <<< "${runs[0]}"
read -r second second_seen second_start second_sets <<< "${runs[1]}"
budget=$(( $(left) - 60 ))  # a minute kept for the exports
note "$first ($first_start ${first_sets:-}): $(epochs "$first_seen") epochs, $second" \
  "($second_start ${second_sets:-}): $(epochs "$second_seen") epochs of $images images;" \
  "training budget ${budget} s"
start=$SECONDS
# shellcheck disable=SC2086  # the overrides are KEY=VALUE words without spaces
train_run "$budget" "$first" "$first_seen" "$first_start" ${first_sets:-} &
first_pid=$!
while [ ! -s "$work/run_$first/log.csv" ] && kill -0 $first_pid 2>/dev/null; do sleep 2; done
note "$first: first step logged after $((SECONDS - start)) s (cache, symmetries, start-up)"
# shellcheck disable=SC2086
train_run $(( budget - (SECONDS - start) )) "$second" "$second_seen" "$second_start" \
  ${second_sets:-} &
second_pid=$!
wait $second_pid; note "stage train_$second rc=$? seconds=$((SECONDS - start))"
wait $first_pid; note "stage train_$first rc=$? seconds=$((SECONDS - start))"

# (4) Exports and logs.
for label in "$second" "$first"; do
  run=$work/run_$label
  [ -f "$run/last.pt" ] || { note "$label: no checkpoint"; tail -5 "$work/train_$label.txt"; continue; }
  "$py" - "$run" "$label" <<'EOF' | tee -a "$summary"
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
EOF
  stage "export_$label" 60 "${sq[@]}" export --checkpoint "$run/last.pt" --data "$data" \
    --out "$out/model_$label.pt" 2>&1 | tail -2
  cp "$run/log.csv" "$out/log_$label.csv"; cp "$run/config.json" "$out/config_$label.json"
done
tail -3 "$work/train_$first.txt" "$work/train_$second.txt" 2>/dev/null
note "gpu_recipe done in $SECONDS s"
