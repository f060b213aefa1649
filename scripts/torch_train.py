#!/usr/bin/env python3
"""PyTorch training of the road denoiser: `road train` (crates/road-model/src/train.rs) for a
machine with PyTorch and no Rust toolchain (a lent GPU), writing checkpoints `road` loads as
they are (docs/checkpoint.md) and resuming its own or `road train`'s.

The data is `road data export-torch`'s (docs/torch-training.md): the caches' recordings, lanelet
centre lines and window index as flat arrays, from which this script materialises the same
scene windows Rust does; with `validation_batches.safetensors` in the export it validates on
`road train`'s own fixed batches, so that both runs' validation losses compare. The math
follows train.rs, batch.rs and model.rs step by step (crop and collate, agent buckets, task σ,
the EDM loss on F, AdamW with candle's update, global-norm clipping, warm-up + cosine learning
rate, EMA); random draws come from numpy, seeded per step (exact resume), not Rust's streams.
`crates/road-model/tests/torch_train_parity.rs` checks the batches, loss, gradients and
optimiser steps against candle on a fixture this script writes.

    python scripts/torch_train.py train --config configs/road20-wide5.toml \\
        --export .road-cache/torch --out /tmp/wide5-torch --minutes 8 [--resume] \\
        [--set train.batch_scenes=256] [--device cuda]
    python scripts/torch_train.py make-train-fixture \\
        --out crates/road-model/tests/fixtures/torch_train
    python scripts/torch_train.py validate --config configs/road20-wide4.toml \\
        --checkpoint models/road20-wide4 --export .road-cache/torch
    python scripts/torch_train.py bench --config configs/road20-wide5.toml \\
        [--variants fp32,fp32+device,bf16+device,bf16+device+compile] \\
        [--batch-scenes 256,1024] [--size base] [--json OUT.json]

By default fp32 throughout, TF32 off unless `--allow-tf32`, eager, batches made by numpy on
loader processes: the parity-checked path. Off by default, for speed on a GPU: `--precision
bf16` (autocast, f32 weights, optimiser state, loss and validation), `--compile`
(torch.compile, eager again if it fails) and `--pipeline device` (the training split on the
device, batches gathered there, no step waiting for the device; other random streams).
`bench` times them.

This file holds training, validation, the parity fixture and the command line; the device
pipeline is torch_device_pipeline.py, `bench` torch_train_bench.py, `pick-options`' choice
torch_train_pick.py, and what both pipelines read (the run config, the export, the agent
buckets, the per-step random stream) torch_train_data.py.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
import tomllib
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open
from safetensors.numpy import load_file as load_numpy
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torch_denoiser as td  # noqa: E402  (the forward pass, its config parsing and names)
from torch_device_pipeline import DeviceBatches, DeviceData  # noqa: E402
from torch_train_data import (  # noqa: E402  (the run config, the export, the step stream)
    AgentBuckets,
    ConfigError,
    ExportedSplit,
    Run,
    SceneInput,
    TrainConfig,
    load_run,
    parse_run,
    step_rng,
)
from torch_train_pick import PRECISIONS, pick_options  # noqa: E402  (no torch: CI tests it)

ADAM_BETA1 = 0.9
ADAM_BETA2 = 0.999
ADAM_EPS = 1e-8
# train.rs VALIDATION_SEED: the validation draws' own seed (numpy's stream here, not Rust's).
VALIDATION_SEED = 0x005EED0F7A11
BATCHES_FORMAT = "road-torch-validation-batches"
WEIGHTS_FILE = "weights.safetensors"
TRAIN_STATE_FILE = "train_state.safetensors"
META_FILE = "config.toml"
LOG_HEADER = "step,loss,learning_rate,grad_norm,samples_per_sec,validation_loss,wall_secs"
DATA_SOURCE = "INTERACTION DR v1.0 (non-commercial licence), official validation split"


# --------------------------------------------------------------------------------------------
# Schedules: batch.rs's task profiles, train.rs's learning rate.
# --------------------------------------------------------------------------------------------


def warmup_u(k: int, f: int, tau: float) -> float:
    return min(max(k / f + tau, 0.0), 1.0)


def rolling_u(k: int, f: int, tau: float) -> float:
    return min(max((k + tau) / f, 0.0), 1.0)


def full_u(k: int, f: int, tau: float) -> float:
    return min(max(tau, 0.0), 1.0)


def learning_rate(t: TrainConfig, step: int) -> float:
    """train.rs `learning_rate`: linear warm-up, then cosine decay to the minimum."""
    if step < t.warmup_steps:
        return t.learning_rate * (step + 1) / t.warmup_steps
    span = max(t.steps - t.warmup_steps, 1)
    progress = min((step - t.warmup_steps) / span, 1.0)
    return t.min_learning_rate + 0.5 * (t.learning_rate - t.min_learning_rate) * (
        1.0 + math.cos(math.pi * progress)
    )


# --------------------------------------------------------------------------------------------
# TOML out (checkpoint config.toml: checkpoint.rs CheckpointMeta).
# --------------------------------------------------------------------------------------------


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        text = repr(v)
        return text if any(c in text for c in ".e") else text + ".0"
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def dump_toml(table: dict[str, Any], prefix: str = "") -> str:
    """Scalars first, then sub-tables as `[prefix.key]` (None values left out, as serde does)."""
    lines = [
        f"{k} = {_toml_value(v)}"
        for k, v in table.items()
        if v is not None and not isinstance(v, dict)
    ]
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in table.items():
        if isinstance(v, dict):
            name = f"{prefix}.{k}" if prefix else k
            out += f"\n[{name}]\n" + dump_toml(v, name)
    return out


# --------------------------------------------------------------------------------------------
# Tasks, draws and batches (batch.rs, train.rs sample_scenes).
# --------------------------------------------------------------------------------------------


def task_sigma_of(run: Run, warmup: bool, tau: float, u_ca: float) -> np.ndarray:
    """batch.rs `task_sigma_of`: observed slots at σ(u_ca), future slot k at σ(profile(k, F,
    τ)), each at least σ_min. `[W]` f32."""
    w, n = run.model.window_slots, run.obs_slots
    f = w - n
    profile = (warmup_u if warmup else rolling_u) if run.rolling else full_u
    e = run.edm
    obs = max(e.sigma(u_ca), e.sigma_min)
    row = [
        obs if slot < n else max(e.sigma(profile(slot - n, f, tau)), e.sigma_min)
        for slot in range(w)
    ]
    return np.array(row, dtype=np.float64).astype(np.float32)


@dataclass
class Draw:
    """The scenes of one batch with every random choice that made them (the parity fixture
    records these)."""

    inputs: list[SceneInput] = field(default_factory=list)
    sigma: list[np.ndarray] = field(default_factory=list)  # [W] each
    noise: list[np.ndarray] = field(default_factory=list)  # [A_s, W, 3] each, after the drop
    window: list[int] = field(default_factory=list)
    start: list[int] = field(default_factory=list)
    angle: list[float] = field(default_factory=list)
    tau: list[float] = field(default_factory=list)
    warmup: list[bool] = field(default_factory=list)
    u_ca: list[float] = field(default_factory=list)
    raw_noise: list[np.ndarray] = field(default_factory=list)  # [A_window, W, 3] before the drop


def sample_scenes(
    run: Run,
    ds: ExportedSplit,
    scenes: int,
    buckets: AgentBuckets | None,
    rng: np.random.Generator,
    rotate: bool,
) -> Draw:
    """train.rs `sample_scenes`: the first window uniform, the others uniform within its
    agent-count bucket; a uniform crop; an optional rotation; the task's σ; standard normal
    noise; agents absent from the crop dropped."""
    w = run.model.window_slots
    if ds.steps < w:
        raise ValueError(f"the export's windows have {ds.steps} steps, the model needs {w}")
    if len(ds) == 0:
        raise ValueError(f"the {ds.split} export has no windows")
    t = run.train
    draw = Draw()
    anchor: int | None = None
    for _ in range(scenes):
        if buckets is not None and anchor is not None:
            index = buckets.pick(anchor, rng)
        else:
            index = int(rng.integers(len(ds)))
        if anchor is None:
            anchor = index
        start = int(rng.integers(ds.steps - w + 1))
        angle = float(rng.uniform(0.0, 2.0 * math.pi)) if rotate else 0.0
        tau = float(rng.random())
        warmup = run.rolling and bool(rng.random() < t.warmup_task_prob)
        u_ca = float(rng.uniform(0.0, t.augmentation_ratio)) if t.augmentation_ratio > 0 else 0.0
        agents = int(ds.agent_counts[index])
        draw.raw_noise.append(rng.standard_normal((agents, w, 3)).astype(np.float32))
        draw.sigma.append(task_sigma_of(run, warmup, tau, u_ca))
        draw.window.append(index)
        draw.start.append(start)
        draw.angle.append(angle)
        draw.tau.append(tau)
        draw.warmup.append(warmup)
        draw.u_ca.append(u_ca)
    # Materialising draws nothing: done for the whole batch at once.
    for scene, angle, raw in zip(
        ds.scenes(draw.window, draw.start, w, run.model), draw.angle, draw.raw_noise
    ):
        if rotate:
            scene.rotate(angle, run.model.heading_scale)
        draw.noise.append(scene.drop_absent_agents(raw))
        draw.inputs.append(scene)
    return draw


BATCH_KEYS = ("x0", "x_noisy", "sigma", "valid", "agent_features", "map", "map_valid")


def collate(draw: Draw) -> dict[str, np.ndarray]:
    """batch.rs `collate`: padded to the batch's largest agent and polyline counts (at least
    1); `x_noisy = x0 + σ·ε` on every slot of a real agent (zero state where invalid)."""
    b = len(draw.inputs)
    w = draw.inputs[0].states.shape[1]
    a = max(1, max(s.states.shape[0] for s in draw.inputs))
    p = max(1, max(s.map.shape[0] for s in draw.inputs))
    q = draw.inputs[0].map.shape[1] if draw.inputs[0].map.ndim == 3 else 0
    q = max([s.map.shape[1] for s in draw.inputs if s.map.shape[0] > 0], default=q)
    out = {
        "x0": np.zeros((b, a, w, 3), np.float32),
        "x_noisy": np.zeros((b, a, w, 3), np.float32),
        "sigma": np.zeros((b, w), np.float32),
        "valid": np.zeros((b, a, w), np.float32),
        "agent_features": np.zeros((b, a, td.AGENT_FEATURES), np.float32),
        "map": np.zeros((b, p, q, 2), np.float32),
        "map_valid": np.zeros((b, p), np.float32),
    }
    for i, (s, sigma, eps) in enumerate(zip(draw.inputs, draw.sigma, draw.noise)):
        n = s.states.shape[0]
        out["sigma"][i] = sigma
        out["x0"][i, :n] = s.states
        out["x_noisy"][i, :n] = s.states + sigma[None, :, None] * eps
        out["valid"][i, :n] = s.valid
        out["agent_features"][i, :n] = s.features
        m = s.map.shape[0]
        out["map"][i, :m] = s.map
        out["map_valid"][i, :m] = 1.0
    return out


def to_device(batch: dict[str, np.ndarray], device: torch.device) -> dict[str, Tensor]:
    pin = device.type == "cuda"
    out = {}
    for k, v in batch.items():
        t = torch.from_numpy(v)
        if pin:
            t = t.pin_memory()
        out[k] = t.to(device, non_blocking=pin)
    return out


# --------------------------------------------------------------------------------------------
# The loss (model.rs edm_error_sum / edm_loss).
# --------------------------------------------------------------------------------------------


def forward_parts_of(model: td.Denoiser, batch: dict[str, Tensor]):
    """The denoiser's parts (`Denoiser.forward_parts`) on a batch's inputs."""
    return model.forward_parts(
        batch["x_noisy"],
        batch["sigma"],
        batch["valid"],
        batch["agent_features"],
        batch["map"],
        batch["map_valid"],
    )


def edm_error_sum(model: td.Denoiser, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """The squared error summed over valid agent-slots, written on F (no cancellation of
    D − x0 at small σ), and the number of values summed (3 per valid agent-slot).

    Without a reference: `λ(σ)·|D − x0|² = |F − (x0 − c_skip·x)/c_out|²`. With a
    constant-velocity reference (coefficients at σ·s): `λ(σ)·(c_out'/s)²·|F − (s·(x0 − r) −
    c_skip'·y)/c_out'|²`."""
    return error_sum_of(model.config, batch, forward_parts_of(model, batch))


def error_sum_of(
    config: td.ModelConfig, batch: dict[str, Tensor], out: td.Outputs
) -> tuple[Tensor, Tensor]:
    """`edm_error_sum` from the forward's outputs (in f32: a bf16 forward's F is widened)."""
    x0 = batch["x0"]
    valid4 = batch["valid"].unsqueeze(3)
    r = out.residual
    raw = out.raw if out.raw.dtype == torch.float32 else out.raw.float()
    if r is None:
        target = (x0 - batch["x_noisy"] * out.c_skip) / out.c_out
        err = (raw - target).square()
    else:
        y0 = (x0 - r.reference) * r.scale
        target = (y0 - r.y * r.c_skip) / r.c_out
        sd = config.sigma_data
        b, w = batch["sigma"].shape
        s2 = batch["sigma"].square().reshape(b, 1, w, 1)
        lam = (s2 + sd * sd) / (s2 * (sd * sd))  # [B, 1, W, 1]
        weight = (r.c_out / r.scale).square() * lam  # [B, A, W, 1]
        err = (raw - target).square() * weight
    err = err * valid4
    count = batch["valid"].sum() * 3.0
    return err.sum(), count


def batch_loss(model: td.Denoiser, batch: dict[str, Tensor]) -> Tensor:
    """The training loss: the error sum over the batch's value count (at least 1)."""
    error_sum, count = edm_error_sum(model, batch)
    return error_sum / count.clamp(min=1.0)


