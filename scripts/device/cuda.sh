#!/usr/bin/env bash
# matfit on a lent NVIDIA GPU (issue 37): is cuda_ad_rgb chosen by itself, may its renders share a dataset with
# llvm_ad_rgb's, how fast does render-dataset go with 1 to 12 processes, what does `matfit fit` cost there.
#
#   bash scripts/device/cuda.sh prepare    here (libLLVM >= 19, network): .whl/ (the wheels the device lacks) and
#                                          .device/ (LLVM renders to compare with, a slim model, the example to fit)
#   bash scripts/device/cuda.sh device     on the device, as the device tool's run: installs the wheels, measures
#                                          for at most ~4 minutes, writes $OUT/cuda.json and $OUT/cuda.log
#   bash scripts/device/cuda.sh rehearse   here: every device step with llvm_ad_rgb and tiny counts (${OUT:-/tmp/cuda-rehearsal})
#
# PYTHON picks the interpreter for prepare and rehearse (default: python3).
set -uo pipefail
cd "$(dirname "$0")/../.." || exit 2
python=${PYTHON:-python3}
case "${1:-}" in
  prepare)
    if ! ls .whl/mitsuba-*.whl > /dev/null 2>&1; then
      # pack-wheels.sh writes into the git root it runs in, and its .git/info/exclude step needs a plain clone (a
      # worktree's .git is a file): it runs in an empty repository, and its .whl/ moves here (ignored: *.whl).
      scratch=$(mktemp -d) && git init -q "$scratch" && (cd "$scratch" && bash /work/shared/device/pack-wheels.sh) \
        && rm -rf .whl && mv "$scratch/.whl" .whl && rm -rf "$scratch" || { echo "error: packing the wheels failed"; exit 2; }
    fi
    "$python" scripts/device/cuda.py prepare || exit 2
    travelling=$(git ls-files -z | grep -zv '^matfit/data/model/' | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
    extra=$(du -cb .whl .device | tail -1 | cut -f1)
    echo "travels: $(( (travelling + extra) >> 20 )) MiB of 64 (tracked files less matfit/data/model, .whl, .device)"
    echo "the device run: mv matfit/data/model /tmp/matfit-model-aside, then run with carry [\".whl\", \".device\"]"
    echo "  and command 'bash scripts/device/cuda.sh device' (timeout_s 300), then mv /tmp/matfit-model-aside matfit/data/model"
    ;;
  device)
    : "${OUT:?OUT must name the folder that comes back}"
    for needed in .whl/mitsuba-*.whl .device/compare.npz; do
      [ -f "$needed" ] || { echo "error: $needed is missing: run 'bash scripts/device/cuda.sh prepare' here and carry .whl and .device" | tee "$OUT/cuda.log"; exit 2; }
    done
    {
      echo "installing $(ls .whl | tr '\n' ' ')"
      python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl 2>&1 | tail -3
    } > "$OUT/cuda.log" 2>&1
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XDG_CACHE_HOME=/tmp/matfit-cache
    python3 scripts/device/cuda.py measure "$OUT" 2>&1 | tee -a "$OUT/cuda.log" | tail -40
    ;;
  rehearse)
    out=${OUT:-/tmp/cuda-rehearsal}
    mkdir -p "$out"
    cache=$(mktemp -d)
    PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XDG_CACHE_HOME=$cache "$python" scripts/device/cuda.py measure "$out" --rehearse \
      --budget "${BUDGET:-900}" 2>&1 | tee "$out/cuda.log" | tail -40
    rm -rf "$cache"
    ;;
  *)
    echo "usage: bash scripts/device/cuda.sh prepare|device|rehearse"
    exit 2
    ;;
esac
