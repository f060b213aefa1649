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

fp32 throughout, TF32 off unless `--allow-tf32`.
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
import zlib
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open
from safetensors.numpy import load_file as load_numpy
from safetensors.torch import load_file, save_file
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torch_denoiser as td  # noqa: E402  (the forward pass, its config parsing and names)

ADAM_BETA1 = 0.9
ADAM_BETA2 = 0.999
ADAM_EPS = 1e-8
# train.rs VALIDATION_SEED: the validation draws' own seed (numpy's stream here, not Rust's).
VALIDATION_SEED = 0x005EED0F7A11
# train.rs AgentBuckets::MIN_BUCKET.
MIN_BUCKET = 256
EXPORT_FORMAT = "road-torch-dataset"
BATCHES_FORMAT = "road-torch-validation-batches"
EXPORT_VERSION = "1"
STATES_ENCODING = "u32-delta-byteplanes-zlib"
PI32 = np.float32(np.pi)
TAU32 = np.float32(2.0) * PI32
WEIGHTS_FILE = "weights.safetensors"
TRAIN_STATE_FILE = "train_state.safetensors"
META_FILE = "config.toml"
LOG_HEADER = "step,loss,learning_rate,grad_norm,samples_per_sec,validation_loss,wall_secs"
DATA_SOURCE = "INTERACTION DR v1.0 (non-commercial licence), official validation split"


class ConfigError(ValueError):
    """A bad run config or override; the message names the file and key."""


# --------------------------------------------------------------------------------------------
# Run config: configs/<run>.toml (config.rs RunConfig) with `--set key=value` overrides.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainConfig:
    """config.rs `TrainConfig`; defaults as its `Default`."""

    batch_scenes: int = 16
    steps: int = 20_000
    learning_rate: float = 1e-3
    warmup_steps: int = 200
    min_learning_rate: float = 1e-5
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    warmup_task_prob: float = 0.1
    augmentation_ratio: float = 0.5
    seed: int = 0
    val_every_steps: int = 250
    val_batches: int = 8
    checkpoint_every_secs: int = 300
    bucket_by_agents: bool = True
    workers: int = 2  # candle's data parallelism: no effect on the math here
    rotation_augmentation: bool = False
    init_from: str | None = None


@dataclass(frozen=True)
class Edm:
    sigma_min: float = 0.002
    sigma_max: float = 80.0
    rho: float = 7.0
    sigma_data: float = 0.5

    def sigma(self, u: float) -> float:
        """road_sched::edm `EdmSchedule::sigma`: clamped, 0 at u = 0."""
        u = min(max(u, 0.0), 1.0)
        if u == 0.0:
            return 0.0
        inv_rho = 1.0 / self.rho
        lo = self.sigma_min**inv_rho
        hi = self.sigma_max**inv_rho
        return (lo + u * (hi - lo)) ** self.rho


def warmup_u(k: int, f: int, tau: float) -> float:
    return min(max(k / f + tau, 0.0), 1.0)


def rolling_u(k: int, f: int, tau: float) -> float:
    return min(max((k + tau) / f, 0.0), 1.0)


def full_u(k: int, f: int, tau: float) -> float:
    return min(max(tau, 0.0), 1.0)


@dataclass
class Run:
    """A parsed run: the raw tables (written back into checkpoints) and typed views."""

    table: dict[str, Any]
    name: str
    model: td.ModelConfig
    edm: Edm
    obs_slots: int
    future_slots: int
    rolling: bool  # planner kind "rolling": warm-up or rolling tasks; else full diffusion
    train: TrainConfig


def parse_override(item: str) -> tuple[list[str], Any]:
    """`key=value` as road's `--set`: the value is TOML (`40`, `0.5`, `"text"`, `true`), a
    bare word a string; dotted keys reach into tables."""
    if "=" not in item:
        raise ConfigError(f"an override must look like key=value, got `{item}`")
    key, raw = item.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.split("."), value


