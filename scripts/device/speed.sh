#!/usr/bin/env bash
# `matfit bench-speed` on a lent NVIDIA GPU (issue 48): the default fit's cold and warm times with cuda_ad_rgb.
#
#   bash scripts/device/speed.sh prepare   here: .whl/ (the wheels the device lacks, ../shared/device/pack-wheels.sh)
#                                          and .device/model (the decoder and encoders 1 and 8: what may travel)
#   bash scripts/device/speed.sh device    on the device, as the device tool's run (carry .whl and .device, with
#                                          matfit/data/model moved out of the tree for the call): $OUT/speed.md
set -uo pipefail
cd "$(dirname "$0")/../.." || exit 2
case "${1:-}" in
  prepare)
    [ -d .whl ] || { echo "error: pack the wheels first: see scripts/device/cuda.sh prepare"; exit 2; }
    mkdir -p .device/model
    for name in decoder encoder-1 encoder-8; do cp matfit/data/model/$name.json matfit/data/model/$name.msgpack .device/model/; done
    cp matfit/data/model/evaluation.json matfit/data/model/MODEL.md .device/model/
    du -sh .whl .device
    ;;
  device)
    : "${OUT:?OUT must name the folder that comes back}"
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl > "$OUT/speed.log" 2>&1
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XDG_CACHE_HOME=/tmp/matfit-cache
    nvidia-smi --query-gpu=name --format=csv,noheader >> "$OUT/speed.log" 2>&1
    python3 -c "from matfit.rendering import engine; print(engine.choose_variant(None))" >> "$OUT/speed.log" 2>&1
    timeout 480 python3 -m matfit bench-speed --model .device/model --repeats "${REPEATS:-5}" > "$OUT/speed.md" 2>> "$OUT/speed.log"
    echo "exit $?" >> "$OUT/speed.log"
    cat "$OUT/speed.md"; tail -5 "$OUT/speed.log"
    ;;
  *)
    echo "usage: bash scripts/device/speed.sh prepare|device"
    exit 2
    ;;
esac
