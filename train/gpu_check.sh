#!/usr/bin/env bash
# Check the CUDA path on a machine with an NVIDIA GPU, and measure it: Mitsuba's cuda_ad_mono
# silhouettes (doctor's self-test), a small dataset rendered on the GPU, training with the
# paper's configuration (train/configs/a.toml, reprojection through Mitsuba) on CUDA, the same
# under torchrun, the trainer's distributed path (nccl, SyncBatchNorm, DDP) through
# train/gpu_ddp_probe.py, and `sq-mitsuba bench render` on CUDA.
#
# Usage, from the repository root:  train/gpu_check.sh [OUT_DIR]     (default /tmp/sq-gpu-check)
#   Without mitsuba installed it unpacks .gpu/site-cpXY.tar.xz (train/gpu_bundle.sh builds it)
#   into /tmp/site. Environment: STEPS (training steps, default 100), MODELS and IMAGES (the
#   dataset: models, images per model; default 8 and 32), DATA (an existing SPE3R-layout
#   dataset instead), DATA_FALLBACK (a dataset to train on if rendering one fails), WORK (folder kept for the dataset and runs; default temporary), SQ_SRC (folder holding the sq_mitsuba package; default the repository),
#   PROBE_STEPS (steps of stages 4 and 5, default 8: past the first epoch's validation with
#   the default dataset), REPEATS (bench repeats, default 5), PYTHON (default python3), DEVICE (default cuda; cpu dry-runs the script). Every stage runs under a time limit and the script goes on
#   after a failure; it prints one "stage ... rc=..." line per stage and writes
#   OUT_DIR/summary.txt, the training logs (log_*.csv) and bench_render.txt.
set -u -o pipefail