def load_run_table(path: Path, overrides: list[str]) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"cannot read run config {path}: {e}") from e
    for item in overrides:
        keys, value = parse_override(item)
        target = table
        for part in keys[:-1]:
            target = target.setdefault(part, {})
            if not isinstance(target, dict):
                raise ConfigError(f"override `{item}`: `{part}` is not a table")
        target[keys[-1]] = value
    return table


def parse_run(table: dict[str, Any], origin: str) -> Run:
    """The checks of config.rs `RunConfig::validate` this script relies on; unknown `[train]`
    keys are an error naming them (config.rs denies unknown fields)."""
    unknown = set(table) - {"name", "model", "planner", "train"}
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in {origin}")
    if "name" not in table or "planner" not in table:
        raise ConfigError(f"{origin} lacks `name` or `[planner]`")
    try:
        model = td.parse_model_config(table.get("model", {}))
    except ValueError as e:
        raise ConfigError(f"{origin}: {e}") from e
    edm_table = table.get("model", {}).get("edm", {})
    edm = Edm(**{k: float(v) for k, v in edm_table.items()})
    planner = table["planner"]
    obs = int(planner.get("obs_slots", 10))
    future = int(planner.get("future_slots", 10))
    if obs + future != model.window_slots:
        raise ConfigError(
            f"{origin}: model.window_slots ({model.window_slots}) must equal planner "
            f"obs_slots + future_slots ({obs + future})"
        )
    train_table = dict(table.get("train", {}))
    for key in ("kink_augmentation", "history_noise_m"):
        if key in train_table:
            raise ConfigError(
                f"train.{key} in {origin}: not in the PyTorch path (road train only)"
            )
    known = set(TrainConfig.__dataclass_fields__)
    unknown = set(train_table) - known
    if unknown:
        raise ConfigError(f"unknown [train] key(s) {sorted(unknown)} in {origin}")
    defaults = TrainConfig()
    typed: dict[str, Any] = {}
    for key in known:
        default = getattr(defaults, key)
        value = train_table.get(key, default)
        if key == "init_from":
            typed[key] = None if value is None else str(value)
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"train.{key} must be true or false in {origin}")
            typed[key] = value
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"train.{key} must be a whole number ≥ 0 in {origin}")
            typed[key] = value
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"train.{key} must be a number in {origin}")
            typed[key] = float(value)
    t = TrainConfig(**typed)
    if t.batch_scenes == 0 or not t.learning_rate > 0 or not 0 <= t.ema_decay < 1:
        raise ConfigError(
            f"{origin}: train: batch_scenes ≥ 1, learning_rate > 0, 0 ≤ ema_decay < 1"
        )
    if not (0 <= t.warmup_task_prob <= 1 and 0 <= t.augmentation_ratio <= 1):
        raise ConfigError(f"{origin}: train: warmup_task_prob and augmentation_ratio in [0, 1]")
    return Run(
        table=table,
        name=str(table["name"]),
        model=model,
        edm=edm,
        obs_slots=obs,
        future_slots=future,
        rolling=planner.get("kind", "rolling") == "rolling",
        train=t,
    )


def load_run(path: Path, overrides: list[str]) -> Run:
    return parse_run(load_run_table(path, overrides), f"{path} with overrides {overrides}")


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
# The export: road data export-torch (crates/road-model/src/torch_export.rs).
# --------------------------------------------------------------------------------------------


def unpack_states(packed: np.ndarray, frames: int) -> np.ndarray:
    """torch_export.rs `pack_states` inverted: `[frames, 3]` f32."""
    planes = np.frombuffer(zlib.decompress(packed.tobytes()), dtype=np.uint8)
    if planes.size != frames * 12:
        raise ValueError(f"packed track states hold {planes.size} bytes, expected {frames * 12}")
    deltas = planes.reshape(3, 4, frames).transpose(2, 0, 1).copy().view("<u4")[..., 0]
    bits = np.cumsum(deltas, axis=0, dtype=np.uint32)  # wraps modulo 2³², as the deltas did
    return bits.view(np.float32)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """dataset.rs `wrap_angle` in f32: `(a + π).rem_euclid(2π) − π`, −π itself to +π."""
    r = np.fmod(a + PI32, TAU32)
    r = np.where(r < 0, r + TAU32, r)
    w = r - PI32
    return np.where(w <= -PI32, w + TAU32, w).astype(np.float32)