def mixed_batch_loss(
    model: td.Denoiser, batch: dict[str, Tensor], dtype: torch.dtype | None
) -> Tensor:
    """`batch_loss` with the network's forward under `torch.autocast(dtype)` (`--precision
    bf16`: products in bf16, softmax, norms and sums in f32; the weights stay f32) and the
    loss itself in f32; `dtype` None is `batch_loss`."""
    if dtype is None:
        return batch_loss(model, batch)
    with torch.autocast(device_type=batch["x0"].device.type, dtype=dtype):
        out = forward_parts_of(model, batch)
    error_sum, count = error_sum_of(model.config, batch, out)
    return error_sum / count.clamp(min=1.0)


# --------------------------------------------------------------------------------------------
# Training state: raw weights, AdamW moments, EMA (train.rs Trainer).
# --------------------------------------------------------------------------------------------


def is_residual_branch_output(name: str) -> bool:
    """train.rs `is_residual_branch_output`."""
    if not name.startswith("blocks."):
        return False
    rest = name[len("blocks.") :]
    if "." not in rest:
        return False
    tensor = rest.split(".", 1)[1]
    return tensor in {
        "time.o.weight",
        "time.o.bias",
        "agents.o.weight",
        "agents.o.bias",
        "map.o.weight",
        "map.o.bias",
        "mlp_out.weight",
        "mlp_out.bias",
    }


def seeded_init(model: td.Denoiser, seed: int) -> None:
    """model.rs `init_seeded`'s distributions (numpy's stream): linear weights Kaiming-normal
    (fan-in, ReLU gain), biases uniform ±1/√fan_in, layer norms 1 and 0, pair weights 0,
    embeddings N(0, 0.02²)."""
    rng = np.random.default_rng(seed)
    state = model.state_dict()
    with torch.no_grad():
        for name in sorted(state):
            t = state[name]
            leaf = name.rsplit(".", 2)[-2] if name.count(".") >= 1 else ""
            if name.endswith((".pair_k", ".pair_v")):
                v = np.zeros(t.shape)
            elif leaf.startswith("ln_"):
                v = np.full(t.shape, 1.0 if name.endswith(".weight") else 0.0)
            elif name.endswith(".weight"):
                v = rng.standard_normal(t.shape) * math.sqrt(2.0 / t.shape[1])
            elif name.endswith(".bias"):
                fan_in = state[name[: -len(".bias")] + ".weight"].shape[1]
                bound = 1.0 / math.sqrt(fan_in)
                v = rng.uniform(-bound, bound, t.shape)
            else:
                v = rng.standard_normal(t.shape) * 0.02
            t.copy_(torch.from_numpy(v.astype(np.float32)))


