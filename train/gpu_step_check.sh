#!/usr/bin/env bash
# Measure the training step on a GPU against the network alone, and check that the batch-256
# recipe learns as the batch-32 one does (issue 34). About 9 minutes on one H200; every stage
# runs under `timeout` and the script goes on after a failure.
#
#   (a) `sq-mitsuba bench train --device cuda --batch 256`: the shipped recipe's network alone
#       (forward, backward, AdamW) against its full training step, images/s each and the ratio,
#       at batch 32 and 256;
#   (b) a small dataset rendered here, then train/configs/shipped.toml at batch 32 and
#       train/configs/shipped_b256.toml at batch 256 (its square-root learning-rate scaling,
#       then linear scaling) for the same number of images seen (each a whole cosine schedule,
#       same data and seed), the validation Chamfer-L1 values and their ratios, and each run's
#       training images/s;
#   (b') the training loop itself at the large batch (batches made by the data stream), with
#       the prefetch off, on a thread and in two worker processes (data.prefetch,
#       data.prefetch_workers), median training images/s each;
#   (c) everything in OUT_DIR: summary.txt, bench_train.txt, stream.txt, log_b32.csv, ... .
#
# Usage, from the repository root:  train/gpu_step_check.sh [OUT_DIR]  (default /tmp/sq-gpu-step)
#   Without mitsuba installed it unpacks .gpu/site-cpXY.tar.xz (train/gpu_bundle.sh builds it)
#   into /tmp/site. Environment (defaults in brackets):
#   DEVICE [cuda]; cpu dry-runs the whole script with the sizes below made tiny by hand, e.g.
#     DEVICE=cpu MODELS=4 IMAGES=10 RESOLUTION=64 SPP=4 SEEN=128 BATCH_LARGE=64 REPEATS=1 \
#       train/gpu_step_check.sh /tmp/dry
#   MODELS [32], IMAGES [16] images per model (the val split takes 2 of each model's 10 or
#   more), RESOLUTION [96], SPP [16]: the dataset; DATA: an existing SPE3R-layout dataset
#   instead; SEEN [20480]: training images seen by each run; BATCH_LARGE [256]: the large
#   batch; TRAIN_SECONDS [110]: cap of each run's training (a run cut by it is reported as not
#   comparable); BENCH_SECONDS [180]; TOTAL_SECONDS [540]: every stage ends by then (the
#   script's own limit); REPEATS [10]: bench pairs; PYTHON [python3]; WORK: folder kept for
#   the dataset and runs (default temporary); STAGES ["bench dataset stream learn"].
set -u -o pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
source "$repo/train/gpu_stages.sh" sq-gpu-step "${1:-}"
stages=${STAGES:-bench dataset stream learn}
want() { [[ " $stages " == *" $1 "* ]]; }
large=${BATCH_LARGE:-256}
seen=${SEEN:-20480}
sq=("$py" -m sq_mitsuba)

source "$repo/train/gpu_site.sh" gpu_step_check
export PYTHONPATH=$repo${PYTHONPATH:+:$PYTHONPATH}
[ -n "${DATA:-}" ] && DATA=$(absolute "$DATA")
cd "$repo" || exit 2

note "gpu_step_check: device $device, batch 32 and $large, $seen images seen per run"
{ nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"; } | tee -a "$summary"
"$py" -c 'import torch, sys; print("python", sys.version.split()[0], "torch", torch.__version__,
"cuda", torch.cuda.is_available(), torch.cuda.get_device_name() if torch.cuda.is_available()
else "")' 2>&1 | tee -a "$summary"

# (a) The network alone against the full step, batch 32 and $large.
if want bench; then
  stage bench "${BENCH_SECONDS:-180}" "${sq[@]}" bench train --device "$device" --batch "$large" --step-only \
    --repeats "${REPEATS:-10}" --warmup 2 2>&1 | tee "$out/bench_train.txt"
  grep -E "headline|images/s" "$out/bench_train.txt" >> "$summary"
