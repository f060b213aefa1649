#!/usr/bin/env bash
# The GPU suite of issue 15 in one call, for a machine lent for minutes: adapter, kernel and
# whole-denoiser self-test, the autotuner's table, engine throughput over batch sizes, serving
# throughput. The lent
# machine has no Rust toolchain and no package registry: prepare here, carry `dist/`.
#
#   bash scripts/gpu-suite.sh prepare     # here: dist/road.gz (stripped release binary) and
#                                         # dist/validation.roadds.gz (from .road-cache)
#   bash scripts/gpu-suite.sh run [--quick] [--no-torch] [--engine-only] [--pack] [--budget-secs S]
#                                         # there (device tool: carry ["dist", ".gl"]), or here
#                                         # on lavapipe; writes $OUT (default gpu-suite-out/)
#
# `--quick` runs small batches only (how CI-sized machines and lavapipe test the script: 2.5 min
# here with --no-torch). `--no-torch` skips the Heun serving bench and PyTorch. `--engine-only`
# runs the self-test, the engine and the GPU's serving bench alone (about 2 minutes on an H100):
# what a lend measures when the kernels changed and the front end did not, leaving time to
# train (scripts/gpu-session.sh runs it so). `--pack` leaves one suite.tar in $OUT (a lent
# machine returns at most 8 files). The procedure for
# a lent machine (what to move out of the tree so that it travels, the Vulkan loader, the run
# call) is in docs/lent-gpu.md, "The GPU suite"; it ran on an H100
# on 2026-11-26 in 203 s with --no-torch, before the demo-gpu and zenoh-gpu steps were added,
# and whole on an H200 on 2026-11-30 in about 450 s (before serve-large and the split torch steps).
# Each step below has its own time limit and the suite goes on past a step that fails or
# overruns (`steps.txt` says which), so whatever finished comes back.
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
    # What travels to a lent machine is capped at 64 MiB, working tree included: carry the two
    # compressed (about 15 MB instead of 50); `run` unpacks them.
    gzip -9 -f dist/road dist/validation.roadds
    du -sh dist/*
    ;;
run)
    quick=false
    torch=true
    engine_only=false
    pack=false
    budget=0
    args=("${@:2}")
    for ((i = 0; i < ${#args[@]}; i++)); do
        case "${args[$i]}" in
        --quick) quick=true ;;
        --no-torch) torch=false ;;
        --engine-only) engine_only=true ;;
        --pack) pack=true ;;
        --budget-secs) i=$((i + 1)); budget=${args[$i]:-0} ;;
        *) echo "unknown option ${args[$i]} (run [--quick] [--no-torch] [--engine-only] [--pack] [--budget-secs S])" >&2; exit 2 ;;
        esac
    done
    # With --budget-secs, each step's limit is cut to what is left of the budget (less 20 s
    # for packing) and a step with under 20 s left is skipped, so that the suite always ends
    # by itself and packs what it has: a device call cut off at its limit packs nothing.
    suite_start=$(date +%s)
    bin="${ROAD_BIN:-dist/road}"
    out="${OUT:-gpu-suite-out}"
    mkdir -p "$out"
    for packed in dist/road.gz dist/validation.roadds.gz; do
        if [ -f "$packed" ] && [ ! -f "${packed%.gz}" ]; then
            gunzip -k "$packed"
        fi
    done
    if [ -f dist/road ]; then chmod +x dist/road; fi
    if [ ! -x "$bin" ]; then
        echo "no $bin: run 'bash scripts/gpu-suite.sh prepare' first (and carry dist/)" >&2
        exit 2
    fi
    if $quick; then
        batches=(1 8)
        scenes=(1 8)
        zenoh_scenes=(4)
        ticks=4
    else
        batches=(1 8 64 512 2048 4096)
        scenes=(1 16 128 512 1024)
        zenoh_scenes=(16 128 512 1024)
        ticks=8
    fi
    # step NAME SECS OUTPUT COMMAND...: COMMAND's standard output into OUTPUT under a time
    # limit (SECS on a lent GPU, 3 × SECS with --quick: lavapipe on 2 cores is slower than the
    # full suite on a GPU); its outcome and time go to steps.txt, and the suite goes on whatever
    # it was.
    limit_scale=1
    # finish: the cache removed and, with --pack, every file of $out in one suite.tar (a lent
    # machine returns at most 8 files; the full suite writes 16).
    finish() {
        rm -rf "$out/cache"
        if $pack; then
            (cd "$out" && tar -cf suite.tar --exclude suite.tar -- * && find . -maxdepth 1 -type f ! -name suite.tar -delete)
        fi
        ls -la "$out"
    }
    $quick && limit_scale=3
    step() {
        local name=$1 secs=$(($2 * limit_scale)) output=$3 start rc=0
        shift 3
        start=$(date +%s)
        if [ "$budget" -gt 0 ]; then
            local left=$((suite_start + budget - 20 - start))
            if [ "$left" -lt 20 ]; then
                echo "$name: skipped, $left s of the budget left" | tee -a "$out/steps.txt"
                return 0
            fi
            if [ "$left" -lt "$secs" ]; then secs=$left; fi
        fi
        timeout "$secs" "$@" > "$output" || rc=$?
        echo "$name: exit $rc after $(($(date +%s) - start)) s (limit $secs s)" | tee -a "$out/steps.txt"
    }
    {
        echo "# $(date -u +%FT%TZ) $(uname -srm)"
        command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv || true
        # A lent machine returns at most 8 files: the adapter goes with the machine.
        "$bin" gpu info
    } 2>&1 | tee "$out/machine.txt"
    # Kernels and whole denoisers against the CPU references on this adapter: nothing is timed
    # unless they agree.
    # (Into machine.txt too: a lent machine returns at most 8 files.)
    selftest=0
    "$bin" gpu selftest --checkpoints models/road20-wide4 models/road20 --precisions f32 \
        | tee -a "$out/machine.txt" || selftest=${PIPESTATUS[0]}
    if [ "$selftest" -ne 0 ]; then
        echo "selftest: exit $selftest: nothing timed" | tee -a "$out/steps.txt"
        finish
        exit "$selftest"
    fi
    # f16 in a process of its own: a driver that refuses the cooperative kernels (a panic,
    # not a mismatch) or a mismatch skips the f16 steps and stops nothing else.
    f16=true
    step selftest-f16 60 "$out/selftest-f16.txt" "$bin" gpu selftest \
        --checkpoints models/road20-wide4 models/road20 --precisions f16
    cat "$out/selftest-f16.txt" >> "$out/machine.txt" && rm -f "$out/selftest-f16.txt"
    if ! tail -1 "$out/steps.txt" | grep -q "^selftest-f16: exit 0 "; then
        f16=false
        echo "selftest-f16: failed: no f16 steps" | tee -a "$out/steps.txt"
    fi
    # The autotuner's table for this adapter (into machine.txt too), cached where every later
    # step's `road serve` and `road demo` read it (they would tune on their own otherwise).
    mkdir -p "$out/cache"
    export ROAD_GPU_TUNE_CACHE="$out/cache/gpu-tune.json"
    step tune 60 "$out/tune.txt" "$bin" gpu tune --checkpoints models/road20-wide4 models/road20
    cat "$out/tune.txt" >> "$out/machine.txt" && rm -f "$out/tune.txt"
    # Engine throughput: the WGSL engine beside the candle CPU reference, same batches.
    cp dist/validation.roadds "$out/cache/validation.roadds" 2>/dev/null \
        || cp .road-cache/validation.roadds "$out/cache/validation.roadds"
    # The candle reference takes minutes per step at thousands of scenes: timed up to 8 only
    # (the first lent run, 2026-11-26, measured it to 64: docs/experiments/2026-11-26-gpu-h100/).
    # road20 stands for every D = 64 checkpoint (the same shapes), road20-wide4 is the default.
    # The blocks as residual chains (the default since 2026-11-27: 12–13.5 dispatches an
    # evaluation) and layer by layer (38–40), each with the kernels chosen per layer (auto) beside each linear
    # variant alone (the chains run linear layers only for the first q/k/v and the map's k/v;
    # the per-polyline encoder was measured against the blocked one on 2026-11-26); then the
    # default's steps profiled kernel by kernel at two batches, compiled with and without wgpu's
    # runtime checks (a step of its own: a step cut off at its limit returns nothing).
    step engine 150 "$out/engine.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 models/road20 --batches "${batches[@]}" \
        --cpu-max-batch 8 --fusion chains layers --linear-kernels auto rowwise tiled blocked \
        --cache "$out/cache" --json
    # The chains on the wide tile (32–64 rows a workgroup, blocks of 8 × 8, weights read as
    # vec4; built 2026-11-30 for the large batches where the narrow tile lost 2.3× to layers)
    # beside the narrow tile and layers, the kernels chosen per layer: a step of its own, so
    # that the first card to run it cannot cost the engine step its rows.
    step engine-wide-chains 60 "$out/engine-wide-chains.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 models/road20 --batches "${batches[@]}" \
        --cpu-max-batch 0 --fusion chains wide-chains layers --cache "$out/cache" --json
    # 4 096 scenes of road20-wide4 padded to 23 agents pass the adapter's 2 GiB binding when
    # profiled whole (H200, 2026-11-30); packed, as the engine step runs them, they fit.
    # One scene too: its 3.6 ms a Heun step (2 evaluations of 24 dispatches, 2026-11-30) is 75 µs a
    # dispatch, far above a kernel's work there; the profile's round trip and per-kernel times say which it is.
    profile_batches=(1 512 2048)
    $quick && profile_batches=(8)
    # Scenes packed (from 128 moving scenes on a card; 2026-11-30) against one batch padded to
    # the most agents, the default kernels; `eager` packs from 2 scenes, as lavapipe does:
    # whether a card's rule should start lower.
    step engine-packing 60 "$out/engine-packing.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 models/road20 --batches "${batches[@]}" \
        --cpu-max-batch 0 --packing on eager off --cache "$out/cache" --json
    # The map's keys kept between evaluations while the anchors hold (the default since
    # 2026-11-30: a Heun step makes them once) against made every evaluation, the default
    # kernels: what the pick, the encoder and every block's map k, v cost a card.
    keys_batches=(1 8 512 4096)
    $quick && keys_batches=(1 8)
    step engine-map-keys 45 "$out/engine-map-keys.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 --batches "${keys_batches[@]}" --cpu-max-batch 0 \
        --map-keys kept remade --cache "$out/cache" --json
    # f16 (the blocks' layers on the tensor cores where cooperative matrices are offered;
    # layer by layer, as f16 runs) beside f32 layer by layer, the same run; the self-test above
    # checked it against its reference. Then `linear_f16` (the same rounding without tensor
    # cores) beside it up to 512 scenes, a step of its own: row-wise at thousands of scenes it
    # could overrun, and a step cut off returns nothing.
    $f16 && step engine-f16 90 "$out/engine-f16.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 --batches "${batches[@]}" --cpu-max-batch 0 \
        --fusion layers --precisions f32 f16 --cache "$out/cache" --json
    f16_off_batches=(1 8 64 512)
    $quick && f16_off_batches=(1 8)
    $f16 && step engine-f16-cores 60 "$out/engine-f16-cores.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 --batches "${f16_off_batches[@]}" --cpu-max-batch 0 \
        --fusion layers --precisions f16 --tensor-cores on off --cache "$out/cache" --json
    step engine-profile 120 "$out/engine-profile.json" "$bin" bench engine \
        --checkpoints models/road20-wide4 --batches "${profile_batches[@]}" --cpu-max-batch 0 \
        --linear-kernels auto --fusion chains wide-chains layers --shader-checks checked unchecked --profile \
        --cache "$out/cache" --json
    # Serving: scenes ticking through the scheduler, each engine in the same run (the GPU's
    # alone with --engine-only: the CPU column does not change with the kernels).
    serve_engines=(cpu gpu)
    $engine_only && serve_engines=(gpu)
    step serve 150 "$out/serve.json" "$bin" bench serve --checkpoint models/road20-wide4 \
        --engines "${serve_engines[@]}" --scenes "${scenes[@]}" --ticks "$ticks" \
        --cache "$out/cache" --json
    # The GPU's serving ceiling: thousands of scenes (the CPU engine takes seconds a tick there).
    $quick || step serve-large 90 "$out/serve-large.json" "$bin" bench serve \
        --checkpoint models/road20-wide4 --engines gpu --scenes 2048 4096 --ticks "$ticks" \
        --cache "$out/cache" --json
    # Serving with the f16 layers (ROAD_GPU_PRECISION), the GPU alone, up to its ceiling.
    f16_scenes=(2048 4096)
    $quick && f16_scenes=(1 8)
    $f16 && ROAD_GPU_PRECISION=f16 step serve-f16 90 "$out/serve-f16.json" "$bin" bench serve \
        --checkpoint models/road20-wide4 --engines gpu --scenes "${f16_scenes[@]}" \
        --ticks "$ticks" --cache "$out/cache" --json
    if $engine_only; then
        finish
        exit 0
    fi
    # The networked path: `road demo` served by `road serve --engine gpu` in-process over
    # loopback zenoh (60 ticks of the roundabout's script; round trips and engine time per tick).
    step demo-gpu 60 "$out/demo-gpu.txt" "$bin" demo --scripted --steps 60 --engine gpu --mcap "$out/cache/demo.mcap" \
        --gif "$out/cache/demo.gif"
    # The networked server on the GPU at scale: one zenoh client thread per scene.
    step zenoh-gpu 90 "$out/zenoh-gpu.json" "$bin" bench serve --zenoh --server-engine gpu \
        --checkpoint models/road20-wide4 --scenes "${zenoh_scenes[@]}" --ticks "$ticks" --json
    if ! $torch; then
        # A short lend: the Heun serving bench and PyTorch were measured on the first one.
        finish
        exit 0
    fi
    # The default's planner before the multistep sampler, under Heun (two evaluations per
    # step; the default samples by the multistep sampler's one: docs/results.md). The GPU
    # alone: with the CPU column as well it ran past 80 s on the H200 (2026-11-30).
    step serve-heun 80 "$out/serve-heun.json" "$bin" bench serve \
        --checkpoint models/road20-wide4 \
        --planner road20-nearfit-lanes-guarded-k20-jerk-3cm-a2-amax6-yield --engines gpu \
        --scenes "${scenes[@]}" --ticks "$ticks" --cache "$out/cache" --json
    # The PyTorch peer: the same checkpoint's forward in eager PyTorch (fp32), one denoiser
    # evaluation per call, batches as above; `torch.compile` too unless --quick.
    if python3 -c 'import torch, safetensors' 2>/dev/null; then
        device=cpu
        if python3 -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)'; then
            device=cuda
        fi
        # Eager over every batch with cuBLAS at the model's shapes (torch.json's `gemm`), then
        # `torch.compile` at two batches apart: compiling all six ran past 120 s on the H200
        # (2026-11-30; two took 75 s).
        step torch 60 /dev/null python3 scripts/torch_denoiser.py bench \
            --checkpoint models/road20-wide4 --batches "${batches[@]}" --device "$device" \
            --json-out "$out/torch.json"
        $quick || step torch-compile 150 /dev/null python3 scripts/torch_denoiser.py bench \
            --checkpoint models/road20-wide4 --batches 512 4096 --device "$device" --compile \
            --json-out "$out/torch-compile.json"
    else
        echo "torch: no PyTorch with safetensors here: no PyTorch column" | tee -a "$out/steps.txt"
    fi
    finish
    ;;
*)
    sed -n 2,12p "$0" >&2
    exit 2
    ;;
esac