def fit_slot_embedding(weights: dict[str, Tensor], window_slots: int) -> None:
    """train.rs `fit_slot_embedding`: keep the first rows, repeat the last for new slots."""
    e = weights.get("slot_embedding")
    if e is None or e.shape[0] == window_slots:
        return
    kept = e[: min(e.shape[0], window_slots)]
    if window_slots > e.shape[0]:
        kept = torch.cat([kept, e[-1:].repeat(window_slots - e.shape[0], 1)], dim=0)
    print(f"the slot embedding of a {e.shape[0]}-slot window fitted to {window_slots} slots")
    weights["slot_embedding"] = kept


@dataclass
class Meta:
    step: int = 0
    wall_secs: float = 0.0
    untrained_validation_loss: float | None = None
    validation_loss: float | None = None


ATTENTIONS = ("explicit", "sdpa")
COMPILE_SCOPES = ("forward", "blocks")
# The layers a bf16 forward keeps in f32: the input embeddings (positions in 40 m units and
# log σ lose too much to bf16's 8-bit mantissa) and the output head; a few FLOPs in all. On
# road20-wide4's weights (6 batches of 64) bf16 everywhere shifted the loss by +0.9 to +2.3 %
# (gradient cosine to f32's 0.90–0.98); with these in f32, +0.35 to +0.8 % (0.988–0.999).
F32_LAYERS = ("embed_state", "embed_noise", "embed_agent", "embed_relative", "map_point", "head")


class F32Linear(nn.Linear):
    """A linear layer that stays f32 under autocast (`F32_LAYERS`). With a fan-in of at most 8
    (all but the head) its product is a few multiply-adds per output written out, not a matrix
    product, so that it stays f32 where TF32 is allowed too (a GPU's TF32 products round
    their inputs to 10 bits)."""

    def forward(self, x: Tensor) -> Tensor:
        with torch.autocast(device_type=x.device.type, enabled=False):
            x = x.float()
            if self.in_features > 8:
                return nn.functional.linear(x, self.weight, self.bias)
            y = self.bias + x[..., 0:1] * self.weight[:, 0]
            for k in range(1, self.in_features):
                y = y + x[..., k : k + 1] * self.weight[:, k]
            return y