fi

# (b1) A small dataset, rendered here (on the GPU with the CUDA variant).
data=${DATA:-}
if [ -z "$data" ] && want dataset; then
  data=$work/dataset
  stage models 90 "${sq[@]}" models generate --count "${MODELS:-32}" --points 20000 \
    --out "$work/models" > "$work/models.txt" 2>&1
  if stage dataset 150 "${sq[@]}" dataset render --models "$work/models" --out "$data" \
      --images-per-model "${IMAGES:-16}" --resolution "${RESOLUTION:-96}" \
      --spp "${SPP:-16}" --quiet; then
    note "dataset: $(find "$data" -path '*/images/*' -type f | wc -l) images"
  else
    data=
  fi
fi

# (b1') The training loop's own images/s at the large batch, the batches made by the data
#       stream, without prefetch, with the thread and with worker processes (STREAM_MODES:
#       off, thread, or a number of workers), STREAM_STEPS steps each; each mode is its own
#       `sq-mitsuba train` process, as a user runs it (a mode that followed two others in one
#       process measured 30 % slower).
if want stream && [ -n "$data" ]; then
  read -r -a modes <<< "${STREAM_MODES:-off thread 2}"
  per_mode=$(( ${STREAM_SECONDS:-150} / ${#modes[@]} ))
  for mode in "${modes[@]}"; do
    case $mode in
      off) sets=(--set data.prefetch=false) ;;
      thread) sets=(--set data.prefetch=true --set data.prefetch_workers=0) ;;
      *) sets=(--set data.prefetch=true --set "data.prefetch_workers=$mode") ;;
    esac
    rm -rf "$work/stream_$mode"
    stage "stream_$mode" "$per_mode" "${sq[@]}" train --config train/configs/shipped_b256.toml \
      --data "$data" --out "$work/stream_$mode" --max-steps "${STREAM_STEPS:-40}" --quiet \
      --set "device=\"$device\"" --set "optim.batch_size=$large" --set validation.every=0 \
      --set "data.cache_dir=\"$work/cache\"" "${sets[@]}" > "$work/stream_$mode.txt" 2>&1
  done
  "$py" - "$work" "$large" "${modes[@]}" <<'EOF' 2>&1 | tee "$out/stream.txt"
"""Median training images/s of each mode's log.csv (past the first 3 steps: kernels' warm-up)."""
import csv
import statistics
import sys
from pathlib import Path

work, large, modes = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
rates = {}
for mode in modes:
    path = work / f"stream_{mode}" / "log.csv"
    if not path.exists():
        print(f"training loop, batch {large}, prefetch {mode}: no log (see stream_{mode}.txt)")
        continue
    log = list(csv.DictReader(path.open()))
    log = log[3:] if len(log) > 4 else log[1:]
    rates[mode] = statistics.median(float(r["images_per_s"]) for r in log)
    print(f"training loop, batch {large}, prefetch {mode}: median {rates[mode]:.1f} images/s "
          f"over {len(log)} steps")
if "off" in rates and len(rates) > 1:
    print("prefetch " + ", ".join(
        f"{'on a thread' if m == 'thread' else f'in {m} worker processes'} / off: "
        f"{rates[m] / rates['off']:.2f} x" for m in rates if m != "off"))
EOF
  grep -E "^training loop|^prefetch " "$out/stream.txt" >> "$summary"
fi

# (b2) Batch 32 against batch $large for the same images seen; (c) the summary.
if want learn && [ -n "$data" ]; then
  # Each run's training cap fits what is left (start-up, caches and validations besides).
  train_s=${TRAIN_SECONDS:-110}
  fit=$(( (deadline - SECONDS - 90) / 2 ))
  [ "$fit" -lt "$train_s" ] && train_s=$fit
  [ "$train_s" -lt 5 ] && train_s=5
  stage learn $(( 2 * train_s + 90 )) "$py" - "$data" "$work" "$out" "$device" \
      "$seen" "$large" "$train_s" <<'EOF' 2>&1 | tee "$out/learn.txt"
