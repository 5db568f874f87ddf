#!/usr/bin/env bash
# One round on a GPU machine, run from the repo root with warp on PYTHONPATH (../shared/tools/gpu-wheels.sh):
# installs this checkout (and a baseline checkout, if given) into /tmp with empty kernel caches, then
#   tests: the CUDA tests (ADSEISMIC_TEST_DEVICE=cuda:0) of every propagator and gradient;
#   bench: `adseismic bench` on the GPU for the baseline and this checkout, one after the other, same scenes.
# Usage: bash benchmarks/device_round.sh tests|bench OUTDIR [BASELINE_DIR] [SCENES...]
set -uo pipefail
what=$1 out=$(realpath -m "$2") base=${3:-}
shift $(( $# < 3 ? $# : 3 ))
scenes=${*:-S600 S600x16 S4000 S3D400 E2000 E600x16}
mkdir -p "$out"
install() {  # $1 source, $2 target
  [ -d "$2/adseismic" ] || python3 -m pip install -q --no-deps --no-build-isolation --no-index --target "$2" "$1" >/dev/null
}
install . /tmp/ours
[ -n "$base" ] && install "$base" /tmp/base
site=$(echo "$PYTHONPATH" | tr ':' '\n' | grep -m1 site || echo /tmp/site)
export PYTHONUNBUFFERED=1
repo=$PWD
if [ "$what" = tests ]; then  # from the source tree (pytest puts the repo first on sys.path): link the installed layout
  ln -sfn ../kernels adseismic/kernels && ln -sfn ../data_synthetic adseismic/data_synthetic
  export WARP_CACHE_PATH=/tmp/cache_tests ADSEISMIC_TEST_DEVICE=cuda:0
  rm -rf "$WARP_CACHE_PATH"
  PYTHONPATH=$site:$repo python3 -m pytest -q -p no:cacheprovider -m "" --durations=15 \
    tests/test_propagate.py tests/test_gradient.py tests/test_elastic.py tests/test_devices.py tests/test_adjoint.py 2>&1 | tee "$out/tests.log"
else
  cd /tmp  # not the repo: the installed packages are the ones imported
  for who in ${base:+base} ours; do
    export WARP_CACHE_PATH=/tmp/cache_$who
    PYTHONPATH=$site:/tmp/$who python3 -m adseismic.cli bench --device cuda:0 --no-deepwave --scenes $scenes -o "$out/$who" -q 2>&1 | tail -40
  done
fi