class Trainer:
    """Parameters (the model's, sorted by name), AdamW moments and the EMA, on `device`.

    `precision` "bf16" runs the training forward under bf16 autocast (f32 weights, moments,
    EMA and loss); `compile` runs it (forward and loss, and so their backward) through
    `torch.compile`, falling back to eager, with a warning, if compiling raises; with
    `compile_scope` "blocks" only the transformer blocks are compiled (one graph shared by
    them all: a fraction of the compile time). `attention` "sdpa" runs the attentions
    without pair features through PyTorch's fused kernel. Validation is f32 eager with
    written-out attention either way."""

    def __init__(
        self,
        run: Run,
        device: torch.device,
        precision: str = "fp32",
        compile: bool = False,
        compile_mode: str = "default",
        compile_scope: str = "forward",
        attention: str = "explicit",
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: one of {', '.join(PRECISIONS)}")
        if compile_scope not in COMPILE_SCOPES:
            raise ValueError(
                f"compile scope {compile_scope!r}: one of {', '.join(COMPILE_SCOPES)}"
            )
        if attention not in ATTENTIONS:
            raise ValueError(f"attention {attention!r}: one of {', '.join(ATTENTIONS)}")
        self.run = run
        self.device = device
        self.precision = precision
        self.autocast_dtype = torch.bfloat16 if precision == "bf16" else None
        self.compile_mode = compile_mode if compile else None
        self.compile_error: str | None = None
        self.compile_scope = compile_scope
        self.attention = attention
        self._compiled: Any = None
        self._compiled_blocks = False
        # TF32 during validation: None leaves the flags as they are.
        self.validation_tf32: bool | None = None
        # Compile with the batch dimension dynamic as well (`bench`: one graph for every
        # batch size of a model).
        self.dynamic_batch = False
        self.model = td.Denoiser(run.model)
        seeded_init(self.model, run.train.seed)
        self.model.to(device)
        self.model.use_sdpa(attention == "sdpa")
        if self.autocast_dtype is not None:
            for name in F32_LAYERS:
                layer = getattr(self.model, name, None)
                if type(layer) is nn.Linear:
                    layer.__class__ = F32Linear  # the same parameters, an f32 forward
        named = dict(self.model.named_parameters())
        self.names = sorted(named)
        if set(self.names) != set(self.model.state_dict()):
            raise ValueError("the mirror has buffers that are not parameters")
        self.params = [named[n] for n in self.names]
        self.adam_m = [torch.zeros_like(p) for p in self.params]
        self.adam_v = [torch.zeros_like(p) for p in self.params]
        self.ema = [p.detach().clone() for p in self.params]
        self.meta = Meta()
        self.ema_model = td.Denoiser(run.model).to(device).eval()
        if compile:
            self._compile(compile_mode)

    def _compile(self, mode: str) -> None:
        dtype = self.autocast_dtype
        try:
            import torch._dynamo as dynamo

            # Agent counts vary by batch (and, in `bench`, models and batch sizes by case):
            # room for the recompilations.
            dynamo.config.cache_size_limit = max(dynamo.config.cache_size_limit, 64)
            if self.compile_scope == "blocks":
                # Regional compilation: the blocks are one module class whose parameters
                # dynamo treats as inputs, so the first block's graph serves the others.
                for block in self.model.blocks:
                    block.compile(mode=mode)
                self._compiled_blocks = True
            else:
                self._compiled = torch.compile(
                    lambda model, batch: mixed_batch_loss(model, batch, dtype), mode=mode
                )
        except Exception as e:  # noqa: BLE001  (any failure: train uncompiled)
            self._compile_failed(e)

    def _compile_failed(self, e: BaseException) -> None:
        self.compile_error = " ".join(f"{type(e).__name__}: {e}".split())[:500]
        self._compiled = None
        if self._compiled_blocks:
            for block in self.model.blocks:
                block._compiled_call_impl = None  # what nn.Module.compile set: eager again
            self._compiled_blocks = False
        print(
            f"warning: torch.compile failed ({self.compile_error}); continuing uncompiled",
            file=sys.stderr,
            flush=True,
        )

    @property
    def compiled(self) -> bool:
        """Whether the training forward runs compiled (False after a fallback)."""
        return self._compiled is not None or self._compiled_blocks

    def mode(self) -> str:
        """What the training forward runs as, for the checkpoint's `hardware` line."""
        label = "bf16 autocast" if self.precision == "bf16" else "fp32"
        if torch.backends.cuda.matmul.allow_tf32 and self.device.type == "cuda":
            label += " (TF32)"
        if self.attention == "sdpa":
            label += ", SDPA attention"
        if self.compiled:
            label += ", compiled" if self.compile_scope == "forward" else ", blocks compiled"
        return label

    def _loss_backward(self, batch: dict[str, Tensor]) -> Tensor:
        """The batch loss, its gradient accumulated into the parameters' `.grad`."""
        self.model.train()
        for p in self.params:
            p.grad = None
        if self.compiled:
            try:
                if self._compiled is None:
                    return self._eager_loss_backward(batch)  # through the compiled blocks
                if hasattr(torch._dynamo, "maybe_mark_dynamic"):
                    for key in ("x0", "x_noisy", "valid", "agent_features"):
                        torch._dynamo.maybe_mark_dynamic(batch[key], 1)  # agents
                    if self.dynamic_batch:
                        for tensor in batch.values():
                            torch._dynamo.maybe_mark_dynamic(tensor, 0)
                loss = self._compiled(self.model, batch)
                loss.backward()
                return loss
            except torch.cuda.OutOfMemoryError:
                raise
            except Exception as e:  # noqa: BLE001  (any compile failure: go on eager)
                self._compile_failed(e)
                for p in self.params:
                    p.grad = None
        return self._eager_loss_backward(batch)

    def _eager_loss_backward(self, batch: dict[str, Tensor]) -> Tensor:
        if self.autocast_dtype is None:
            loss = batch_loss(self.model, batch)
        else:
            loss = mixed_batch_loss(self.model, batch, self.autocast_dtype)
        loss.backward()
        return loss

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.params)

    def initialise_from(self, checkpoint: Path) -> list[str]:
        """`train.init_from`: another checkpoint's EMA weights into the weights and the EMA;
        tensors it lacks keep their initialisation (added blocks start as the identity)."""
        path = checkpoint / WEIGHTS_FILE
        if not path.is_file():
            raise FileNotFoundError(f"train.init_from: no {WEIGHTS_FILE} in {checkpoint}")
        weights = load_file(str(path))
        fit_slot_embedding(weights, self.run.model.window_slots)
        expected = {n: tuple(p.shape) for n, p in zip(self.names, self.params)}
        problems = [f"unexpected tensor `{n}`" for n in sorted(set(weights) - set(expected))]
        problems += [
            f"tensor `{n}` has shape {list(weights[n].shape)}, the config needs {list(s)}"
            for n, s in expected.items()
            if n in weights and tuple(weights[n].shape) != s
        ]
        if problems:
            raise ValueError(f"{path}: weights do not fit the config: " + "; ".join(problems))
        fresh = []
        with torch.no_grad():
            for i, name in enumerate(self.names):
                if name in weights:
                    self.params[i].copy_(weights[name].to(torch.float32))
                    self.ema[i] = self.params[i].detach().clone()
                else:
                    fresh.append(name)
                    if is_residual_branch_output(name):
                        self.params[i].zero_()
                        self.ema[i] = self.params[i].detach().clone()
        if fresh:
            print(f"tensors {path} lacks start from their initialisation: {', '.join(fresh)}")
        return fresh

    def restore(self, out: Path) -> None:
        """`--resume`: the raw weights and moments of `train_state.safetensors`, the EMA of
        `weights.safetensors` and the step of `config.toml` (written by this script or by
        `road train`)."""
        with open(out / META_FILE, "rb") as f:
            meta = tomllib.load(f)
        saved = parse_run(meta["run"], str(out / META_FILE))
        if saved.model != self.run.model or (saved.obs_slots, saved.future_slots) != (
            self.run.obs_slots,
            self.run.future_slots,
        ):
            raise ValueError(
                f"{out / META_FILE}: the checkpoint's model or planner differs from the run's "
                "config"
            )
        state = load_file(str(out / TRAIN_STATE_FILE))
        ema = load_file(str(out / WEIGHTS_FILE))

        def get(source: dict[str, Tensor], key: str, file: str) -> Tensor:
            if key not in source:
                raise ValueError(f"{out / file}: missing tensor `{key}`")
            return source[key].to(self.device, torch.float32)

        with torch.no_grad():
            for i, name in enumerate(self.names):
                self.params[i].copy_(get(state, f"param.{name}", TRAIN_STATE_FILE))
                self.adam_m[i] = get(state, f"adam_m.{name}", TRAIN_STATE_FILE).clone()
                self.adam_v[i] = get(state, f"adam_v.{name}", TRAIN_STATE_FILE).clone()
                self.ema[i] = get(ema, name, WEIGHTS_FILE).clone()
        self.meta = Meta(
            step=int(meta["step"]),
            wall_secs=float(meta.get("wall_secs", 0.0)),
            untrained_validation_loss=meta.get("untrained_validation_loss"),
            validation_loss=meta.get("validation_loss"),
        )

    def gradients(self, batch: dict[str, Tensor]) -> tuple[float, list[Tensor]]:
        """The batch loss and its gradient for every parameter (sorted names)."""
        loss = self._loss_backward(batch)
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        return float(loss.detach()), grads

    def device_step(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, float]:
        """One training step that never waits for the device (`--pipeline device`): the
        gradients, then `apply_gradients`' update in place with the clipping factor computed
        on the device. Returns the loss and the gradient norm as device scalars (read them
        later, in bulk) and the learning rate."""
        loss = self._loss_backward(batch)
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        grad_norm, lr = self.apply_gradients_on_device(grads)
        return loss.detach(), grad_norm, lr

    @torch.no_grad()
    def apply_gradients_on_device(self, grads: list[Tensor]) -> tuple[Tensor, float]:
        """`apply_gradients` without a host round trip: the same operations in the same
        order, the global norm (f64) and `min(1, clip / norm)` kept on the device, the
        weights, moments and EMA updated in place. Returns the norm (a device scalar) and the
        learning rate."""
        t = self.run.train
        norms = torch.stack(torch._foreach_norm(grads)).double()
        grad_norm = norms.square().sum().sqrt()
        clip = torch.where(
            grad_norm > t.grad_clip, t.grad_clip / grad_norm, torch.ones_like(grad_norm)
        ).float()
        lr = learning_rate(t, self.meta.step)
        step = self.meta.step + 1
        bc1 = 1.0 - ADAM_BETA1**step
        bc2 = 1.0 - ADAM_BETA2**step
        d = t.ema_decay
        g = torch._foreach_mul(grads, clip)
        torch._foreach_mul_(self.adam_m, ADAM_BETA1)
        torch._foreach_add_(self.adam_m, torch._foreach_mul(g, 1.0 - ADAM_BETA1))
        torch._foreach_mul_(self.adam_v, ADAM_BETA2)
        torch._foreach_add_(
            self.adam_v, torch._foreach_mul(torch._foreach_mul(g, g), 1.0 - ADAM_BETA2)
        )
        root = torch._foreach_sqrt(torch._foreach_div(self.adam_v, bc2))
        torch._foreach_add_(root, ADAM_EPS)
        update = torch._foreach_div(torch._foreach_div(self.adam_m, bc1), root)
        params = [p.detach() for p in self.params]
        torch._foreach_mul_(params, 1.0 - lr * t.weight_decay)
        torch._foreach_sub_(params, torch._foreach_mul(update, lr))
        torch._foreach_mul_(self.ema, d)
        torch._foreach_add_(self.ema, torch._foreach_mul(params, 1.0 - d))
        self.meta.step = step
        return grad_norm, lr

    @torch.no_grad()
    def apply_gradients(self, grads: list[Tensor]) -> tuple[float, float]:
        """train.rs `Trainer::apply_gradients`: clipping by the global norm, AdamW as candle
        (weights decayed by (1 − lr·wd), then `lr · m̂ / (√v̂ + ε)` subtracted), the EMA, the
        step. Returns the gradient norm before clipping and the learning rate."""
        t = self.run.train
        # The norm per tensor in f32, the total in f64 (train.rs sums each tensor's Σ g²).
        norms = torch.stack(torch._foreach_norm(grads)).double()
        grad_norm = math.sqrt(float(norms.square().sum()))
        clip = t.grad_clip / grad_norm if grad_norm > t.grad_clip else 1.0
        lr = learning_rate(t, self.meta.step)
        step = self.meta.step + 1
        bc1 = 1.0 - ADAM_BETA1**step
        bc2 = 1.0 - ADAM_BETA2**step
        d = t.ema_decay
        # Multi-tensor ops (a few kernels per line on CUDA, not one per parameter), in
        # train.rs' order: m = β1·m + (1 − β1)·g, v = β2·v + (1 − β2)·g², update =
        # (m / bc1) / (√(v / bc2) + ε), p = p·(1 − lr·wd) − lr·update, ema = d·ema + (1 − d)·p.
        g = torch._foreach_mul(grads, clip)
        m = torch._foreach_mul(self.adam_m, ADAM_BETA1)
        torch._foreach_add_(m, torch._foreach_mul(g, 1.0 - ADAM_BETA1))
        v = torch._foreach_mul(self.adam_v, ADAM_BETA2)
        torch._foreach_add_(v, torch._foreach_mul(torch._foreach_mul(g, g), 1.0 - ADAM_BETA2))
        root = torch._foreach_sqrt(torch._foreach_div(v, bc2))
        torch._foreach_add_(root, ADAM_EPS)
        update = torch._foreach_div(torch._foreach_div(m, bc1), root)
        new = torch._foreach_mul([p.detach() for p in self.params], 1.0 - lr * t.weight_decay)
        torch._foreach_sub_(new, torch._foreach_mul(update, lr))
        for p, n in zip(self.params, new):
            p.data = n  # the parameter takes the new tensor: no copy, any torch 2.x
        ema = torch._foreach_mul(self.ema, d)
        torch._foreach_add_(ema, torch._foreach_mul(new, 1.0 - d))
        self.ema, self.adam_m, self.adam_v = ema, m, v
        self.meta.step = step
        return grad_norm, lr

    def load_ema_model(self) -> td.Denoiser:
        with torch.no_grad():
            for name, p in self.ema_model.named_parameters():
                p.copy_(self.ema[self.names.index(name)])
        return self.ema_model

    @torch.no_grad()
    def validate(self, batches: list[dict[str, Tensor]]) -> float:
        """Mean loss of the EMA weights over the fixed validation batches (train.rs
        `validate`: each batch's error sum over its count, averaged over batches)."""
        model = self.load_ema_model()
        flags = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
        if self.validation_tf32 is not None:
            # `--precision bf16` allows TF32 for training's f32 products, not validation's.
            torch.backends.cuda.matmul.allow_tf32 = self.validation_tf32
            torch.backends.cudnn.allow_tf32 = self.validation_tf32
        try:
            total = 0.0
            for batch in batches:
                error_sum, count = edm_error_sum(model, batch)
                total += float(error_sum / count.clamp(min=1.0))
        finally:
            torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags
        loss = total / max(len(batches), 1)
        self.meta.validation_loss = loss
        return loss

    def tensors(self) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """(`weights.safetensors`: the EMA; `train_state.safetensors`: raw weights and
        moments), on the CPU."""
        cpu = lambda t: t.detach().to("cpu", torch.float32).contiguous()  # noqa: E731
        weights = {n: cpu(e) for n, e in zip(self.names, self.ema)}
        state: dict[str, Tensor] = {}
        for i, n in enumerate(self.names):
            state[f"param.{n}"] = cpu(self.params[i])
            state[f"adam_m.{n}"] = cpu(self.adam_m[i])
            state[f"adam_v.{n}"] = cpu(self.adam_v[i])
        return weights, state

    def save(self, out: Path, data: dict[str, Any], hardware: str) -> None:
        """The checkpoint folder as `road train` writes it (docs/checkpoint.md)."""
        out.mkdir(parents=True, exist_ok=True)
        weights, state = self.tensors()
        for file, tensors in ((WEIGHTS_FILE, weights), (TRAIN_STATE_FILE, state)):
            tmp = out / (file + ".tmp")
            save_file(tensors, str(tmp))
            os.replace(tmp, out / file)
        meta: dict[str, Any] = {
            "step": self.meta.step,
            "parameters": self.parameter_count(),
            "wall_secs": float(self.meta.wall_secs),
            "hardware": hardware,
            "validation_loss": self.meta.validation_loss,
            "untrained_validation_loss": self.meta.untrained_validation_loss,
            "run": self.run.table,
            "data": data,
        }
        tmp = out / (META_FILE + ".tmp")
        tmp.write_text(dump_toml(meta))
        os.replace(tmp, out / META_FILE)