@dataclass
class SceneInput:
    """batch.rs `SceneInput`: one scene cropped to the model's window, model units."""

    states: np.ndarray  # [A, W, 3] f32: x, y, heading·heading_scale; 0 where invalid
    valid: np.ndarray  # [A, W] bool
    features: np.ndarray  # [A, 6] f32
    map: np.ndarray  # [P, Q, 2] f32

    def rotate(self, angle_rad: float, heading_scale: float) -> None:
        """batch.rs `SceneInput::rotate`, f32: valid states and every map point turn."""
        a = np.float32(angle_rad)
        sin, cos = np.sin(a), np.cos(a)
        x, y = self.states[..., 0].copy(), self.states[..., 1].copy()
        turned_x = cos * x - sin * y
        turned_y = sin * x + cos * y
        heading = self.states[..., 2] + a * np.float32(heading_scale)
        v = self.valid
        self.states[..., 0] = np.where(v, turned_x, self.states[..., 0])
        self.states[..., 1] = np.where(v, turned_y, self.states[..., 1])
        self.states[..., 2] = np.where(v, heading, self.states[..., 2])
        mx, my = self.map[..., 0].copy(), self.map[..., 1].copy()
        self.map[..., 0] = cos * mx - sin * my
        self.map[..., 1] = sin * mx + cos * my

    def drop_absent_agents(self, noise: np.ndarray) -> np.ndarray:
        """batch.rs `drop_absent_agents`: agents with no valid slot go with their noise rows,
        unless none is valid. Returns the kept noise."""
        keep = self.valid.any(axis=1)
        if not keep.any() or keep.all():
            return noise
        self.states = self.states[keep]
        self.valid = self.valid[keep]
        self.features = self.features[keep]
        return noise[keep]


