#!/usr/bin/env bash
# Check the pass path (`predict --sequence`, `study passes`) on a machine with an NVIDIA GPU,
# where Mitsuba renders with cuda_ad_mono and torch's network runs on the CPU, and measure
# what a GPU user gets from it (issue "a pass of images"):
#   (1) doctor's silhouette self-test on the chosen variant;
#   (2) two sets of passes made there, as on the CPU: 12 spacecraft of the held-out families
#       (catalogue seed 7) and a tuning set of 12 of the training families (catalogue seed 77,
#       every model marked test), each one pass of 8 frames at 256 px, spp 16, dataset seed 7;
#   (3) `bench sequence` with Mitsuba on the GPU (seconds per frame, 8 frames), and at the end,
#       if time is left, on the CPU's LLVM variant on the same machine (6);
#   (4) `predict --sequence --ordered` on one pass through the CLI (its files listed);
#   (5) `study passes --counts 8` on the tuning set with the default options and with a
#       heavier fit that a GPU affords (HEAVY, below), then on the held-out set with the one of
#       the two whose mean 2D IoU is higher on the tuning set (chosen there, never on the
#       held-out passes).
# Every stage runs under a time limit and the script goes on after a failure; OUT_DIR gets
# summary.txt (stage lines, bench figures, the studies' summary tables) and each study's
# per_frame.csv.
#
# Usage, from the repository root:  train/gpu_sequence_check.sh [OUT_DIR]
#   (default /tmp/sq-gpu-sequence). Without mitsuba installed it unpacks .gpu/site-cpXY.tar.xz
#   (train/gpu_bundle.sh builds it). Environment: MODELS [12] passes per set, WORKERS [8],
#   HEAVY (the heavier fit's --set options), TOTAL_SECONDS [540] (the whole script's time; a
#   stage with under 10 s left is skipped), PYTHON [python3], WORK (folder kept for the data;
#   default temporary). A dry run on a machine without a GPU (Mitsuba then on LLVM):
#   MODELS=1 WORKERS=1 train/gpu_sequence_check.sh /tmp/dry
set -u -o pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
source "$repo/train/gpu_stages.sh" sq-gpu-sequence "${1:-}"
models=${MODELS:-12}
workers=${WORKERS:-8}
# A heavier joint fit: twice the steps and the patience, finer meshes and masks (each tried
# alone on 2 cores: eval/experiments/README.md, "Passes"). The first run (2026-11-30) also grew
# up to three primitives (sequence.grow=3): the tuning set's outlines no nearer, its shape
# further, so the setting offered leaves them out.
heavy=${HEAVY:-sequence.steps=120 sequence.patience=24 sequence.level=2 sequence.resolution=128}
sq=("$py" -m sq_mitsuba)

source "$repo/train/gpu_site.sh" gpu_sequence_check
export PYTHONPATH=$repo${PYTHONPATH:+:$PYTHONPATH}
cd "$repo" || exit 2
nvidia-smi -L 2>&1 | tee -a "$summary"
note "cores $(nproc)"

# 1. The variant (CUDA preferred when Dr.Jit's backend works) and the silhouette self-test.
stage doctor 120 "${sq[@]}" doctor --render 2>&1 | tee "$work/doctor.txt"
grep -E "variant|device|silhouette" "$work/doctor.txt" >> "$summary"

# 2. The two sets of passes.
make_passes() {  # NAME FAMILIES SEED
  local name=$1 families=$2 seed=$3
  stage "models-$name" 150 "${sq[@]}" models generate --generator composed --families "$families" \
    --count "$models" --seed "$seed" --points 20000 --out "$work/${name}_models" --workers "$workers"
  # Every spacecraft of the set is scored: none is anyone's training model.
  sed -i 's/,train$/,test/; s/,val$/,test/' "$work/${name}_models/splits.csv"
  stage "passes-$name" 200 "${sq[@]}" dataset render --models "$work/${name}_models" \
    --out "$work/${name}_passes" --images-per-model 8 --pass-frames 8 --resolution 256 \
    --spp 16 --seed 7 --workers "$workers" --quiet
}
make_passes held held-out 7
make_passes tune training 77

# 3. Seconds per frame of predict_sequence, Mitsuba on the GPU (on the CPU at the end: 6).
stage bench-cuda 120 "${sq[@]}" bench sequence --repeats 3 2>&1 | tee "$work/bench_cuda.txt"
grep -E "per frame|variant|load|Measured" "$work/bench_cuda.txt" | sed 's/^/cuda: /' >> "$summary"

# 4. The CLI on one pass of the held-out set.
first=$(find "$work/held_passes" -mindepth 1 -maxdepth 1 -type d | sort | head -1)
if [ -n "$first" ]; then
  stage predict 120 "${sq[@]}" predict $(find "$first/images" -type f | sort) --sequence \
    --ordered --out "$work/predict" --quiet
  ls "$work/predict" >> "$summary" 2>&1
fi

# 5. The studies: tuning set default and heavy, then the held-out set with the better one.
study() {  # NAME DATA [--set ...]
  local name=$1 data=$2; shift 2
  stage "study-$name" 240 "${sq[@]}" study passes --data "$data" --out "$work/study_$name" \
    --counts 8 --quiet "$@"
  { echo "--- study $name"; cat "$work/study_$name/summary.md"; } >> "$summary" 2>&1
  cp "$work/study_$name/per_frame.csv" "$out/per_frame_$name.csv" 2>/dev/null
}
sets=(); for s in $heavy; do sets+=(--set "$s"); done
study tune_default "$work/tune_passes"
study tune_heavy "$work/tune_passes" "${sets[@]}"
iou() { awk -F'|' '$3 ~ /sequence/ {split($7, a, " "); print a[1]}' "$work/study_$1/summary.md" 2>/dev/null; }
default_iou=$(iou tune_default); heavy_iou=$(iou tune_heavy)
note "tuning set, sequence 2D IoU: default ${default_iou:-none}, heavy ${heavy_iou:-none}"
if [ -n "$heavy_iou" ] && [ -n "$default_iou" ] && awk "BEGIN {exit !($heavy_iou > $default_iou)}"; then
  note "chosen on the tuning set: heavy ($heavy)"
  study held_heavy "$work/held_passes" "${sets[@]}"
else
  note "chosen on the tuning set: default"
  study held_default "$work/held_passes"
fi
# 6. The same bench with Mitsuba on the CPU's LLVM variant, if time is left.
SQ_MITSUBA_VARIANT=llvm_ad_mono stage bench-llvm 150 "${sq[@]}" bench sequence --repeats 3 \
  2>&1 | tee "$work/bench_llvm.txt"
grep -E "per frame|variant|load|Measured" "$work/bench_llvm.txt" | sed 's/^/llvm: /' >> "$summary"
echo "=== summary"; cat "$summary"
