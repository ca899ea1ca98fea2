#!/usr/bin/env bash
# Does the network fit the spacecraft it trained on? Its reading of images it was trained on,
# scored like the test split: a folder of links to some training models of a dataset (their
# images included), all marked "test", then `sq-mitsuba eval` on it. If the network reads
# its own training images no better than unseen families, the gap to the targets is one of
# fitting, not of generalising.
#
#   eval/experiments/training_fit.sh DATA CHECKPOINT OUT [PREFIX:COUNT[:STEP] ...] [-- EVAL_ARGS ...]
#
# DATA: a dataset folder (SPE3R layout, splits.csv); CHECKPOINT: the network; OUT: the eval
# folder (the links go to OUT.data). PREFIX:COUNT picks COUNT training models whose names
# start with PREFIX, spread evenly over them; PREFIX:COUNT:STEP every STEP-th of them from the
# first (default cs:60:30 pg:40:20, the model card's: compositional models and part graphs).
# 300 images at most are scored, spread evenly; arguments after -- go to `sq-mitsuba eval`
# (e.g. --no-baseline for a checkpoint that stores no baseline).
set -euo pipefail
[ $# -ge 3 ] || { echo "usage: $0 DATA CHECKPOINT OUT [PREFIX:COUNT[:STEP] ...] [-- EVAL_ARGS ...]" >&2
  exit 2; }
DATA=$(realpath "$1"); CHECKPOINT=$2; OUT=$3; shift 3
PICKS=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do PICKS+=("$1"); shift; done
[ $# -gt 0 ] && shift  # the --
[ ${#PICKS[@]} -gt 0 ] || PICKS=(cs:60:30 pg:40:20)
SQ=${SQ:-sq-mitsuba}
[ -f "$DATA/splits.csv" ] || { echo "$DATA: no splits.csv (not a dataset folder)" >&2; exit 2; }
# Pick every model first, so that a bad pick fails before anything is written.
CHOSEN=()
for pick in "${PICKS[@]}"; do
  IFS=: read -r prefix count step <<< "$pick"
  [[ $count =~ ^[1-9][0-9]*$ && ${step:-1} =~ ^[1-9][0-9]*$ ]] || {
    echo "$pick: expected PREFIX:COUNT or PREFIX:COUNT:STEP, COUNT and STEP >= 1" >&2; exit 2; }
  mapfile -t names < <(awk -F, -v p="$prefix" '$2 == "train" && index($1, p) == 1 {print $1}' \
    "$DATA/splits.csv")
  span=$(( step ? (count - 1) * step + 1 : count ))
  [ ${#names[@]} -ge "$span" ] || { echo "$DATA: only ${#names[@]} training models start with" \
    "'$prefix', asked for $count${step:+ every $step}" >&2; exit 2; }
  for ((i = 0; i < count; i++)); do
    CHOSEN+=("${names[$(( step ? i * step : i * ${#names[@]} / count ))]}")
  done
done
LINKS=$OUT.data
rm -rf "$LINKS.tmp" && mkdir -p "$LINKS.tmp"
cp "$DATA/camera.json" "$LINKS.tmp/"
for name in "${CHOSEN[@]}"; do
  ln -s "$(realpath "$DATA/$name")" "$LINKS.tmp/$name"
  echo "$name,test" >> "$LINKS.tmp/splits.csv"
done
rm -rf "$LINKS" && mv "$LINKS.tmp" "$LINKS"
$SQ eval --checkpoint "$CHECKPOINT" --data "$LINKS" --split test --limit 300 --out "$OUT" \
  --set figures=false --quiet "$@"
