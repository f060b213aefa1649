"""`torch_train.py pick-options`: the training options a bench's measurements (`bench --json`)
favour, and the bench's variant syntax they are read in. Standard library only, so that CI,
which has no PyTorch, tests it (scripts/tests).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

PRECISIONS = ("fp32", "bf16")  # torch_train.py's `--precision` choices, a variant's precisions


@dataclass(frozen=True)
class Variant:
    """A `bench` variant, `+`-joined tokens: fp32 | bf16, compile | compile-blocks, host |
    device, tf32, sdpa."""

    label: str
    precision: str = "fp32"
    compile: bool = False
    compile_scope: str = "forward"
    pipeline: str = "host"
    tf32: bool = False
    attention: str = "explicit"


def parse_variant(text: str) -> Variant:
    fields: dict[str, Any] = {}
    for token in text.strip().split("+"):
        if token in PRECISIONS:
            fields["precision"] = token
        elif token == "compile":
            fields["compile"] = True
        elif token == "compile-blocks":
            fields["compile"] = True
            fields["compile_scope"] = "blocks"
        elif token == "sdpa":
            fields["attention"] = "sdpa"
        elif token in ("host", "device"):
            fields["pipeline"] = token
        elif token == "tf32":
            fields["tf32"] = True
        else:
            raise ValueError(
                f"bench variant `{text}`: unknown token `{token}` (fp32, bf16, compile, "
                "compile-blocks, host, device, tf32, sdpa)"
            )
    return Variant(label=text.strip(), **fields)


# What `pick-options` asks of a variant before a training call uses it instead of the baseline.
PICK_MIN_GAIN = 1.05  # scene-samples/s over the baseline's at the same batch
PICK_MAX_COMPILE_SECS = 90.0  # a compiled variant's warm-up, its compiling included


def pick_options(
    bench_json: Any, batch_scenes: int, baseline: str = "bf16+device", size: str = "base"
) -> tuple[list[str], str]:
    """The training options a bench's measurements favour (`gpu-session.sh` trains with them):
    among the variants of model `size` measured at the batch nearest `batch_scenes` that differ
    from `baseline` by `sdpa` and `compile-blocks` alone, the fastest that beats it by
    `PICK_MIN_GAIN` (compiled ones only where they compiled within `PICK_MAX_COMPILE_SECS`).
    Returns the options and a sentence saying why."""
    rows = [
        r
        for r in bench_json.get("cases", [])
        if "scene_samples_per_sec" in r and not r.get("error") and r.get("size") == size
    ]
    base = parse_variant(baseline)
    options = ["--precision", base.precision, "--pipeline", base.pipeline]
    if base.tf32:
        options.append("--allow-tf32")
    measured = sorted({int(r["batch_scenes"]) for r in rows if r["variant"] == baseline})
    if not measured:
        return options, f"no measurement of {baseline}: the baseline's options"
    batch = min(measured, key=lambda b: (abs(b - batch_scenes), b))
    at = {r["variant"]: r for r in rows if int(r["batch_scenes"]) == batch}
    base_rate = float(at[baseline]["scene_samples_per_sec"])
    best: tuple[float, Variant] | None = None
    notes = []
    for label, r in at.items():
        v = parse_variant(label)
        same_base = (v.precision, v.pipeline, v.tf32) == (base.precision, base.pipeline, base.tf32)
        if label == baseline or not same_base or (v.compile and v.compile_scope != "blocks"):
            continue
        gain = float(r["scene_samples_per_sec"]) / base_rate
        compile_secs = float(r.get("warmup_secs", 1e9))
        if v.compile and (not r.get("compiled") or compile_secs > PICK_MAX_COMPILE_SECS):
            notes.append(f"{label} {gain:.2f}× but compiled late or not at all")
            continue
        notes.append(f"{label} {gain:.2f}×")
        if gain >= PICK_MIN_GAIN and (best is None or gain > best[0]):
            best = (gain, v)
    why = f"at batch {batch}: {baseline} {base_rate:.0f} scene-samples/s; " + (
        ", ".join(notes) or "nothing else measured"
    )
    if best is None:
        return options, why + f": {baseline}'s options"
    v = best[1]
    if v.attention == "sdpa":
        options += ["--attention", "sdpa"]
    if v.compile:
        options += ["--compile", "--compile-scope", "blocks"]
    return options, why + f": {v.label}"
