#!/usr/bin/env bash
# Training on a lent GPU machine, one call at a time (docs/torch-training.md): runs
# scripts/torch_train.py on CUDA (on the CPU with a warning where there is none), continuing the
# run in OUT when OUT holds its state, and stops (validated, saved) before the time budget is
# spent, so that the next call continues with the same command.
#
#   bash scripts/gpu-train.sh CONFIG OUT [--minutes M] [--from DIR] [torch_train.py train options]
#   bash scripts/gpu-train.sh bench CONFIG [torch_train.py bench options]
#
#   CONFIG   a run config, configs/<run>.toml (its train.init_from folder must be in the tree)
#   OUT      the checkpoint folder (on the lent machine: under $OUT, so that it comes back)
#   --minutes M   wall-clock budget of this call, default 8 (a device call may run 10 minutes;
#                 start-up and the last validation and checkpoint fit in the rest)
#   --from DIR    the previous call's OUT, carried back to the machine: copied to OUT first
#                 (when OUT has no state of its own), then resumed
#   other options go to torch_train.py train, e.g. --set train.batch_scenes=256, --allow-tf32,
#   and the speed options (all off by default: fp32, eager, batches made on the host):
#   --precision bf16, --compile, --pipeline device
#
#   bench    scene-samples/s of model sizes x batch sizes x variants, a few timed steps each,
#            no checkpoint: by default the config's model and a 2.4 M-parameter one, batches of
#            256 and 1024, fp32 / fp32+device / bf16+device / bf16+device+compile. On the
#            lent machine (carry .road-cache/torch):
#              bash scripts/gpu-train.sh bench configs/road20-wide5.toml --json $OUT/bench.json --budget-secs 360
#
# The machine needs the export of `road data export-torch` (.road-cache/torch, about 23 MiB:
# carry it; ROAD_TORCH_EXPORT names another folder) and python3 with torch, safetensors and
# numpy (PYTHON names another interpreter). torch.compile's caches go to
# .road-cache/torch-compile (TORCHINDUCTOR_CACHE_DIR), kept while the machine stays warm. Here,
# without a GPU, the same command trains on the CPU:
# `bash scripts/gpu-train.sh configs/road20-wide5.toml /tmp/t --minutes 2`.
set -euo pipefail
cd "$(dirname "$0")/.."

usage() {
    sed -n '2,/^set -euo/p' "$0" | sed '$d' >&2
    exit 2
}
mode=train
if [ "${1:-}" = bench ]; then
    mode=bench
    shift
    [ $# -ge 1 ] || usage
    config=$1
    out=""
    shift
else
    [ $# -ge 2 ] || usage
    config=$1
    out=$2
    shift 2
fi
minutes=8
from=""
rest=()
while [ $# -gt 0 ]; do
    case "$1" in
    --minutes)
        minutes=$2
        shift 2
        ;;
    --from)
        from=$2
        shift 2
        ;;
    *)
        rest+=("$1")
        shift
        ;;
    esac
done
python=${PYTHON:-python3}
export_dir=${ROAD_TORCH_EXPORT:-.road-cache/torch}

if [ ! -f "$config" ]; then
    echo "gpu-train: no run config $config" >&2
    exit 2
fi
for split in train validation; do
    if [ ! -f "$export_dir/$split.safetensors" ]; then
        echo "gpu-train: no $export_dir/$split.safetensors: run 'road data export-torch --config $config' and carry $export_dir" >&2
        exit 2
    fi
done
if ! "$python" -c "import torch, safetensors, numpy" 2>/dev/null; then
    echo "gpu-train: $python lacks torch, safetensors or numpy (PYTHON names another)" >&2
    exit 2
fi
if "$python" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    device=cuda
    if command -v nvidia-smi >/dev/null; then
        nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
    fi
else
    echo "gpu-train: warning: CUDA is not available: training on the CPU" >&2
    device=cpu
fi
export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-$PWD/.road-cache/torch-compile}
if [ "$mode" = bench ]; then
    set -x
    exec "$python" scripts/torch_train.py bench --config "$config" --export "$export_dir" \
        --device "$device" "${rest[@]}"
fi
if [ -n "$from" ] && [ ! -f "$out/train_state.safetensors" ]; then
    if [ ! -f "$from/train_state.safetensors" ]; then
        echo "gpu-train: --from $from holds no train_state.safetensors" >&2
        exit 2
    fi
    mkdir -p "$out"
    cp -r "$from"/. "$out"/
    echo "gpu-train: continuing the run of $from (step $(sed -n 's/^step = //p' "$out/config.toml"))"
fi
resume=()
if [ -f "$out/train_state.safetensors" ]; then
    resume=(--resume)
fi
set -x
exec "$python" scripts/torch_train.py train --config "$config" --out "$out" \
    --export "$export_dir" --device "$device" --minutes "$minutes" "${resume[@]}" "${rest[@]}"