class ExportedSplit:
    """One split of the export; `scene(index, start, …)` materialises a window as
    dataset.rs `Dataset::window` and crops it as batch.rs `SceneInput::from_window`."""

    def __init__(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(
                f"no export at {path}: run `road data export-torch` (docs/torch-training.md)"
            )
        with safe_open(str(path), framework="numpy") as f:
            meta = f.metadata() or {}
        if meta.get("format") != EXPORT_FORMAT or meta.get("format_version") != EXPORT_VERSION:
            raise ValueError(
                f"{path} is not a version-{EXPORT_VERSION} road torch export "
                f"(format {meta.get('format')!r}, version {meta.get('format_version')!r})"
            )
        if meta.get("track_states_encoding") != STATES_ENCODING:
            raise ValueError(f"{path}: unknown track state encoding")
        self.path = path
        self.split = meta["split"]
        self.window_config = tomllib.loads(meta["window_config"])
        a = load_numpy(str(path))
        frames = int(meta["track_states_shape"].split(",")[0])
        self.track_states = unpack_states(a["track_states_packed"], frames)  # [frames, 3]
        self.track_offsets = a["track_offsets"]
        self.track_first_frame = a["track_first_frame"].astype(np.int64)
        self.track_type = a["track_type"].astype(np.int64)
        self.track_length_m = a["track_length_m"]
        self.track_width_m = a["track_width_m"]
        self.recording_track_offsets = a["recording_track_offsets"]
        self.recording_map = a["recording_map"].astype(np.int64)
        self.lanelet_centres = a["lanelet_centres"]  # [L, Q, 2] f64 metres
        self.map_lanelet_offsets = a["map_lanelet_offsets"]
        self.window_recording = a["window_recording"].astype(np.int64)
        self.window_start_frame = a["window_start_frame"].astype(np.int64)
        self.window_origin_m = a["window_origin_m"]
        self.window_agent_offsets = a["window_agent_offsets"]
        self.window_agents = a["window_agents"].astype(np.int64)
        self.window_polyline_offsets = a["window_polyline_offsets"]
        self.window_polylines = a["window_polylines"].astype(np.int64)
        self.steps = int(self.window_config["window_steps"])
        self.scale_m = float(self.window_config["position_scale_m"])
        self.points = int(self.window_config["polyline_points"])
        # Per-window agent counts (for the agent buckets).
        self.agent_counts = np.diff(self.window_agent_offsets)

    def __len__(self) -> int:
        return len(self.window_recording)

    def scene(self, index: int, start: int, slots: int, c: td.ModelConfig) -> SceneInput:
        """Window `index`'s steps `start..start + slots` in model units."""
        return self.scenes([index], [start], slots, c)[0]

    def scenes(
        self, indices: list[int], starts: list[int], slots: int, c: td.ModelConfig
    ) -> list[SceneInput]:
        """Windows `indices`, each cropped to `starts[i]..starts[i] + slots`, in model units:
        the agents of all of them at once (the heading unwraps step by step, so a batch pays
        one loop over the steps, not one per scene)."""
        indices_a = np.asarray(indices, np.int64)
        counts = self.agent_counts[indices_a]  # [B]
        rec = self.window_recording[indices_a]  # [B]
        scene_of = np.repeat(np.arange(len(indices)), counts)  # [N] scene of each agent row
        agent_rows = np.concatenate(
            [
                np.arange(self.window_agent_offsets[i], self.window_agent_offsets[i + 1])
                for i in indices
            ]
        )
        tracks = self.recording_track_offsets[rec][scene_of] + self.window_agents[agent_rows]
        # Only the steps up to the crops' ends matter: the heading unwraps from each window's
        # first step on.
        steps = max(starts) + slots
        frames = self.window_start_frame[indices_a][scene_of][:, None] + np.arange(steps)
        rel = frames - self.track_first_frame[tracks][:, None]  # [N, S]
        length = (self.track_offsets[tracks + 1] - self.track_offsets[tracks])[:, None]
        valid = (rel >= 0) & (rel < length)
        rows = np.where(valid, self.track_offsets[tracks][:, None] + rel, 0)
        raw = self.track_states[rows]  # [N, S, 3] f32 metres and radians
        origin = self.window_origin_m[indices_a][scene_of][:, None, :]  # [N, 1, 2]
        # SceneFrame::to_norm: f64 difference and division, then f32.
        xy = ((raw[..., :2].astype(np.float64) - origin) / self.scale_m).astype(np.float32)
        psi = raw[..., 2]
        n = len(tracks)
        heading = np.zeros((n, steps), np.float32)
        previous = np.zeros(n, np.float32)
        seen = np.zeros(n, bool)
        for s in range(steps):
            v = valid[:, s]
            h = np.where(seen, previous + wrap_angle(psi[:, s] - previous), wrap_angle(psi[:, s]))
            heading[:, s] = np.where(v, h, 0.0)
            previous = np.where(v, h, previous).astype(np.float32)
            seen |= v
        heading *= np.float32(c.heading_scale)
        features = np.zeros((n, td.AGENT_FEATURES), np.float32)
        features[:, 0] = self.track_length_m[tracks] / np.float32(5.0)
        features[:, 1] = self.track_width_m[tracks] / np.float32(2.5)
        features[np.arange(n), 2 + self.track_type[tracks]] = 1.0
        out = []
        first_row = np.concatenate([[0], np.cumsum(counts)])
        for i, (index, start) in enumerate(zip(indices, starts)):
            agents = slice(first_row[i], first_row[i + 1])
            crop = slice(start, start + slots)
            v = valid[agents, crop]
            states = np.zeros((counts[i], slots, 3), np.float32)
            states[..., 0] = np.where(v, xy[agents, crop, 0], 0.0)
            states[..., 1] = np.where(v, xy[agents, crop, 1], 0.0)
            states[..., 2] = np.where(v, heading[agents, crop], 0.0)
            lanelets = self.window_polylines[
                self.window_polyline_offsets[index] : self.window_polyline_offsets[index + 1]
            ][: c.map_polylines]  # nearest first
            first = self.map_lanelet_offsets[self.recording_map[rec[i]]]
            centres = self.lanelet_centres[first + lanelets]  # [P, Q, 2] f64 metres
            polylines = ((centres - self.window_origin_m[index]) / self.scale_m).astype(np.float32)
            out.append(SceneInput(states, v.copy(), features[agents].copy(), polylines))
        return out


class AgentBuckets:
    """train.rs `AgentBuckets`: contiguous agent-count ranges of at least MIN_BUCKET windows."""

    def __init__(self, counts: np.ndarray) -> None:
        members: list[list[int]] = [[]]
        by_count: dict[int, list[int]] = {}
        for i, c in enumerate(counts.tolist()):
            by_count.setdefault(c, []).append(i)
        for c in range(int(counts.max(initial=0)) + 1):
            members[-1].extend(by_count.get(c, []))
            if len(members[-1]) >= MIN_BUCKET:
                members.append([])
        if len(members) > 1 and len(members[-1]) < MIN_BUCKET:
            tail = members.pop()
            members[-1].extend(tail)
        self.members = [np.array(m, np.int64) for m in members]
        self.bucket_of = np.zeros(len(counts), np.int64)
        for b, m in enumerate(self.members):
            self.bucket_of[m] = b

    def pick(self, anchor: int, rng: np.random.Generator) -> int:
        m = self.members[self.bucket_of[anchor]]
        return int(m[rng.integers(len(m))])


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


def edm_error_sum(model: td.Denoiser, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """The squared error summed over valid agent-slots, written on F (no cancellation of
    D − x0 at small σ), and the number of values summed (3 per valid agent-slot).

    Without a reference: `λ(σ)·|D − x0|² = |F − (x0 − c_skip·x)/c_out|²`. With a
    constant-velocity reference (coefficients at σ·s): `λ(σ)·(c_out'/s)²·|F − (s·(x0 − r) −
    c_skip'·y)/c_out'|²`."""
    out = model.forward_parts(
        batch["x_noisy"],
        batch["sigma"],
        batch["valid"],
        batch["agent_features"],
        batch["map"],
        batch["map_valid"],
    )
    x0 = batch["x0"]
    valid4 = batch["valid"].unsqueeze(3)
    r = out.residual
    if r is None:
        target = (x0 - batch["x_noisy"] * out.c_skip) / out.c_out
        err = (out.raw - target).square()
    else:
        y0 = (x0 - r.reference) * r.scale
        target = (y0 - r.y * r.c_skip) / r.c_out
        sd = model.config.sigma_data
        b, w = batch["sigma"].shape
        s2 = batch["sigma"].square().reshape(b, 1, w, 1)
        lam = (s2 + sd * sd) / (s2 * (sd * sd))  # [B, 1, W, 1]
        weight = (r.c_out / r.scale).square() * lam  # [B, A, W, 1]
        err = (out.raw - target).square() * weight
    err = err * valid4
    count = batch["valid"].sum() * 3.0
    return err.sum(), count


def batch_loss(model: td.Denoiser, batch: dict[str, Tensor]) -> Tensor:
    """The training loss: the error sum over the batch's value count (at least 1)."""
    error_sum, count = edm_error_sum(model, batch)
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


class Trainer:
    """Parameters (the model's, sorted by name), AdamW moments and the EMA, on `device`."""

    def __init__(self, run: Run, device: torch.device) -> None:
        self.run = run
        self.device = device
        self.model = td.Denoiser(run.model)
        seeded_init(self.model, run.train.seed)
        self.model.to(device)
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
        self.model.train()
        for p in self.params:
            p.grad = None
        loss = batch_loss(self.model, batch)
        loss.backward()
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        return float(loss.detach()), grads

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
        total = 0.0
        for batch in batches:
            error_sum, count = edm_error_sum(model, batch)
            total += float(error_sum / count.clamp(min=1.0))
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


def step_rng(seed: int, step: int) -> np.random.Generator:
    return np.random.default_rng([seed, step])


def _loader_init(run: Run, export: str, helper: bool = False) -> None:
    if helper:
        torch.set_num_threads(1)  # numpy work only: leave the cores to the main process
    _LOADER["run"] = run
    _LOADER["train"] = ExportedSplit(Path(export) / "train.safetensors")
    _LOADER["buckets"] = (
        AgentBuckets(_LOADER["train"].agent_counts) if run.train.bucket_by_agents else None
    )


def _loader_batch(step: int) -> dict[str, np.ndarray]:
    run: Run = _LOADER["run"]
    draw = sample_scenes(
        run,
        _LOADER["train"],
        run.train.batch_scenes,
        _LOADER["buckets"],
        step_rng(run.train.seed, step),
        run.train.rotation_augmentation,
    )
    return collate(draw)


class Batches:
    """Training batches by step: inline, or `workers` processes preparing the next steps."""

    def __init__(self, run: Run, export: Path, workers: int, ahead: int) -> None:
        self.pool: ProcessPoolExecutor | None = None
        self.pending: dict[int, Future[dict[str, np.ndarray]]] = {}
        self.ahead = ahead
        if workers > 0:
            import multiprocessing

            self.pool = ProcessPoolExecutor(
                workers,
                mp_context=multiprocessing.get_context("fork"),
                initializer=_loader_init,
                initargs=(run, str(export), True),
            )
            # A fork pool starts every worker on its first task: do it now, before this
            # process initialises CUDA (a forked child must not inherit a CUDA context).
            self.pool.submit(int).result()
        else:
            _loader_init(run, str(export))

    def get(self, step: int, last: int) -> dict[str, np.ndarray]:
        if self.pool is None:
            return _loader_batch(step)
        for s in range(step, min(step + self.ahead, last)):
            if s not in self.pending:
                self.pending[s] = self.pool.submit(_loader_batch, s)
        return self.pending.pop(step).result()

    def close(self) -> None:
        if self.pool is not None:
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


def hardware(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)}, PyTorch {torch.__version__} fp32"
    cpu = platform.processor() or "CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {torch.get_num_threads()} threads, PyTorch {torch.__version__} fp32"


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


def train(args: argparse.Namespace) -> None:
    run = load_run(args.config, args.overrides)
    t = run.train
    device = pick_device(args.device)
    torch.backends.cuda.matmul.allow_tf32 = args.allow_tf32
    torch.backends.cudnn.allow_tf32 = args.allow_tf32
    if args.threads:
        torch.set_num_threads(args.threads)
    started = time.monotonic()
    deadline = started + args.minutes * 60.0 if args.minutes else None
    export = args.export
    validation_split = ExportedSplit(export / "validation.safetensors")
    out = args.out or Path("models") / run.name
    until = min(args.until_step or t.steps, t.steps)
    workers = args.loader_workers
    if workers < 0:
        workers = 0 if device.type == "cpu" else max(1, min(8, (os.cpu_count() or 2) - 2))
    batches = Batches(run, export, workers, ahead=max(2, 2 * workers))
    trainer = Trainer(run, device)
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
    hw = hardware(device)
    print(
        f"training {run.name} ({trainer.parameter_count()} parameters) on {hw} from step "
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
    try:
        while trainer.meta.step < until:
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
                print(
                    f"step {step}/{until} loss {np.mean(window_losses):.4f} lr {lr:.2e} "
                    f"grad {grad_norm:.3f} {rate:.2f} steps/s {rate * t.batch_scenes:.1f} "
                    f"scene-samples/s val {trainer.meta.validation_loss}",
                    flush=True,
                )
                window_t, window_steps, window_losses, last_print = now, 0, [], now
            if now - last_checkpoint >= checkpoint_every or step == until:
                log.flush()
                trainer.meta.wall_secs = wall
                trainer.save(out, data, hw)
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
            trainer.save(out, data, hw)
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
                "device": hw,
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
