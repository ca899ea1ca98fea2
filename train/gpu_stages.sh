# Sourced by the GPU scripts that work to a deadline (train/gpu_step_check.sh,
# train/gpu_recipe.sh): `note` prints a line and keeps it in $summary; `stage NAME LIMIT_S
# COMMAND...` runs COMMAND under `timeout`, within LIMIT_S and within $deadline (in bash's
# SECONDS), skips it when under 10 s are left, and notes its exit status and seconds. Needs
# $summary and $deadline set before either is called.
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