# --------------------------------------------------------------------------------------------
# Validation batches.
# --------------------------------------------------------------------------------------------


def exported_validation_batches(path: Path, run: Run) -> list[dict[str, np.ndarray]] | None:
    """`road train`'s own fixed validation batches from the export, when they were written for
    this run's window, task and batch shape; None (with the reason) otherwise."""
    if not path.is_file():
        print(f"no {path.name} in the export: validating on this script's own draws")
        return None
    with safe_open(str(path), framework="numpy") as f:
        meta = f.metadata() or {}
    t = run.train
    wanted = {
        "format": BATCHES_FORMAT,
        "window_slots": str(run.model.window_slots),
        "obs_slots": str(run.obs_slots),
        "map_polylines": str(run.model.map_polylines),
        "batch_scenes": str(t.batch_scenes),
        "batches": str(t.val_batches),
    }
    floats = {
        "heading_scale": run.model.heading_scale,
        "augmentation_ratio": t.augmentation_ratio,
        "warmup_task_prob": t.warmup_task_prob,
    }
    differ = [f"{k} {meta.get(k)} ≠ {v}" for k, v in wanted.items() if meta.get(k) != v]
    differ += [
        f"{k} {meta.get(k)} ≠ {v}"
        for k, v in floats.items()
        if k not in meta or float(meta[k]) != v
    ]
    if differ:
        print(
            f"{path} was written for another run ({', '.join(differ)}): validating on this "
            "script's own draws (`road data export-torch --config` this run's config and "
            "--set overrides to use road train's)"
        )
        return None
    a = load_numpy(str(path))
    n = int(meta["batches"])
    print(f"validating on road train's {n} fixed batches of {t.batch_scenes} scenes ({path})")
    return [{k: a[f"batch{i}.{k}"] for k in BATCH_KEYS} for i in range(n)]


def own_validation_batches(run: Run, ds: ExportedSplit) -> list[dict[str, np.ndarray]]:
    """train.rs `validation_batches`' idea with numpy's stream: a fixed seed, no buckets, no
    rotation."""
    rng = np.random.default_rng(VALIDATION_SEED)
    return [
        collate(sample_scenes(run, ds, run.train.batch_scenes, None, rng, rotate=False))
        for _ in range(run.train.val_batches)
    ]


# --------------------------------------------------------------------------------------------
# Batch preparation on helper processes (the GPU machine's CPUs), deterministic per step.
# --------------------------------------------------------------------------------------------

_LOADER: dict[str, Any] = {}


def _loader_init(run: Run, export: str, helper: bool = False) -> None:
    if helper:
        torch.set_num_threads(1)  # numpy work only: leave the cores to the main process
    _LOADER["run"] = run
    _LOADER["train"] = ExportedSplit(Path(export) / "train.safetensors")
    _LOADER["buckets"] = (
        AgentBuckets(_LOADER["train"].agent_counts) if run.train.bucket_by_agents else None
    )


def _loader_batch(step: int, run: Run | None = None) -> dict[str, np.ndarray]:
    """Step `step`'s batch of `run` (default: the loader's own run)."""
    run = run or _LOADER["run"]
    draw = sample_scenes(
        run,
        _LOADER["train"],
        run.train.batch_scenes,
        _LOADER["buckets"],
        step_rng(run.train.seed, step),
        run.train.rotation_augmentation,
    )
    return collate(draw)


def loader_pool(run: Run, export: Path, workers: int) -> ProcessPoolExecutor:
    """`workers` helper processes holding the training split (forked: make it before this
    process initialises CUDA)."""
    import multiprocessing

    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("fork"),
        initializer=_loader_init,
        initargs=(run, str(export), True),
    )
    # A fork pool starts every worker on its first task: do it now, before this process
    # initialises CUDA (a forked child must not inherit a CUDA context).
    pool.submit(int).result()
    return pool


