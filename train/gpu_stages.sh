# Sourced by the GPU scripts that work to a deadline (train/gpu_step_check.sh,
# train/gpu_recipe.sh, train/gpu_sequence_check.sh) as
# `source train/gpu_stages.sh NAME [OUT_DIR]`, after setting $repo. It sets what they start
# with: `absolute PATH`; $out (OUT_DIR, default /tmp/NAME) with an empty $summary
# (OUT_DIR/summary.txt) in it; $device (DEVICE, default cuda; cpu dry-runs the script); $py
# (PYTHON, default python3); $work (WORK, default a temporary folder removed at the end);
# $deadline, TOTAL_SECONDS (default 540) from now, in bash's SECONDS. Then `note` prints a
# line and keeps it in $summary, and `stage NAME LIMIT_S COMMAND...` runs COMMAND under
# `timeout`, within LIMIT_S and the deadline, skips it when under 10 s are left, and notes its
# exit status and seconds.
absolute() { case $1 in /*) echo "$1" ;; *) echo "$PWD/$1" ;; esac; }
out=$(absolute "${2:-/tmp/$1}")
device=${DEVICE:-cuda}
py=${PYTHON:-python3}
work=${WORK:+$(absolute "$WORK")}
[ -z "$work" ] && work=$(mktemp -d "/tmp/$1-work.XXXX") && trap 'rm -rf "$work"' EXIT
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
summary="$out/summary.txt"
: > "$summary"
deadline=$(( SECONDS + ${TOTAL_SECONDS:-540} ))

note() { echo "$*" | tee -a "$summary"; }
stage() {
  local name=$1 limit=$2; shift 2
  local left=$(( deadline - SECONDS ))
  [ "$limit" -gt "$left" ] && limit=$left
  if [ "$limit" -lt 10 ]; then note "stage $name skipped: out of time"; return 124; fi
  echo "=== stage $name (limit ${limit} s): $*"
  local start=$SECONDS
  timeout -k 10 "$limit" "$@"
  local rc=$?
  note "stage $name rc=$rc seconds=$((SECONDS - start))"
  return $rc
}
