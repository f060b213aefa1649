"""What every part of `torch_train.py`'s training path reads: the run config (configs/<run>.toml
with `--set` overrides, config.rs `RunConfig`), `road data export-torch`'s splits
(`ExportedSplit`: scene windows materialised as dataset.rs and batch.rs do), train.rs's
agent-count buckets and the per-step random stream. Shared by torch_train.py and
torch_device_pipeline.py (and torch_diagnose.py), so that neither pipeline imports the other.
"""

from __future__ import annotations

import tomllib
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch_denoiser as td
from safetensors import safe_open
from safetensors.numpy import load_file as load_numpy

# train.rs AgentBuckets::MIN_BUCKET.
MIN_BUCKET = 256
EXPORT_FORMAT = "road-torch-dataset"
EXPORT_VERSION = "1"
STATES_ENCODING = "u32-delta-byteplanes-zlib"
PI32 = np.float32(np.pi)
TAU32 = np.float32(2.0) * PI32


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
    for key in ("kink_augmentation", "history_noise_m", "initialisation_task_prob"):
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
        agent_rows = np.concatenate(
            [
                np.arange(self.window_agent_offsets[i], self.window_agent_offsets[i + 1])
                for i in indices
            ]
        )
        # Only the steps up to the crops' ends matter: the heading unwraps from each window's
        # first step on.
        valid, xy, heading, features = self.agent_steps(
            indices_a, agent_rows, max(starts) + slots, c.heading_scale
        )
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

    def agent_steps(
        self, indices_a: np.ndarray, agent_rows: np.ndarray, steps: int, heading_scale: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The agents of windows `indices_a` (their rows `agent_rows` of `window_agents`, window
        by window) over each window's first `steps` steps, in model units: validity `[N, S]`,
        positions `[N, S, 2]`, headings `[N, S]` (unwrapped step by step from each agent's
        first valid one, then scaled) and features `[N, AGENT_FEATURES]`."""
        counts = self.agent_counts[indices_a]  # [B]
        rec = self.window_recording[indices_a]  # [B]
        scene_of = np.repeat(np.arange(len(indices_a)), counts)  # [N] scene of each agent row
        tracks = self.recording_track_offsets[rec][scene_of] + self.window_agents[agent_rows]
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
        heading *= np.float32(heading_scale)
        features = np.zeros((n, td.AGENT_FEATURES), np.float32)
        features[:, 0] = self.track_length_m[tracks] / np.float32(5.0)
        features[:, 1] = self.track_width_m[tracks] / np.float32(2.5)
        features[np.arange(n), 2 + self.track_type[tracks]] = 1.0
        return valid, xy, heading, features


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
# The per-step random stream (both pipelines' draws: deterministic per step, exact resume).
# --------------------------------------------------------------------------------------------


def step_rng(seed: int, step: int) -> np.random.Generator:
    return np.random.default_rng([seed, step])
