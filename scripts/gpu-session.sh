#!/usr/bin/env bash
# One call of a lent GPU machine that does both jobs of a lend, in order (docs/lent-gpu.md,
# "A lent session in one call"): the GPU engine's suite (self-test, engine, serving), then
# the PyTorch trainer's throughput, then training the large checkpoint until the deadline,
# validated and saved, so that the next lend resumes it. At most 8 files of 16 MiB come back
# from a lent machine: steps.txt, train.log, results.tar (the suite's and the bench's JSON),
# the run's tar and its training state in 15 MiB parts (see the end of this script).
#
#   bash scripts/gpu-session.sh [--budget-secs S] [--from DIR] [--config CONFIG]
#                               [--train-bench-secs S] [--no-suite] [--quick]
#                               [-- torch_train.py train options]
#
#   --budget-secs S   the whole command's wall clock (default 540: a device call may run 600)
#   --from DIR        the previous lend's run folder (its tar unpacked and its state parts
#                     joined here), carried
#   --config CONFIG   the run to train (default configs/road20-large.toml)
#   --train-bench-secs S   the trainer's throughput bench (default 150; 0 skips it): the
#                 run's model at batches of 1024 and 2048, bf16 with batches made on the GPU
#                 (the training calls' path; 7 279 scene-samples/s at 2048 on the H200), that
#                 with fused attention (sdpa), and that with the blocks compiled (regional
#                 compilation: the whole forward did not finish compiling within 120 s on
#                 the H100); each case profiled for 3 steps (its top operators and kernels
#                 per step in the JSON)
#   --no-suite    skip the engine suite (a lend whose first call ran the whole suite:
#                 scripts/gpu-suite.sh run --budget-secs 510; this call then trains)
#   --quick       small batches, in the bench and the training (how this machine tests the
#                 procedure on lavapipe and the CPU)
#   options after `--` go to torch_train.py train (default: what the bench favours,
#                 `torch_train.py pick-options`: --precision bf16 --pipeline device, with
#                 --attention sdpa and the blocks compiled where each measured ≥ 5 % faster at
#                 the run's batch, compiled ones only where they compiled within 90 s; on the
#                 H100, 2026-11-26, compiling the whole forward took the 4-minute budget)
#
# Carry: dist (bash scripts/gpu-suite.sh prepare), .gl (the Vulkan loader), the run's export
# (.road-cache/torch-large for road20-large: ROAD_TORCH_EXPORT names it) and, from the second
# lend on, the run folder given to --from. Here, on lavapipe and the CPU, the same command
# checks the procedure (`--quick --budget-secs 600`, PYTHON naming a python with torch: a few
# steps of training).
set -euo pipefail
cd "$(dirname "$0")/.."
started=$(date +%s)

budget=540
from=""
config=configs/road20-large.toml
bench_secs=150
quick=()
suite=true
train_options=(--precision bf16 --pipeline device)
picked=false  # options given after `--`: train with those, whatever the bench says
while [ $# -gt 0 ]; do
    case "$1" in
    --budget-secs) budget=$2; shift 2 ;;
    --from) from=$2; shift 2 ;;
    --config) config=$2; shift 2 ;;
    --train-bench-secs) bench_secs=$2; shift 2 ;;
    --quick) quick=(--quick); shift ;;
    --no-suite) suite=false; shift ;;
    --) shift; train_options=("$@"); picked=true; break ;;
    *) sed -n '2,/^set -euo/p' "$0" | sed '$d' >&2; exit 2 ;;
    esac
done
out="${OUT:-gpu-session-out}"
mkdir -p "$out"
run=$(basename "$config" .toml)
export ROAD_TORCH_EXPORT=${ROAD_TORCH_EXPORT:-.road-cache/torch-large}
left() { echo $((started + budget - $(date +%s))); }

# 1. The engine suite: self-test, engine (GPU settings side by side), profile, serving.
if $suite; then
    OUT="$out" bash scripts/gpu-suite.sh run --engine-only ${quick[@]+"${quick[@]}"} \
        || echo "suite: exit $?" >>"$out/steps.txt"
fi

# 2. The trainer's throughput: a few timed steps per variant, no checkpoint.
if [ "$bench_secs" -gt 0 ] && [ "$(left)" -gt $((bench_secs + 120)) ]; then
    start=$(date +%s)
    rc=0
    batches=1024,2048
    [ ${#quick[@]} -gt 0 ] && batches=8
    timeout $((bench_secs + 30)) bash scripts/gpu-train.sh bench "$config" --size base \
        --batch-scenes "$batches" \
        --variants bf16+device,bf16+device+sdpa,bf16+device+sdpa+compile-blocks \
        --profile-steps 3 --json "$out/train-bench.json" --budget-secs "$bench_secs" \
        >"$out/train-bench.txt" 2>&1 || rc=$?
    echo "train-bench: exit $rc after $(($(date +%s) - start)) s" | tee -a "$out/steps.txt"
    if ! $picked && [ -f "$out/train-bench.json" ]; then
        if options=$("${PYTHON:-python3}" scripts/torch_train.py pick-options --config "$config" \
            --bench "$out/train-bench.json" 2>>"$out/steps.txt"); then
            read -r -a train_options <<<"$options"
        fi
        echo "train options: ${train_options[*]}" | tee -a "$out/steps.txt"
    fi
    # Its table is in the JSON; the text is the log, appended to the training log below.
fi

# 3. Training until the deadline (a minute kept for the tar and the transfer back).
run_dir=/tmp/gpu-session/$run
mkdir -p "$(dirname "$run_dir")"
from_args=()
if [ -n "$from" ]; then
    from_args=(--from "$from")
fi
minutes=$(python3 -c "print(max(0.0, ($(left) - 60) / 60))")
start=$(date +%s)
rc=0
{
    cat "$out/train-bench.txt" 2>/dev/null || true
    quick_train=()
    [ ${#quick[@]} -gt 0 ] && quick_train=(--set train.batch_scenes=8)
    bash scripts/gpu-train.sh "$config" "$run_dir" --minutes "$minutes" ${from_args[@]+"${from_args[@]}"} \
        ${quick_train[@]+"${quick_train[@]}"} "${train_options[@]}"
} >"$out/train.log" 2>&1 || rc=$?
rm -f "$out/train-bench.txt"
echo "train: exit $rc after $(($(date +%s) - start)) s (budget $minutes min)" | tee -a "$out/steps.txt"
# Pack for the way back (at most 8 files of at most 16 MiB): the suite's and the bench's
# results as one tar; the run's weights, config and log as another; its training state (three
# copies of the weights: 29 MB for road20-large) in parts of 15 MiB. Back here:
# `cat $run.train_state.part-* > $run/train_state.safetensors` restores it for --from.
results=()
for f in machine.txt engine.json engine-packing.json engine-f16.json engine-f16-cores.json \
    engine-profile.json serve.json serve-large.json serve-f16.json train-bench.json; do
    [ -f "$out/$f" ] && results+=("$f")
done
if [ ${#results[@]} -gt 0 ]; then
    tar -cf "$out/results.tar" -C "$out" "${results[@]}" && (cd "$out" && rm -f "${results[@]}")
fi
if [ -d "$run_dir" ]; then
    tar -cf "$out/$run.tar" --exclude train_state.safetensors -C "$(dirname "$run_dir")" "$run"
    if [ -f "$run_dir/train_state.safetensors" ]; then
        split -b 15m -d "$run_dir/train_state.safetensors" "$out/$run.train_state.part-"
    fi
fi
ls -la "$out"
