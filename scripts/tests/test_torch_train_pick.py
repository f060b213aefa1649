"""`torch_train.py pick-options`' choice (scripts/torch_train_pick.py) on hand-written bench
JSON shaped as `bench --json` writes it; no PyTorch needed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

SCRIPTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(SCRIPTS))

from torch_train_pick import (  # noqa: E402
    PICK_MAX_COMPILE_SECS,
    PICK_MIN_GAIN,
    Variant,
    parse_variant,
    pick_options,
)

BASE = ["--precision", "bf16", "--pipeline", "device"]
SDPA = ["--attention", "sdpa"]
BLOCKS = ["--compile", "--compile-scope", "blocks"]


def case(variant: str, rate: float, batch: int = 256, size: str = "base", **extra: Any) -> dict:
    """One case row as `bench` writes it (a compiled one with `compiled` and `warmup_secs`)."""
    v = parse_variant(variant)
    row: dict[str, Any] = {
        "size": size,
        "batch_scenes": batch,
        "variant": variant,
        "precision": v.precision,
        "compile": v.compile,
        "pipeline": v.pipeline,
        "parameters": 3_100_000,
        "scene_samples_per_sec": rate,
        "warmup_secs": 4.2,
        "compiled": v.compile,
    }
    row.update(extra)
    return row


def bench(*cases: dict) -> dict:
    """A bench file: its header, the pipelines' data rows (no size, `data:` variants), cases."""
    data = [
        {"batch_scenes": 256, "variant": "data:host", "scene_samples_per_sec": 9000.0},
        {"batch_scenes": 256, "variant": "data:device", "scene_samples_per_sec": 90000.0},
    ]
    header = {"config": "configs/road20-large.toml", "steps": 20, "secs": 300.0}
    return {**header, "cases": data + list(cases)}


def test_constants_are_the_documented_thresholds() -> None:
    assert PICK_MIN_GAIN == 1.05
    assert PICK_MAX_COMPILE_SECS == 90.0


def test_parse_variant_tokens() -> None:
    assert parse_variant(" bf16+device+sdpa+compile-blocks ") == Variant(
        label="bf16+device+sdpa+compile-blocks",
        precision="bf16",
        compile=True,
        compile_scope="blocks",
        pipeline="device",
        attention="sdpa",
    )
    assert parse_variant("fp32+tf32+compile") == Variant(
        label="fp32+tf32+compile", compile=True, compile_scope="forward", tf32=True
    )
    assert parse_variant("fp32") == Variant(label="fp32")
    with pytest.raises(ValueError, match="unknown token `fp16`"):
        parse_variant("fp16+device")


def test_fastest_variant_over_the_gain_is_chosen() -> None:
    js = bench(
        case("bf16+device", 1000.0),
        case("bf16+device+sdpa", 1100.0),
        case("bf16+device+sdpa+compile-blocks", 1300.0, warmup_secs=60.0),
        case("bf16+device+compile-blocks", 1200.0, warmup_secs=55.0),
    )
    options, why = pick_options(js, 256)
    assert options == BASE + SDPA + BLOCKS
    assert why.startswith("at batch 256: bf16+device 1000 scene-samples/s; ")
    assert "bf16+device+sdpa 1.10×" in why
    assert "bf16+device+compile-blocks 1.20×" in why
    assert why.endswith(": bf16+device+sdpa+compile-blocks")


def test_each_option_alone() -> None:
    sdpa, why = pick_options(
        bench(case("bf16+device", 1000.0), case("bf16+device+sdpa", 1060.0)), 256
    )
    assert sdpa == BASE + SDPA
    assert why.endswith(": bf16+device+sdpa")
    blocks, why = pick_options(
        bench(case("bf16+device", 1000.0), case("bf16+device+compile-blocks", 1060.0)), 256
    )
    assert blocks == BASE + BLOCKS
    assert why.endswith(": bf16+device+compile-blocks")


