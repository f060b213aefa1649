"""`torch_train.py bench`: the training throughput (scene-samples/s) of model sizes × batch sizes
× variants (precision, torch.compile, host or device pipeline), a few timed optimiser steps each,
as JSON lines, a table and optionally a JSON file; no checkpoints. torch_train.py's `main` parses
the command line and imports this module only when `bench` runs.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np
import torch
from torch_device_pipeline import DeviceBatches, DeviceData
from torch_train import (
    BENCH_SIZES,
    Batches,
    Trainer,
    hardware,
    loader_pool,
    pick_device,
    to_device,
)
from torch_train_data import ExportedSplit, Run, load_run_table, parse_run
from torch_train_pick import Variant, parse_variant


def parse_size(text: str) -> tuple[str, list[str]]:
    """`LABEL` (the config's model) or `LABEL:key=value,key=value` (`--set` overrides)."""
    label, _, sets = text.partition(":")
    return label, [item for item in sets.split(",") if item]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _unique_graphs() -> int | None:
    try:
        from torch._dynamo.utils import counters

        return int(counters["stats"]["unique_graphs"])
    except Exception:  # noqa: BLE001  (a private counter: absent is fine)
        return None


def bench_case(
    run: Run,
    variant: Variant,
    device: torch.device,
    make_batches: Any,
    args: argparse.Namespace,
    row: dict[str, Any],
    fresh_compile: bool = True,
) -> dict[str, Any]:
    """Warm-up steps (compilation among them), then up to `--steps` timed optimiser steps (at
    least 3, at most `--case-secs` after those), of a seeded-initialised model. A compiled
    case compiles with the batch dimension dynamic; `fresh_compile` False reuses the graphs
    of the previous case (the same model and variant at another batch size)."""
    trainer: Trainer | None = None
    batches: Any = None
    try:
        tf32 = variant.tf32 or variant.precision == "bf16"
        torch.backends.cuda.matmul.allow_tf32 = tf32
        torch.backends.cudnn.allow_tf32 = tf32
        if variant.compile and fresh_compile:
            import torch._dynamo as dynamo

            dynamo.reset()
        trainer = Trainer(
            run,
            device,
            variant.precision,
            variant.compile,
            args.compile_mode,
            variant.compile_scope,
            variant.attention,
        )
        trainer.dynamic_batch = True
        row["parameters"] = trainer.parameter_count()
        batches = make_batches(variant.pipeline, run)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        agents: list[int] = []

        def one(step: int, first: int | None = None) -> Any:
            if variant.pipeline == "device":
                batch = batches.get(step, first=first)
                agents.append(batch["x0"].shape[1])
                return trainer.device_step(batch)[0]
            batch = to_device(batches.get(step, 1 << 40), device)
            agents.append(batch["x0"].shape[1])
            loss, grads = trainer.gradients(batch)
            trainer.apply_gradients(grads)
            return loss

        _sync(device)
        start = time.monotonic()
        warmup = args.warmup_steps + (args.compile_warmup_steps if variant.compile else 0)
        anchors: list[int | None] = [None] * warmup
        if variant.compile and variant.pipeline == "device" and batches.buckets is not None:
            # A batch from each agent-count bucket first: the recompilations for new agent
            # counts happen here, not in the timed steps.
            anchors = [int(m[0]) for m in batches.buckets.members] + anchors
            warmup = len(anchors)
        for k, first in enumerate(anchors):
            one(k, first)
        _sync(device)
        row["warmup_steps"] = warmup
        row["warmup_secs"] = round(time.monotonic() - start, 2)
        graphs = _unique_graphs()
        agents.clear()
        start = time.monotonic()
        steps = 0
        loss: Any = None
        while steps < args.steps:
            loss = one(warmup + steps)
            steps += 1
            if steps >= 3 and time.monotonic() - start > args.case_secs:
                break
        _sync(device)
        secs = time.monotonic() - start
        after = _unique_graphs()
        row.update(
            steps=steps,
            secs=round(secs, 3),
            steps_per_sec=round(steps / secs, 3),
            scene_samples_per_sec=round(steps * run.train.batch_scenes / secs, 1),
            mean_agents=round(float(np.mean(agents)), 2),
            last_loss=float(loss),
            compiled=trainer.compiled,
            compile_error=trainer.compile_error,
            graphs_compiled_while_timed=None if graphs is None else after - graphs,
        )
        if device.type == "cuda":
            row["peak_memory_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
        if args.profile_steps > 0:
            try:
                row["profile"] = profile_steps(
                    one, warmup + steps, args.profile_steps, args.profile_top, device
                )
            except torch.cuda.OutOfMemoryError:
                raise
            except Exception as e:  # noqa: BLE001  (the timing above stands without it)
                row["profile_error"] = f"{type(e).__name__}: {e}".splitlines()[0][:500]
    except torch.cuda.OutOfMemoryError:
        row["error"] = "out of memory"
    except Exception as e:  # noqa: BLE001  (one failed case must not end the bench)
        row["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:500]
    finally:
        if batches is not None:
            batches.close()
        trainer = batches = None  # the model and its batches freed before the next case
        import gc

        gc.collect()
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return row


def profile_steps(
    one: Any, first_step: int, steps: int, top: int, device: torch.device
) -> dict[str, Any]:
    """`steps` more steps under torch.profiler: where a step's time goes, the `top` operators
    by their own time on the device (on the CPU, by their own CPU time), and on a GPU the
    kernels launched per step (what launch-bound steps and fusion show in)."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        for k in range(steps):
            one(first_step + k)
        _sync(device)
    events = prof.key_averages()

    def own_us(e: Any) -> float:
        if cuda:  # named self_cuda_time_total before PyTorch 2.4
            own = getattr(e, "self_device_time_total", None)
            return float(own if own is not None else e.self_cuda_time_total)
        return float(e.self_cpu_time_total)

    total_us = sum(own_us(e) for e in events)
    ranked = sorted(events, key=own_us, reverse=True)[:top]
    out: dict[str, Any] = {
        "steps": steps,
        "by": "self device time" if cuda else "self CPU time",
        "ms_per_step": round(total_us / 1000 / steps, 3),
        "ops": [
            {
                "name": e.key,
                "ms_per_step": round(own_us(e) / 1000 / steps, 3),
                "share": round(own_us(e) / total_us, 4) if total_us > 0 else None,
                "calls_per_step": round(e.count / steps, 1),
            }
            for e in ranked
        ],
    }
    if cuda:
        out["kernels_per_step"] = round(
            sum(e.count for e in events if e.device_type == DeviceType.CUDA) / steps, 1
        )
    return out


def bench_data(
    run: Run, pipeline: str, device: torch.device, make_batches: Any, args: argparse.Namespace
) -> dict[str, Any]:
    """How fast a pipeline alone delivers batches on the device (no model)."""
    row: dict[str, Any] = {"batch_scenes": run.train.batch_scenes, "variant": f"data:{pipeline}"}
    batches = make_batches(pipeline, run)
    try:

        def one(step: int) -> None:
            if pipeline == "device":
                batches.get(step)
            else:
                to_device(batches.get(step, 1 << 40), device)

        for k in range(2):
            one(k)
        _sync(device)
        start = time.monotonic()
        n = 0
        while n < args.steps:
            one(2 + n)
            n += 1
            if n >= 3 and time.monotonic() - start > args.case_secs:
                break
        _sync(device)
        secs = time.monotonic() - start
        row.update(
            steps=n,
            secs=round(secs, 3),
            batches_per_sec=round(n / secs, 2),
            scene_samples_per_sec=round(n * run.train.batch_scenes / secs, 1),
        )
    except Exception as e:  # noqa: BLE001
        row["error"] = f"{type(e).__name__}: {e}".splitlines()[0][:500]
    finally:
        batches.close()
    return row


def bench(args: argparse.Namespace) -> None:
    """Every size × batch size × variant: scene-samples/s of training steps, as JSON lines, a
    table and (`--json`) a file rewritten after each case. Writes no checkpoint."""
    started = time.monotonic()
    variants = [parse_variant(v) for v in args.variants.split(",") if v.strip()]
    sizes = [parse_size(x) for x in (args.size or list(BENCH_SIZES))]
    batch_sizes = [int(x) for x in str(args.batch_scenes).split(",") if x.strip()]
    runs: list[tuple[str, Run]] = []
    for label, sets in sizes:
        for scenes in batch_sizes:
            table = load_run_table(args.config, args.overrides + sets)
            table.setdefault("train", {})["batch_scenes"] = scenes
            table["train"].pop("init_from", None)  # seeded initialisation: any size fits
            runs.append((label, parse_run(table, f"{args.config} with {args.overrides + sets}")))
    device = pick_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    export = args.export
    workers = args.loader_workers
    if workers < 0:
        workers = 0 if device.type == "cpu" else max(1, min(8, (os.cpu_count() or 2) - 2))
    pool = None
    if workers > 0 and any(v.pipeline == "host" for v in variants):
        pool = loader_pool(runs[0][1], export, workers)  # forked before CUDA starts
    device_data: dict[tuple[float, int], DeviceData] = {}

    def make_batches(pipeline: str, run: Run) -> Any:
        if pipeline == "device":
            key = (run.model.heading_scale, run.model.map_polylines)
            if key not in device_data:
                device_data[key] = DeviceData(
                    ExportedSplit(export / "train.safetensors"), run.model, device
                )
            return DeviceBatches(run, device_data[key])
        return Batches(run, export, workers if pool else 0, max(2, 2 * workers), pool=pool)

    header: dict[str, Any] = {
        "config": str(args.config),
        "overrides": args.overrides,
        "device": hardware(device, "").rstrip(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "loader_workers": workers if pool else 0,
        "steps": args.steps,
        "case_secs": args.case_secs,
        "compile_mode": args.compile_mode,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    rows: list[dict[str, Any]] = []

    def write() -> None:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            out = {**header, "secs": round(time.monotonic() - started, 1), "cases": rows}
            args.json.write_text(json.dumps(out, indent=1) + "\n")

    print(json.dumps(header), flush=True)
    data_done: set[tuple[str, int]] = set()
    # Eager cases first (sizes × batch sizes, the variants in the order given), compiled
    # ones (minutes of compiling) last, by size and variant, each compiled once for all batch
    # sizes: a budget cuts those.
    keyed = []
    for r, (label, run) in enumerate(runs):
        size = [x for x, _ in sizes].index(label)
        for i, v in enumerate(variants):
            keyed.append(((1, size, i, r) if v.compile else (0, r, i, 0), (label, run, v)))
    cases = [case for _, case in sorted(keyed, key=lambda k: k[0])]
    last_compiled: tuple[str, Variant] | None = None
    try:
        for label, run, variant in cases:
            scenes = run.train.batch_scenes
            for pipeline in dict.fromkeys(v.pipeline for v in variants):
                if args.data_rows and (pipeline, scenes) not in data_done:
                    data_done.add((pipeline, scenes))
                    row = bench_data(run, pipeline, device, make_batches, args)
                    print(json.dumps(row), flush=True)
                    rows.append(row)
                    write()
            row = {
                "size": label,
                "batch_scenes": scenes,
                "variant": variant.label,
                "precision": variant.precision,
                "compile": variant.compile,
                "pipeline": variant.pipeline,
            }
            if args.budget_secs and time.monotonic() - started > args.budget_secs:
                row["skipped"] = f"past --budget-secs {args.budget_secs}"
            else:
                fresh = (label, variant) != last_compiled
                bench_case(run, variant, device, make_batches, args, row, fresh)
                if variant.compile:
                    last_compiled = (label, variant)
            print(json.dumps(row), flush=True)
            rows.append(row)
            write()
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    print(f"\n{header['device']}; {time.monotonic() - started:.0f} s")
    print(
        f"{'size':<10} {'params':>9} {'batch':>6} {'variant':<28} {'samples/s':>10} "
        f"{'warm-up s':>9} {'peak GiB':>8}  note"
    )
    for r in rows:
        note = r.get("error") or r.get("skipped") or ""
        if r.get("compile") and r.get("compiled") is False:
            note = note or f"compile fell back: {r.get('compile_error')}"
        print(
            f"{r.get('size', ''):<10} {r.get('parameters', ''):>9} {r['batch_scenes']:>6} "
            f"{r['variant']:<28} {r.get('scene_samples_per_sec', ''):>10} "
            f"{r.get('warmup_secs', ''):>9} {r.get('peak_memory_gib', ''):>8}  {note}"
        )
    write()
