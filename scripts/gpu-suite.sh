#!/usr/bin/env bash
# The GPU suite of issue 15 in one call, for a machine lent for minutes: adapter, kernel and
# whole-denoiser self-test, engine throughput over batch sizes, serving throughput. The lent
# machine has no Rust toolchain and no package registry: prepare here, carry `dist/`.
#
#   bash scripts/gpu-suite.sh prepare        # here: dist/road (stripped release binary) and
#                                            # dist/validation.roadds (from .road-cache)
#   bash scripts/gpu-suite.sh run [--quick]  # there (device tool: carry ["dist"]), or here on
#                                            # lavapipe; writes $OUT (default gpu-suite-out/)
#
# `--quick` runs small batches only (how CI-sized machines and lavapipe test the script; it ran
# end to end on lavapipe here on 2026-11-24: selftest ok, engine.json, serve.json).
# The PyTorch eager reference of the same weights (and `torch.compile`) runs where PyTorch and
# safetensors are installed (the lent machine has them): `scripts/torch_denoiser.py bench`.
set -euo pipefail
cd "$(dirname "$0")/.."

case "${1:-}" in
prepare)
    cargo build --release --locked -j2 -p road-cli
    mkdir -p dist
    cp target/release/road dist/road
    strip dist/road
    if [ ! -f .road-cache/validation.roadds ]; then
        target/release/road data build
    fi
    cp .road-cache/validation.roadds dist/validation.roadds
    du -sh dist/*
    ;;
run)
    quick=false
    [ "${2:-}" = "--quick" ] && quick=true
    bin="${ROAD_BIN:-dist/road}"
    out="${OUT:-gpu-suite-out}"
    mkdir -p "$out"
    if [ ! -x "$bin" ]; then
        echo "no $bin: run 'bash scripts/gpu-suite.sh prepare' first (and carry dist/)" >&2
        exit 2
    fi
    if $quick; then
        batches=(1 8)
        scenes=(1 8)
        ticks=4
    else
        batches=(1 8 64 512 1024 4096)
        scenes=(1 16 128 512)
        ticks=12
    fi
    {
        echo "# $(date -u +%FT%TZ) $(uname -srm)"
        command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv || true
    } | tee "$out/machine.txt"
    "$bin" gpu info | tee "$out/gpu-info.txt"
    # Kernels and whole denoisers against the CPU references on this adapter: nothing is timed
    # unless they agree.
    "$bin" gpu selftest --checkpoints models/road20-wide4 models/road20 | tee "$out/selftest.txt"
    # Engine throughput: the WGSL engine beside the candle CPU reference, same batches.
    mkdir -p "$out/cache"
    cp dist/validation.roadds "$out/cache/validation.roadds" 2>/dev/null \
        || cp .road-cache/validation.roadds "$out/cache/validation.roadds"
    "$bin" bench engine --checkpoints models/road20 models/road20-long2 models/road20-wide4 \
        --batches "${batches[@]}" --cache "$out/cache" --json > "$out/engine.json"
    # Serving: scenes ticking through the scheduler, each engine in the same run.
    "$bin" bench serve --checkpoint models/road20-wide4 --engines cpu gpu \
        --scenes "${scenes[@]}" --ticks "$ticks" --cache "$out/cache" --json > "$out/serve.json"
    # The same under the multistep sampler (one evaluation per step; docs/results.md).
    "$bin" bench serve --checkpoint models/road20-wide4 --planner road20-nearfit-lanes-guarded-k20-2m \
        --engines cpu gpu --scenes "${scenes[@]}" --ticks "$ticks" --cache "$out/cache" --json \
        > "$out/serve-multistep.json"
    rm -rf "$out/cache"
    # The PyTorch peer: the same checkpoint's forward in eager PyTorch (fp32), one denoiser
    # evaluation per call, batches as above; `torch.compile` too unless --quick.
    if python3 -c 'import torch, safetensors' 2>/dev/null; then
        device=cpu
        if python3 -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)'; then
            device=cuda
        fi
        compile=(--compile)
        $quick && compile=()
        python3 scripts/torch_denoiser.py bench --checkpoint models/road20-wide4 \
            --batches "${batches[@]}" --device "$device" "${compile[@]}" \
            --json-out "$out/torch.json" | tee "$out/torch.txt"
    else
        echo "no PyTorch with safetensors here: no PyTorch column" | tee "$out/torch.txt"
    fi
    ls -la "$out"
    ;;
*)
    sed -n 2,12p "$0" >&2
    exit 2
    ;;
esac