class Batches:
    """Training batches by step: inline, or `workers` processes preparing the next steps
    (or those of a shared `pool` of `loader_pool`, given each task's run: `bench`)."""

    def __init__(
        self,
        run: Run,
        export: Path,
        workers: int,
        ahead: int,
        pool: ProcessPoolExecutor | None = None,
    ) -> None:
        self.pool: ProcessPoolExecutor | None = pool
        self.shared = pool is not None
        self.run = run
        self.pending: dict[int, Future[dict[str, np.ndarray]]] = {}
        self.ahead = ahead
        if self.shared:
            pass
        elif workers > 0:
            self.pool = loader_pool(run, export, workers)
        else:
            _loader_init(run, str(export))

    def get(self, step: int, last: int) -> dict[str, np.ndarray]:
        if self.pool is None:
            return _loader_batch(step, self.run)
        for s in range(step, min(step + self.ahead, last)):
            if s not in self.pending:
                self.pending[s] = self.pool.submit(
                    _loader_batch, s, self.run if self.shared else None
                )
        return self.pending.pop(step).result()

    def close(self) -> None:
        if self.shared:
            for future in self.pending.values():
                future.cancel()
            self.pending = {}
        elif self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


# --------------------------------------------------------------------------------------------
# train
# --------------------------------------------------------------------------------------------


def pick_device(name: str) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        print("warning: CUDA is not available: training on the CPU", file=sys.stderr)
        name = "cpu"
    return torch.device(name)


def hardware(device: torch.device, mode: str = "fp32") -> str:
    """The checkpoint's `hardware` line; `mode` what the training forward ran as."""
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)}, PyTorch {torch.__version__} {mode}"
    cpu = platform.processor() or "CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {torch.get_num_threads()} threads, PyTorch {torch.__version__} {mode}"


def prepare_log(path: Path, step: int, untrained: float | None) -> None:
    """train.rs `run_until`: a resumed run drops the rows after its checkpoint; a fresh log
    starts with the header and the step-0 row of the starting validation loss."""
    if path.exists():
        lines = path.read_text().splitlines()
        kept = [lines[0]] + [
            line for line in lines[1:] if line.split(",", 1)[0].isdigit()
            and int(line.split(",", 1)[0]) <= step
        ]
        path.write_text("\n".join(kept) + "\n")
    else:
        text = LOG_HEADER + "\n"
        if untrained is not None:
            text += f"0,,,,,{untrained!r},0\n"
        path.write_text(text)


def print_progress(
    step: int,
    until: int,
    losses: list[float],
    lr: float,
    grad_norm: float,
    steps_per_sec: float,
    t: TrainConfig,
    trainer: Trainer,
) -> None:
    """The progress line of both pipelines' loops: the mean loss and the rate since the last."""
    print(
        f"step {step}/{until} loss {np.mean(losses):.4f} lr {lr:.2e} "
        f"grad {grad_norm:.3f} {steps_per_sec:.2f} steps/s {steps_per_sec * t.batch_scenes:.1f} "
        f"scene-samples/s val {trainer.meta.validation_loss}",
        flush=True,
    )


def train(args: argparse.Namespace) -> None:
    run = load_run(args.config, args.overrides)
    t = run.train
    device = pick_device(args.device)
    # bf16 runs allow TF32 for the f32 products left outside autocast (validation stays f32).
    tf32 = args.allow_tf32 or args.precision == "bf16"
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32
    if args.threads:
        torch.set_num_threads(args.threads)
    started = time.monotonic()
    deadline = started + args.minutes * 60.0 if args.minutes else None
    export = args.export
    validation_split = ExportedSplit(export / "validation.safetensors")
    out = args.out or Path("models") / run.name
    until = min(args.until_step or t.steps, t.steps)
    on_device = args.pipeline == "device"
    workers = args.loader_workers
    if workers < 0:
        workers = 0 if device.type == "cpu" else max(1, min(8, (os.cpu_count() or 2) - 2))
    batches: Batches | DeviceBatches
    if on_device:
        batches = DeviceBatches(
            run, DeviceData(ExportedSplit(export / "train.safetensors"), run.model, device)
        )
    else:
        batches = Batches(run, export, workers, ahead=max(2, 2 * workers))
    trainer = Trainer(
        run,
        device,
        args.precision,
        args.compile,
        args.compile_mode,
        args.compile_scope,
        args.attention,
    )
    trainer.validation_tf32 = args.allow_tf32
    val_np = exported_validation_batches(export / "validation_batches.safetensors", run)
    if val_np is None:
        val_np = own_validation_batches(run, validation_split)
    val_batches = [to_device(b, device) for b in val_np]
    resume = args.resume
    if resume and not (out / TRAIN_STATE_FILE).is_file():
        raise SystemExit(f"--resume: no {TRAIN_STATE_FILE} in {out}")
    if resume:
        trainer.restore(out)
    else:
        if t.init_from is not None:
            trainer.initialise_from(Path(t.init_from))
        trainer.meta.untrained_validation_loss = trainer.validate(val_batches)
    with safe_open(str(export / "train.safetensors"), framework="numpy") as f:
        train_windows = int((f.metadata() or {}).get("windows", 0))
    data = {
        "train_cache": str(export / "train.safetensors"),
        "train_windows": train_windows,
        "validation_windows": len(validation_split),
        "source": DATA_SOURCE,
    }
    hw = hardware(device, trainer.mode())
    print(
        f"training {run.name} ({trainer.parameter_count()} parameters) on {hw} "
        f"({args.pipeline} pipeline) from step "
        f"{trainer.meta.step} to {until}; batch {t.batch_scenes} scenes; train {train_windows} "
        f"windows, validation {len(validation_split)}; starting validation loss "
        f"{trainer.meta.untrained_validation_loss if not resume else trainer.meta.validation_loss}",
        flush=True,
    )
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "train_log.csv"
    prepare_log(log_path, trainer.meta.step, trainer.meta.untrained_validation_loss)
    log = open(log_path, "a")
    wall_before = trainer.meta.wall_secs
    session_start = time.monotonic()
    last_checkpoint = time.monotonic()
    checkpoint_every = args.checkpoint_every_secs or t.checkpoint_every_secs
    first_step = trainer.meta.step
    window_t, window_steps, window_losses = time.monotonic(), 0, []
    last_print = time.monotonic()
    step_secs = 0.0
    reserve = 10.0  # seconds kept for the last validation and checkpoint; measured below
    stopped_early = False
    pending: list[tuple[int, Tensor, Tensor, float]] = []  # device pipeline: steps not logged
    flushed_at = time.monotonic()
    try:
        while on_device and trainer.meta.step < until:
            # The device pipeline: no step waits for the device; losses, norms and the time
            # per step are read in bulk when a row must be printed, validated or saved.
            if deadline is not None and time.monotonic() + 1.5 * step_secs + reserve > deadline:
                stopped_early = True
                break
            loss_t, norm_t, lr = trainer.device_step(batches.get(trainer.meta.step, until))
            step = trainer.meta.step
            pending.append((step, loss_t, norm_t, lr))
            now = time.monotonic()
            due_val = step % max(t.val_every_steps, 1) == 0 or step == until
            due_print = now - last_print >= args.print_every_secs or step == until
            due_save = now - last_checkpoint >= checkpoint_every or step == until
            if not (due_val or due_print or due_save or len(pending) >= 500):
                continue
            values = torch.stack(
                [torch.stack([lo.double(), no.double()]) for _, lo, no, _ in pending]
            ).tolist()  # waits for the device
            now = time.monotonic()
            secs = (now - flushed_at) / len(pending)
            flushed_at = now
            step_secs = secs if step_secs == 0 else 0.9 * step_secs + 0.1 * secs
            val = ""
            if due_val:
                val_start = time.monotonic()
                val = repr(trainer.validate(val_batches))
                reserve = max(reserve, 2.0 * (time.monotonic() - val_start) + 5.0)
                flushed_at = time.monotonic()
            wall = wall_before + time.monotonic() - session_start
            for (row_step, _, _, row_lr), (row_loss, row_norm) in zip(pending, values):
                if not math.isfinite(row_loss):
                    raise SystemExit(f"training diverged: loss {row_loss} at step {row_step}")
                log.write(
                    f"{row_step},{row_loss!r},{row_lr!r},{row_norm!r},"
                    f"{t.batch_scenes / max(secs, 1e-9):.2f},"
                    f"{val if row_step == step else ''},{wall:.1f}\n"
                )
                window_steps += 1
                window_losses.append(row_loss)
            grad_norm = values[-1][1]
            pending = []
            now = time.monotonic()
            if due_print:
                rate = window_steps / (now - window_t)
                print_progress(step, until, window_losses, lr, grad_norm, rate, t, trainer)
                window_t, window_steps, window_losses, last_print = now, 0, [], now
            if due_save:
                log.flush()
                trainer.meta.wall_secs = wall
                trainer.save(out, data, hardware(device, trainer.mode()))
                last_checkpoint = time.monotonic()
                print(f"checkpoint at step {step} in {out}", flush=True)
                flushed_at = time.monotonic()
        if on_device and pending:
            # Stopped for the budget with steps not logged yet.
            values = torch.stack(
                [torch.stack([lo.double(), no.double()]) for _, lo, no, _ in pending]
            ).tolist()
            secs = (time.monotonic() - flushed_at) / len(pending)
            wall = wall_before + time.monotonic() - session_start
            for (row_step, _, _, row_lr), (row_loss, row_norm) in zip(pending, values):
                if not math.isfinite(row_loss):
                    raise SystemExit(f"training diverged: loss {row_loss} at step {row_step}")
                log.write(
                    f"{row_step},{row_loss!r},{row_lr!r},{row_norm!r},"
                    f"{t.batch_scenes / max(secs, 1e-9):.2f},,{wall:.1f}\n"
                )
            pending = []
        while not on_device and trainer.meta.step < until:
            if deadline is not None and time.monotonic() + 1.5 * step_secs + reserve > deadline:
                stopped_early = True
                break
            step_start = time.monotonic()
            batch = to_device(batches.get(trainer.meta.step, until), device)
            loss, grads = trainer.gradients(batch)
            if not math.isfinite(loss):
                raise SystemExit(f"training diverged: loss {loss} at step {trainer.meta.step}")
            grad_norm, lr = trainer.apply_gradients(grads)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            secs = time.monotonic() - step_start
            step_secs = secs if step_secs == 0 else 0.9 * step_secs + 0.1 * secs
            step = trainer.meta.step
            val = ""
            if step % max(t.val_every_steps, 1) == 0 or step == until:
                val_start = time.monotonic()
                val = repr(trainer.validate(val_batches))
                reserve = max(reserve, 2.0 * (time.monotonic() - val_start) + 5.0)
            wall = wall_before + time.monotonic() - session_start
            log.write(
                f"{step},{loss!r},{lr!r},{grad_norm!r},{t.batch_scenes / max(secs, 1e-9):.2f},"
                f"{val},{wall:.1f}\n"
            )
            window_steps += 1
            window_losses.append(loss)
            now = time.monotonic()
            if now - last_print >= args.print_every_secs or step == until:
                rate = window_steps / (now - window_t)
                print_progress(step, until, window_losses, lr, grad_norm, rate, t, trainer)
                window_t, window_steps, window_losses, last_print = now, 0, [], now
            if now - last_checkpoint >= checkpoint_every or step == until:
                log.flush()
                trainer.meta.wall_secs = wall
                trainer.save(out, data, hardware(device, trainer.mode()))
                last_checkpoint = time.monotonic()
                print(f"checkpoint at step {step} in {out}", flush=True)
        if stopped_early:
            # The budget is spent: validate (so the checkpoint's validation loss is its own),
            # log and save, for the next call's --resume.
            loss_val = trainer.validate(val_batches)
            wall = wall_before + time.monotonic() - session_start
            log.write(f"{trainer.meta.step},,,,,{loss_val!r},{wall:.1f}\n")
            log.flush()
            trainer.meta.wall_secs = wall
            trainer.save(out, data, hardware(device, trainer.mode()))
            print(
                f"time budget of {args.minutes} min spent: checkpoint at step "
                f"{trainer.meta.step} in {out} (validation loss {loss_val:.5f}); continue with "
                "--resume",
                flush=True,
            )
    finally:
        log.close()
        batches.close()
    secs = time.monotonic() - session_start
    done = trainer.meta.step - first_step
    print(
        json.dumps(
            {
                "run": run.name,
                "out": str(out),
                "device": hardware(device, trainer.mode()),
                "pipeline": args.pipeline,
                "compile_error": trainer.compile_error,
                "step": trainer.meta.step,
                "until": until,
                "steps_this_call": done,
                "secs": round(secs, 1),
                "steps_per_sec": done / secs if secs > 0 else 0.0,
                "scene_samples_per_sec": done * t.batch_scenes / secs if secs > 0 else 0.0,
                "validation_loss": trainer.meta.validation_loss,
                "starting_validation_loss": trainer.meta.untrained_validation_loss,
                "finished": trainer.meta.step >= until,
            }
        ),
        flush=True,
    )