"""Train shipped.toml at batch 32 and shipped_b256.toml at the large batch on the same data
for the same images seen (whole cosine schedules), and compare their validation Chamfer-L1."""
import csv
import math
import shutil
import statistics
import sys
from pathlib import Path

from sq_mitsuba.config import apply_overrides
from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.train import train

data, work, out = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
device, seen, large, seconds = sys.argv[4], int(sys.argv[5]), int(sys.argv[6]), float(sys.argv[7])
available = len(Spe3rDataset(data, "train", image_size=96, num_surface=1, num_occupancy=2))
# A whole number of large batches per epoch: both runs then see exactly `seen` images (an
# epoch is ceil(images / batch) steps; with fewer images than one large batch they differ).
images = available // large * large if available >= large else available
rows = {}
# The large batch twice: the recipe's square-root learning-rate scaling, and linear scaling.
for label, config_name, batch, extra in (
        ("b32", "shipped.toml", 32, []),
        (f"b{large}", "shipped_b256.toml", large, []),
        (f"b{large}_linear", "shipped_b256.toml", large, ['optim.lr_scaling="linear"'])):
    epochs = max(1, round(seen / (math.ceil(images / batch) * batch)))
    config = apply_overrides(load_train_config(Path("train/configs") / config_name), [
        f'device="{device}"', f"optim.batch_size={batch}", f"optim.epochs={epochs}",
        f"data.train_images={images}", f"validation.every={max(1, epochs // 4)}",
        f"data.cache_dir={work / 'cache'}", *extra])
    run = work / f"run_{label}"
    shutil.rmtree(run, ignore_errors=True)
    result = train(config, data, run, progress=False, max_seconds=seconds)
    log = list(csv.DictReader((run / "log.csv").open()))
    val = list(csv.DictReader((run / "val.csv").open())) if (run / "val.csv").exists() else []
    for name in ("log.csv", "val.csv"):
        if (run / name).exists():
            shutil.copy(run / name, out / f"{name[:-4]}_{label}.csv")
    rate = statistics.median(float(r["images_per_s"]) for r in log[1:]) if len(log) > 1 \
        else float("nan")
    rows[label] = (result, val, rate, batch, config.optim.peak_lr())
    print(f"{label}: {result.steps} of {result.total_steps} steps x {batch} = "
          f"{result.steps * batch} images seen (peak lr {config.optim.peak_lr():.3g}), "
          f"median {rate:.1f} training images/s (validation excluded), "
          f"{result.train_seconds:.1f} s; val Chamfer-L1 by step: "
          + ", ".join(f"{v['step']}: {float(v['chamfer_l1']):.4f}" for v in val))
print(f"train images used {images} of {available}")
small = rows["b32"]
for label in (f"b{large}", f"b{large}_linear"):
    big = rows[label]
    if not (small[1] and big[1]):
        print(f"{label}: no validation in one of the runs: no Chamfer comparison")
        continue
    a, b = float(small[1][-1]["chamfer_l1"]), float(big[1][-1]["chamfer_l1"])
    counts = [r[0].steps * r[3] for r in (small, big)]
    complete = all(r[0].steps == r[0].total_steps for r in (small, big))
    fair = complete and counts[0] == counts[1]
    print(f"val Chamfer-L1 after {counts[0]} / {counts[1]} images seen: batch 32 {a:.4f}, "
          f"{label} (peak lr {big[4]:.3g}) {b:.4f}, ratio {b / a:.3f} (acceptance: <= 1.03)"
          + ("" if fair else " -- NOT COMPARABLE: a run was cut by the time cap or the "
             "images seen differ"))
EOF
  grep -E "^b[0-9]+(_linear)?:|^train images|^val Chamfer|no validation" "$out/learn.txt" >> "$summary"
fi

echo "=== summary"; cat "$summary"