absolute() { case $1 in /*) echo "$1" ;; *) echo "$PWD/$1" ;; esac; }
out=$(absolute "${1:-/tmp/sq-gpu-check}")
steps=${STEPS:-100}
device=${DEVICE:-cuda}  # DEVICE=cpu dry-runs the script on a machine without a GPU
py=${PYTHON:-python3}
repo=$(cd "$(dirname "$0")/.." && pwd)
src=$(absolute "${SQ_SRC:-$repo}")
stages=${STAGES:-doctor dataset train torchrun probe bench}
want() { [[ " $stages " == *" $1 "* ]]; }
# WORK keeps the dataset and runs (default: a temporary folder, removed at the end).
work=${WORK:+$(absolute "$WORK")}
[ -z "$work" ] && work=$(mktemp -d /tmp/sq-gpu-work.XXXX) && trap 'rm -rf "$work"' EXIT
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
summary="$out/summary.txt"
: > "$summary"

note() { echo "$*" | tee -a "$summary"; }
# stage NAME LIMIT_S COMMAND...: run, time, record the exit status.
stage() {
  local name=$1 limit=$2; shift 2
  echo "=== stage $name: $*"
  local start=$SECONDS
  timeout "$limit" "$@"
  local rc=$?
  note "stage $name rc=$rc seconds=$((SECONDS - start))"
  return $rc
}
sq=("$py" -m sq_mitsuba)  # an array: timeout runs programs, not shell functions

source "$repo/train/gpu_site.sh" gpu_check
export PYTHONPATH=$src${PYTHONPATH:+:$PYTHONPATH}
# `python -m` puts the working folder first on sys.path: run from $src so that its sq_mitsuba
# is the one imported.
for var in DATA DATA_FALLBACK; do
  [ -n "${!var:-}" ] && export "$var=$(absolute "${!var}")"
done
cd "$src" || exit 2

nvidia-smi -L 2>&1 | tee -a "$summary"
"$py" -c 'import torch, sys; print("python", sys.version.split()[0], "torch", torch.__version__,
"cuda", torch.cuda.is_available(), torch.cuda.get_device_name() if torch.cuda.is_available()
else "")' 2>&1 | tee -a "$summary"
echo "libraries:"; ldconfig -p | grep -E "libcuda\.so|libnvoptix|libLLVM" || true

# 1. Mitsuba's variant and the silhouette self-test (CUDA is preferred when it works); always.
stage doctor 300 "${sq[@]}" doctor --render 2>&1 | tee "$work/doctor.txt"
if [ "$device" = cuda ] && ! grep -q "variant: cuda_ad_mono" "$work/doctor.txt"; then
  # Dr.Jit looks for libcuda.so and libnvoptix.so.1; point it at the driver's files.
  for pair in DRJIT_LIBCUDA_PATH:libcuda.so.1 DRJIT_LIBOPTIX_PATH:libnvoptix.so.1; do
    var=${pair%%:*} name=${pair#*:}
    lib=$(ldconfig -p | awk -v n="$name" '$1 == n {print $NF; exit}')
    [ -z "$lib" ] && lib=$(find /usr/local/nvidia /usr/lib /usr/lib64 -name "$name" 2>/dev/null | head -1)
    [ -n "$lib" ] && export "$var=$lib" && note "set $var=$lib"
  done
  stage doctor-retry 300 "${sq[@]}" doctor --render 2>&1 | tee "$work/doctor.txt"
fi
grep -E "variant|device|silhouette" "$work/doctor.txt" >> "$summary"

# 2. A small dataset rendered here (on the GPU when the CUDA variant runs).
data=${DATA:-}
if [ -z "$data" ] && want dataset; then
  data=$work/dataset
  stage models 300 "${sq[@]}" models generate --count "${MODELS:-8}" --points 20000 \
    --out "$work/models"
  if stage dataset 420 "${sq[@]}" dataset render --models "$work/models" --out "$data" \
      --images-per-model "${IMAGES:-32}" --resolution 128 --spp 16 --quiet; then
    images=$(find "$data" -path '*/images/*' -type f | wc -l)
    note "dataset: $images images at 128 px, spp 16"
  else
    data=
  fi
fi
if [ -z "$data" ]; then
  data=${DATA_FALLBACK:?no dataset: set DATA, or DATA_FALLBACK, or keep the dataset stage}
  note "dataset: training on $data"
fi

# train_stage NAME RUN_NAME STEPS LAUNCHER... -- EXTRA_OPTIONS...: a.toml on $device.
train_stage() {
  local name=$1 run=$work/$2 count=$3; shift 3
  local launcher=()
  while [ "$1" != -- ]; do launcher+=("$1"); shift; done
  shift
  stage "$name" 900 "${launcher[@]}" train --config "$repo/train/configs/a.toml" \
    --data "$data" --out "$run" --set "device=$device" --max-steps "$count" --quiet "$@" \
    2>&1 | tee "$work/stage.txt"
  grep "^trained\|rror" "$work/stage.txt" >> "$summary"
}

# 3. The paper's configuration (no validation: its rate is the training step's).
if want train; then
  train_stage train run_train "$steps" "${sq[@]}" -- --set validation.every=0
  cp "$work/run_train/log.csv" "$out/log_train.csv" 2>/dev/null
fi
# 4. The same under torchrun (one process), with the config's validation (every epoch).
if want torchrun; then
  train_stage torchrun run_torchrun "${PROBE_STEPS:-8}" "$py" -m torch.distributed.run \
    --standalone --nproc_per_node 1 -m sq_mitsuba --
  cp "$work/run_torchrun/val.csv" "$out/val_torchrun.csv" 2>/dev/null
fi
# 5. The trainer's distributed path in one process (nccl + gloo group, SyncBatchNorm, DDP).
if want probe; then
  train_stage ddp-probe run_probe "${PROBE_STEPS:-8}" "$py" "$repo/train/gpu_ddp_probe.py" --
  cp "$work/run_probe/log.csv" "$out/log_probe.csv" 2>/dev/null
fi
# 6. Where a training step's time goes: cProfile of PROFILE_STEPS (20) steps, top functions by own time and
# by cumulative time (CUDA work is charged to whatever waits for it).
if want profile; then
  train_stage profile run_profile "${PROFILE_STEPS:-20}" "$py" -m cProfile -o "$work/train.prof" -m sq_mitsuba -- \
    --set validation.every=0
  "$py" -c 'import pstats, sys
stats = pstats.Stats(sys.argv[1])
stats.sort_stats("tottime").print_stats(25)
stats.sort_stats("cumulative").print_stats(45)' "$work/train.prof" > "$out/profile.txt" 2>&1
fi
# 7. Silhouette renderer timings.
if want bench; then
  stage bench-render 400 "${sq[@]}" bench render --repeats "${REPEATS:-5}" --warmup 1 \
    --device "$device" 2>&1 | tee "$out/bench_render.txt"
fi

echo "=== summary"; cat "$summary"