def validate_cmd(args: argparse.Namespace) -> None:
    """The validation loss of a checkpoint's weights (as `road train` would log it)."""
    run = load_run(args.config, args.overrides)
    device = pick_device(args.device)
    trainer = Trainer(run, device)
    trainer.initialise_from(args.checkpoint)
    val_np = exported_validation_batches(args.export / "validation_batches.safetensors", run)
    if val_np is None:
        val_np = own_validation_batches(run, ExportedSplit(args.export / "validation.safetensors"))
    loss = trainer.validate([to_device(b, device) for b in val_np])
    print(json.dumps({"checkpoint": str(args.checkpoint), "validation_loss": loss}))


# --------------------------------------------------------------------------------------------
# make-train-fixture: crates/road-model/tests/torch_train_parity.rs
# --------------------------------------------------------------------------------------------

FIXTURE_STEPS = 2


def make_train_fixture(out: Path, init: Path, seed: int) -> None:
    """From the committed synthetic export (`dataset.safetensors`, written by the Rust test)
    and run config (`run.toml`) in `out`, and the torch-parity fixture's random weights as
    `init_from`: two training steps on the CPU, recording every draw, the collated batches,
    the losses and gradients, and the state after them."""
    run = load_run(out / "run.toml", [])
    if run.train.init_from is None:
        raise ConfigError(f"{out / 'run.toml'}: the fixture starts from train.init_from")
    ds = ExportedSplit(out / "dataset.safetensors")
    trainer = Trainer(run, torch.device("cpu"))
    trainer.initialise_from(init)
    buckets = AgentBuckets(ds.agent_counts) if run.train.bucket_by_agents else None
    w = run.model.window_slots
    record: dict[str, Tensor] = {}
    for k in range(FIXTURE_STEPS):
        rng = np.random.default_rng([seed, k])
        draw = sample_scenes(
            run, ds, run.train.batch_scenes, buckets, rng, run.train.rotation_augmentation
        )
        batch = collate(draw)
        a_max = max(n.shape[0] for n in draw.raw_noise)
        raw = np.zeros((len(draw.inputs), a_max, w, 3), np.float32)
        for i, n in enumerate(draw.raw_noise):
            raw[i, : n.shape[0]] = n
        scalars = {
            "window": np.array(draw.window, np.int64),
            "start": np.array(draw.start, np.int64),
            "angle": np.array(draw.angle, np.float64),
            "tau": np.array(draw.tau, np.float64),
            "warmup": np.array(draw.warmup, np.int64),
            "u_ca": np.array(draw.u_ca, np.float64),
            "noise": raw,
        }
        for name, v in {**scalars, **batch}.items():
            record[f"step{k}.{name}"] = torch.from_numpy(np.ascontiguousarray(v))
        loss, grads = trainer.gradients({key: torch.from_numpy(v) for key, v in batch.items()})
        record[f"step{k}.loss"] = torch.tensor([loss], dtype=torch.float64)
        for name, g in zip(trainer.names, grads):
            record[f"step{k}.grad.{name}"] = g.detach().clone().contiguous()
        grad_norm, lr = trainer.apply_gradients(grads)
        record[f"step{k}.grad_norm"] = torch.tensor([grad_norm], dtype=torch.float64)
        record[f"step{k}.learning_rate"] = torch.tensor([lr], dtype=torch.float64)
        clip = min(1.0, run.train.grad_clip / grad_norm)
        print(
            f"step {k}: loss {loss:.6f} grad norm {grad_norm:.4f} (clip factor {clip:.3f}) "
            f"lr {lr:.3e}; warm-up tasks {sum(draw.warmup)}/{len(draw.warmup)}, agents "
            f"{[s.states.shape[0] for s in draw.inputs]} of {[n.shape[0] for n in draw.raw_noise]}"
        )
    weights, state = trainer.tensors()
    for name, v in weights.items():
        record[f"after.ema.{name}"] = v
    for name, v in state.items():
        record[f"after.{name}"] = v
    record["learning_rate_table"] = torch.tensor(
        [learning_rate(run.train, s) for s in range(run.train.steps + 2)], dtype=torch.float64
    )
    save_file(record, str(out / "expected.safetensors"))
    size = sum(p.stat().st_size for p in out.iterdir())
    print(f"wrote {out / 'expected.safetensors'}: {len(record)} tensors; the fixture {size} bytes")


