#!/bin/bash
# Issue 59's GPU measurements on a lent GPU machine (benchmarks/results/gpu.md, "Measured: an H200, 2026-11-29"),
# whose image has torch but not the project's other packages, and takes at most 64 MiB a call.
#
#   bash benchmarks/gpu_carry.sh prepare DOG_SFM_DIR   # here, with network to PyPI: .whl/ and outputs/dog_sfm
#   bash benchmarks/gpu_carry.sh run [gpu_session's arguments]   # there, carry: .whl outputs/dog_sfm
#
# prepare: the wheels the image lacks for Python 3.12 (gsplat without glm's manual; pycolmap's 38 MB wheel unpacked
# and packed again as a 22 MB tar.xz), and the dog's sfm folder. run: installs them under /tmp/site, then
# `python3 -m benchmarks.gpu_session --out $OUT --dog-sfm outputs/dog_sfm ARGS` (gsplat builds at its first call,
# about 100 s with the arch list below).
set -euo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
prepare)
  sfm="${2:?give the sfm folder of the real plush dog (an sfm cache entry)}"
  rm -rf .whl outputs/dog_sfm && mkdir -p .whl outputs
  platforms=""
  for n in 2_17 2_24 2_27 2_28 2_31 2_34 2_35; do platforms+=" --platform manylinux_${n}_x86_64"; done
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $platforms \
    -d .whl gsplat==1.5.3 pycolmap==4.2.1 kornia==0.9.0 kornia_rs==0.2.0 omegaconf==2.3.1 hydra-core==1.3.8 pycocotools
  python3 -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3
  work=$(mktemp -d)
  (cd "$work" && unzip -q "$OLDPWD"/.whl/pycolmap-*.whl && tar cf - pycolmap* | xz -T2 -7 >"$OLDPWD/.whl/pycolmap.tar.xz")
  rm .whl/pycolmap-*.whl
  mkdir "$work/gsplat" && (cd "$work/gsplat" && unzip -q "$OLDPWD"/.whl/gsplat-*.whl \
    && rm -rf gsplat/cuda/csrc/third_party/glm/doc gsplat/cuda/csrc/third_party/glm/test \
    && rm "$OLDPWD"/.whl/gsplat-*.whl && zip -q -r -9 "$OLDPWD/.whl/gsplat-1.5.3-py3-none-any.whl" .)
  rm -rf "$work"
  cp -r "$sfm" outputs/dog_sfm
  du -sh .whl outputs/dog_sfm
  ;;
run)
  shift
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
  tar xJf .whl/pycolmap.tar.xz -C /tmp/site
  export PYTHONPATH="/tmp/site:$PWD" TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  python3 -m benchmarks.gpu_session --out "$OUT" --dog-sfm outputs/dog_sfm "$@"
  ;;
*)
  sed -n 2,11p "$0" >&2
  exit 2
  ;;
esac