def test_gain_under_five_percent_keeps_the_baseline() -> None:
    js = bench(
        case("bf16+device", 1000.0),
        case("bf16+device+sdpa", 1049.0),
        case("bf16+device+sdpa+compile-blocks", 1040.0, warmup_secs=30.0),
    )
    options, why = pick_options(js, 256)
    assert options == BASE
    # 1.049 shows as 1.05× but is under the minimum.
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; bf16+device+sdpa 1.05×, "
        "bf16+device+sdpa+compile-blocks 1.04×: bf16+device's options"
    )
    # Exactly the minimum gain is enough.
    options, why = pick_options(
        bench(case("bf16+device", 1000.0), case("bf16+device+sdpa", 1050.0)), 256
    )
    assert options == BASE + SDPA
    assert why.endswith(": bf16+device+sdpa")


def test_a_slower_variant_is_not_chosen() -> None:
    options, why = pick_options(
        bench(case("bf16+device", 1000.0), case("bf16+device+sdpa", 800.0)), 256
    )
    assert options == BASE
    assert "bf16+device+sdpa 0.80×" in why
    assert why.endswith(": bf16+device's options")


def test_compiled_late_or_not_at_all_is_skipped_even_if_fastest() -> None:
    late = "bf16+device+sdpa+compile-blocks"
    for extra in (
        {"warmup_secs": 91.0},  # compiled, but after more than PICK_MAX_COMPILE_SECS
        {"warmup_secs": 20.0, "compiled": False, "compile_error": "BackendCompilerFailed"},
        {"warmup_secs": None},  # no warm-up measured: treated as late
    ):
        row = case(late, 2000.0, **extra)
        if extra.get("warmup_secs") is None:
            del row["warmup_secs"]
        js = bench(case("bf16+device", 1000.0), case("bf16+device+sdpa", 1100.0), row)
        options, why = pick_options(js, 256)
        assert options == BASE + SDPA, extra
        assert f"{late} 2.00× but compiled late or not at all" in why
        assert why.startswith("at batch 256: ")
        assert why.endswith(": bf16+device+sdpa")
    # Compiled exactly at the limit counts.
    js = bench(case("bf16+device", 1000.0), case(late, 2000.0, warmup_secs=PICK_MAX_COMPILE_SECS))
    assert pick_options(js, 256)[0] == BASE + SDPA + BLOCKS


def test_a_late_compile_alone_keeps_the_baseline() -> None:
    js = bench(
        case("bf16+device", 1000.0),
        case("bf16+device+compile-blocks", 1500.0, warmup_secs=200.0),
    )
    options, why = pick_options(js, 256)
    assert options == BASE
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; bf16+device+compile-blocks 1.50× but "
        "compiled late or not at all: bf16+device's options"
    )


def test_whole_forward_compile_is_never_chosen() -> None:
    js = bench(case("bf16+device", 1000.0), case("bf16+device+compile", 3000.0, warmup_secs=10.0))
    options, why = pick_options(js, 256)
    assert options == BASE
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; nothing else measured: "
        "bf16+device's options"
    )


def test_the_batch_nearest_the_requested_one_is_measured() -> None:
    js = bench(
        case("bf16+device", 1000.0, batch=256),
        case("bf16+device+sdpa", 1200.0, batch=256),
        case("bf16+device", 3000.0, batch=1024),
        case("bf16+device+sdpa", 3030.0, batch=1024),
        case("bf16+device+compile-blocks", 3600.0, batch=1024, warmup_secs=70.0),
    )
    options, why = pick_options(js, 300)
    assert options == BASE + SDPA
    assert why.startswith("at batch 256: bf16+device 1000 scene-samples/s; bf16+device+sdpa 1.20×")
    assert "compile-blocks" not in why  # measured at 1024 only
    options, why = pick_options(js, 900)
    assert options == BASE + BLOCKS
    assert why.startswith("at batch 1024: bf16+device 3000 scene-samples/s; ")
    assert "bf16+device+sdpa 1.01×" in why
    assert why.endswith(": bf16+device+compile-blocks")
    # Halfway between: the smaller batch.
    options, why = pick_options(js, 640)
    assert options == BASE + SDPA
    assert why.startswith("at batch 256: ")
    # Past the largest measured: the largest.
    assert pick_options(js, 4096)[1].startswith("at batch 1024: ")


