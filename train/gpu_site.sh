# Sourced by the GPU check scripts (train/gpu_check.sh, train/gpu_step_check.sh): on a GPU machine
# without mitsuba, unpack the site folder that train/gpu_bundle.sh builds (.gpu/site-cpXY.tar.xz,
# or $BUNDLE) into /tmp/site and put it on PYTHONPATH. Needs $py (the Python) and $repo (the
# repository root); $1 names the calling script in the error.
if ! "$py" -c 'import mitsuba' 2>/dev/null; then
  tag=$("$py" -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')
  bundle=${BUNDLE:-$repo/.gpu/site-$tag.tar.xz}
  if [ ! -f "$bundle" ]; then
    echo "$1: mitsuba is not installed and $bundle is missing (train/gpu_bundle.sh)" >&2
    exit 2
  fi
  mkdir -p /tmp/site && tar -xJf "$bundle" -C /tmp/site
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