# `bench`'s defaults (its code: torch_train_bench.py, imported when the command runs).
BENCH_VARIANTS = "fp32,fp32+device,bf16+device,bf16+device+sdpa,bf16+device+compile"
BENCH_SIZES = ("base", "h192x4:model.hidden=192,model.heads=12,model.blocks=4")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def run_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--config", type=Path, required=True, help="run config, configs/*.toml")
        p.add_argument(
            "--set",
            dest="overrides",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="per-key override as road's --set, e.g. train.batch_scenes=256 (repeatable)",
        )
        p.add_argument(
            "--export",
            type=Path,
            default=Path(".road-cache/torch"),
            help="`road data export-torch`'s folder",
        )
        p.add_argument("--device", default="auto", help="auto (cuda if available), cuda, cpu")

    def speed_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--precision",
            choices=PRECISIONS,
            default="fp32",
            help="bf16: the training forward under bf16 autocast, f32 weights, optimiser "
            "state and loss, TF32 for the remaining f32 products (validation stays f32)",
        )
        p.add_argument(
            "--compile",
            action="store_true",
            help="torch.compile the training forward and loss (eager, with a warning, if "
            "compiling fails)",
        )
        p.add_argument(
            "--compile-mode",
            default="default",
            help="torch.compile's mode (default, max-autotune-no-cudagraphs, …)",
        )
        p.add_argument(
            "--compile-scope",
            choices=COMPILE_SCOPES,
            default="forward",
            help="with --compile: forward (the whole training forward and loss) or blocks "
            "(the transformer blocks only, one graph for all: a fraction of the compile time)",
        )
        p.add_argument(
            "--attention",
            choices=ATTENTIONS,
            default="explicit",
            help="sdpa: attention without pair features through PyTorch's fused "
            "scaled_dot_product_attention (validation keeps the written-out products)",
        )
        p.add_argument(
            "--pipeline",
            choices=("host", "device"),
            default="host",
            help="host: batches made by numpy on loader processes, as road train's (the "
            "default); device: the training split moved to the device once, batches gathered "
            "there, no step waiting for the device (other random streams: another run)",
        )

    tr = sub.add_parser("train", help="train (or continue with --resume) a run")
    run_args(tr)
    tr.add_argument("--out", type=Path, default=None, help="checkpoint folder (models/<name>)")
    tr.add_argument("--resume", action="store_true", help="continue the run in --out")
    tr.add_argument("--until-step", type=int, default=None, help="stop at this step")
    tr.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="wall-clock budget: validate, save and exit before it is spent",
    )
    tr.add_argument(
        "--checkpoint-every-secs",
        type=float,
        default=None,
        help="instead of train.checkpoint_every_secs",
    )
    tr.add_argument("--print-every-secs", type=float, default=10.0)
    tr.add_argument(
        "--loader-workers",
        type=int,
        default=-1,
        help="processes preparing batches (default: none on the CPU, up to 8 with CUDA)",
    )
    tr.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's)")
    tr.add_argument("--allow-tf32", action="store_true", help="TF32 matrix products (not fp32)")
    speed_args(tr)
    be = sub.add_parser(
        "bench",
        help="training throughput of sizes × batch sizes × variants (no checkpoints)",
    )
    run_args(be)
    be.add_argument(
        "--variants",
        default=BENCH_VARIANTS,
        help="comma-separated; each `+`-joined tokens: fp32 | bf16, compile | compile-blocks "
        "(the whole forward, or the blocks only), host | device (the pipeline; host by "
        f"default), tf32, sdpa (fused attention) (default {BENCH_VARIANTS})",
    )
    be.add_argument(
        "--batch-scenes", default="256,1024", help="comma-separated batch sizes (scenes)"
    )
    be.add_argument(
        "--size",
        action="append",
        default=None,
        metavar="LABEL[:KEY=VALUE,…]",
        help="a model size: `base` (the config's) or overrides, repeatable (default: "
        + " and ".join(f"`{x}`" for x in BENCH_SIZES)
        + ")",
    )
    be.add_argument("--steps", type=int, default=20, help="timed steps per case (at most)")
    be.add_argument(
        "--case-secs", type=float, default=5.0, help="stop a case's timing after this (≥ 3 steps)"
    )
    be.add_argument("--warmup-steps", type=int, default=3, help="untimed steps per case")
    be.add_argument(
        "--compile-warmup-steps",
        type=int,
        default=5,
        help="more untimed steps for compiled cases (recompilations for new agent counts)",
    )
    be.add_argument(
        "--budget-secs", type=float, default=0.0, help="skip the cases left after this"
    )
    be.add_argument(
        "--no-data-rows",
        dest="data_rows",
        action="store_false",
        help="leave out the pipeline-only rows (batches/s without a model)",
    )
    be.add_argument("--compile-mode", default="default", help="torch.compile's mode")
    be.add_argument(
        "--profile-steps",
        type=int,
        default=0,
        help="after each case's timing, this many steps under torch.profiler: its top "
        "operators (and kernels per step on a GPU) in the case's row",
    )
    be.add_argument("--profile-top", type=int, default=15, help="operators a profile keeps")
    be.add_argument("--loader-workers", type=int, default=-1, help="as train's")
    be.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's)")
    be.add_argument("--json", type=Path, default=None, help="write the results here as well")
    po = sub.add_parser(
        "pick-options",
        help="the training options a bench JSON favours for a run (one line; why on stderr)",
    )
    run_args(po)
    po.add_argument("--bench", type=Path, required=True, help="`bench --json`'s file")
    po.add_argument("--baseline", default="bf16+device", help="the variant to beat")
    va = sub.add_parser("validate", help="a checkpoint's validation loss on the export")
    run_args(va)
    va.add_argument("--checkpoint", type=Path, required=True)
    fx = sub.add_parser("make-train-fixture", help="write the training-parity fixture")
    fx.add_argument(
        "--out", type=Path, default=Path("crates/road-model/tests/fixtures/torch_train")
    )
    fx.add_argument(
        "--init",
        type=Path,
        default=Path("crates/road-model/tests/fixtures/torch_parity"),
        help="the starting weights (a checkpoint folder of run.toml's model)",
    )
    fx.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    try:
        if args.command == "train":
            train(args)
        elif args.command == "bench":
            import torch_train_bench  # here, not at the top: it imports this module

            torch_train_bench.bench(args)
        elif args.command == "pick-options":
            run = load_run(args.config, args.overrides)
            options, why = pick_options(
                json.loads(args.bench.read_text()), run.train.batch_scenes, args.baseline
            )
            print(f"pick-options: {why}", file=sys.stderr)
            print(" ".join(options))
        elif args.command == "validate":
            torch.backends.cuda.matmul.allow_tf32 = False
            validate_cmd(args)
        else:
            torch.backends.cuda.matmul.allow_tf32 = False
            make_train_fixture(args.out, args.init, args.seed)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        raise SystemExit(f"error: {e}") from e


if __name__ == "__main__":
    main()