def test_only_batches_where_the_baseline_was_measured_count() -> None:
    js = bench(
        case("bf16+device", 1000.0, batch=256),
        case("bf16+device+sdpa", 1010.0, batch=256),
        case("bf16+device+sdpa", 5000.0, batch=1024),  # no baseline at 1024
    )
    options, why = pick_options(js, 1024)
    assert options == BASE
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; bf16+device+sdpa 1.01×: "
        "bf16+device's options"
    )


def test_no_baseline_measured() -> None:
    js = bench(case("bf16+device+sdpa", 5000.0), case("fp32", 100.0))
    assert pick_options(js, 256) == (BASE, "no measurement of bf16+device: the baseline's options")
    assert pick_options({}, 256) == (BASE, "no measurement of bf16+device: the baseline's options")
    # Its options are the baseline's own, tf32 included.
    options, why = pick_options(js, 256, baseline="fp32+host+tf32")
    assert options == ["--precision", "fp32", "--pipeline", "host", "--allow-tf32"]
    assert why == "no measurement of fp32+host+tf32: the baseline's options"


def test_baseline_with_an_error_counts_as_unmeasured() -> None:
    js = bench(
        case("bf16+device", 1000.0, batch=256),
        case("bf16+device+sdpa", 1010.0, batch=256),
        case("bf16+device", 4000.0, batch=1024, error="out of memory"),
        case("bf16+device+sdpa", 4400.0, batch=1024),
    )
    options, why = pick_options(js, 1024)
    assert options == BASE
    assert why.startswith("at batch 256: ")
    only_errors = bench(case("bf16+device", 1000.0, error="RuntimeError: boom"))
    assert pick_options(only_errors, 256) == (
        BASE,
        "no measurement of bf16+device: the baseline's options",
    )


def test_other_sizes_errors_and_skipped_rows_are_ignored() -> None:
    skipped = case("bf16+device+sdpa+compile-blocks", 0.0)
    del skipped["scene_samples_per_sec"]
    skipped["skipped"] = "past --budget-secs 360"
    js = bench(
        case("bf16+device", 1000.0),
        case("bf16+device+sdpa", 1020.0),
        case("bf16+device", 500.0, size="h192x4"),
        case("bf16+device+compile-blocks", 9000.0, size="h192x4", warmup_secs=5.0),
        case("bf16+device+compile-blocks", 9000.0, warmup_secs=5.0, error="out of memory"),
        skipped,
    )
    options, why = pick_options(js, 256)
    assert options == BASE
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; bf16+device+sdpa 1.02×: "
        "bf16+device's options"
    )
    # The other size on its own terms.
    options, why = pick_options(js, 256, size="h192x4")
    assert options == BASE + BLOCKS
    assert why == (
        "at batch 256: bf16+device 500 scene-samples/s; bf16+device+compile-blocks 18.00×: "
        "bf16+device+compile-blocks"
    )


def test_another_precision_or_pipeline_is_never_chosen() -> None:
    js = bench(
        case("bf16+device", 1000.0),
        case("fp32+device+sdpa", 5000.0),
        case("bf16+host+sdpa", 5000.0),
        case("bf16+device+tf32+sdpa", 5000.0),
        case("fp32+device", 5000.0),
        case("bf16+host", 5000.0),
        case("bf16", 5000.0),  # host by default
    )
    options, why = pick_options(js, 256)
    assert options == BASE
    assert why == (
        "at batch 256: bf16+device 1000 scene-samples/s; nothing else measured: "
        "bf16+device's options"
    )


def test_another_baseline() -> None:
    js = bench(
        case("fp32+host", 100.0),
        case("fp32+host+sdpa", 120.0),
        case("bf16+device+sdpa", 5000.0),
    )
    options, why = pick_options(js, 256, baseline="fp32+host")
    assert options == ["--precision", "fp32", "--pipeline", "host", "--attention", "sdpa"]
    assert why == (
        "at batch 256: fp32+host 100 scene-samples/s; fp32+host+sdpa 1.20×: fp32+host+sdpa"
    )


def test_imports_without_torch_or_numpy() -> None:
    code = (
        "import sys, torch_train_pick; "
        "bad = [m for m in ('torch', 'numpy') if m in sys.modules]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], cwd=SCRIPTS, check=True)
