#!/usr/bin/env python3
"""PyTorch eager mirror of the candle denoiser `D(x; σ)` (crates/road-model/src/model.rs).

The mirror reads a checkpoint folder (`config.toml` + `weights.safetensors`, the tensor names of
docs/checkpoint.md) and computes the preconditioned denoiser output for a batch of tensors, so
that a machine with PyTorch and no Rust toolchain can run, benchmark or train the same model.
`crates/road-model/tests/torch_parity.rs` checks candle against a fixture this script writes.

    python scripts/torch_denoiser.py make-fixture \
        --out crates/road-model/tests/fixtures/torch_parity
    python scripts/torch_denoiser.py check --checkpoint models/road20-wide4
    python scripts/torch_denoiser.py bench --checkpoint models/road20-wide4 \
        --batches 1 16 128 512 --device cuda

Every operation follows the candle code in order (float32 throughout, TF32 off unless asked), so
the two agree to float rounding, not merely "closely".
"""

from __future__ import annotations

import argparse
import json
import math
import re
import struct
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

# Additive attention bias of a masked key: exp(−1e9) is exactly 0 in f32 (model.rs, MASKED).
MASKED = -1e9
LN_EPS = 1e-5
# Per-agent static features: length/5 m, width/2.5 m, one-hot type (4) (batch.rs).
AGENT_FEATURES = 6
# Agent-pair features: direction (forward, left), proximity (near, far), heading difference
# (cos, sin) (agent_pairs.rs).
PAIR_FEATURES = 6


class UnsupportedConfig(ValueError):
    """A config option this mirror does not implement (named in the message)."""


# --------------------------------------------------------------------------------------------
# Config: `[run.model]` of a checkpoint's config.toml, the keys of config.rs' ModelConfig.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AgentFrame:
    anchor_slot: int
    relative_scale: float
    residual_scale: float | None

    def relative_features(self) -> int:
        # (forward, left, heading, anchor valid), plus the last step (forward, left) with a
        # constant-velocity reference.
        return 6 if self.residual_scale is not None else 4


@dataclass(frozen=True)
class AgentPairs:
    direction_scale_m: float
    near_scale_m: float
    far_scale_m: float


@dataclass(frozen=True)
class ModelConfig:
    hidden: int = 64
    heads: int = 4
    blocks: int = 3
    mlp_ratio: int = 2
    window_slots: int = 20
    polyline_points: int = 20
    map_polylines: int = 32
    heading_scale: float = 0.25
    position_scale_m: float = 40.0
    sigma_data: float = 0.5
    agent_frame: AgentFrame | None = None
    agent_map_polylines: int | None = None
    agent_pairs: AgentPairs | None = None


_MODEL_KEYS = {
    "hidden",
    "heads",
    "blocks",
    "mlp_ratio",
    "window_slots",
    "polyline_points",
    "map_polylines",
    "heading_scale",
    "position_scale_m",
    "edm",
    "agent_frame",
    "agent_map",
    "agent_pairs",
}
_SUB_KEYS = {
    # σ_min, σ_max and ρ shape the sampler's schedule, not the forward; σ_data enters c_*.
    "edm": ({"sigma_min", "sigma_max", "rho", "sigma_data"}, set()),
    "agent_frame": ({"anchor_slot", "relative_scale"}, {"residual_scale"}),
    "agent_map": ({"polylines"}, set()),
    "agent_pairs": ({"direction_scale_m", "near_scale_m", "far_scale_m"}, set()),
}


def _check_keys(table: dict[str, Any], name: str) -> None:
    """Rejects keys the mirror does not know, naming them (config.rs denies unknown fields)."""
    required, optional = _SUB_KEYS[name]
    unknown = set(table) - required - optional
    if unknown:
        raise UnsupportedConfig(
            f"[run.model.{name}] option(s) not supported by the PyTorch mirror: "
            + ", ".join(f"{name}.{k}" for k in sorted(unknown))
        )
    missing = required - set(table)
    if missing:
        raise UnsupportedConfig(f"[run.model.{name}] lacks {', '.join(sorted(missing))}")


def parse_model_config(model: dict[str, Any]) -> ModelConfig:
    """`[run.model]` → ModelConfig; defaults as config.rs' `ModelConfig::default()`."""
    unknown = set(model) - _MODEL_KEYS
    if unknown:
        raise UnsupportedConfig(
            "[run.model] option(s) not supported by the PyTorch mirror: "
            + ", ".join(sorted(unknown))
        )
    for sub in ("edm", "agent_frame", "agent_map", "agent_pairs"):
        if sub in model:
            _check_keys(model[sub], sub)
    defaults = ModelConfig()
    frame = model.get("agent_frame")
    pairs = model.get("agent_pairs")
    config = ModelConfig(
        hidden=int(model.get("hidden", defaults.hidden)),
        heads=int(model.get("heads", defaults.heads)),
        blocks=int(model.get("blocks", defaults.blocks)),
        mlp_ratio=int(model.get("mlp_ratio", defaults.mlp_ratio)),
        window_slots=int(model.get("window_slots", defaults.window_slots)),
        polyline_points=int(model.get("polyline_points", defaults.polyline_points)),
        map_polylines=int(model.get("map_polylines", defaults.map_polylines)),
        heading_scale=float(model.get("heading_scale", defaults.heading_scale)),
        position_scale_m=float(model.get("position_scale_m", defaults.position_scale_m)),
        sigma_data=float(model.get("edm", {}).get("sigma_data", defaults.sigma_data)),
        agent_frame=None
        if frame is None
        else AgentFrame(
            anchor_slot=int(frame["anchor_slot"]),
            relative_scale=float(frame["relative_scale"]),
            residual_scale=None
            if frame.get("residual_scale") is None
            else float(frame["residual_scale"]),
        ),
        agent_map_polylines=None
        if "agent_map" not in model
        else int(model["agent_map"]["polylines"]),
        agent_pairs=None
        if pairs is None
        else AgentPairs(
            direction_scale_m=float(pairs["direction_scale_m"]),
            near_scale_m=float(pairs["near_scale_m"]),
            far_scale_m=float(pairs["far_scale_m"]),
        ),
    )
    _validate(config)
    return config


def _validate(c: ModelConfig) -> None:
    """The checks of `ModelConfig::validate` that the forward relies on."""
    if c.hidden <= 0 or c.heads <= 0 or c.hidden % c.heads:
        raise ValueError(f"hidden ({c.hidden}) must be a positive multiple of heads ({c.heads})")
    if c.agent_frame is not None:
        if not 0 <= c.agent_frame.anchor_slot < c.window_slots:
            raise ValueError("agent_frame.anchor_slot must be a slot of the window")
        if c.agent_frame.residual_scale is not None and c.agent_frame.anchor_slot == 0:
            raise ValueError("agent_frame.residual_scale needs anchor_slot ≥ 1")
    if c.agent_map_polylines is not None:
        if c.agent_frame is None:
            raise ValueError("agent_map needs an agent_frame")
        if not 1 <= c.agent_map_polylines <= c.map_polylines:
            raise ValueError("agent_map.polylines must lie in 1..=map_polylines")
    if c.agent_pairs is not None and c.agent_frame is None:
        raise ValueError("agent_pairs needs an agent_frame")


def load_config(checkpoint: Path) -> ModelConfig:
    with open(checkpoint / "config.toml", "rb") as f:
        meta = tomllib.load(f)
    return parse_model_config(meta["run"].get("model", {}))


# --------------------------------------------------------------------------------------------
# The network.
# --------------------------------------------------------------------------------------------


def skip_out_in(sigma: Tensor, sigma_data: float) -> tuple[Tensor, Tensor, Tensor]:
    """EDM's c_skip, c_out, c_in of σ of any shape (model.rs, `skip_out_in`)."""
    sd = sigma_data
    denom = sigma.square() + sd * sd  # σ² + σd²
    root = denom.sqrt()
    c_skip = denom.reciprocal() * (sd * sd)
    c_out = (sigma * sd) / root
    c_in = root.reciprocal()
    return c_skip, c_out, c_in


def key_bias(flags: Tensor) -> Tensor:
    """0 where a key is valid, −1e9 where not (model.rs, `key_bias`)."""
    return (flags - 1.0) * -MASKED


class Attention(nn.Module):
    """Multi-head attention with, for agent attention of an agent_pairs model, the pair
    features' key offset `pair_k · r` and value offset `pair_v · r` (`[D, F]`, head h owns
    rows h·dh…)."""

    def __init__(self, d: int, heads: int, pair_features: int | None) -> None:
        super().__init__()
        self.q = nn.Linear(d, d)
        self.k = nn.Linear(d, d)
        self.v = nn.Linear(d, d)
        self.o = nn.Linear(d, d)
        self.heads = heads
        # `Denoiser.use_sdpa`: attention without pair features through PyTorch's fused
        # kernel (no [N, H, Lq, Lk] scores kept for the backward on a GPU).
        self.sdpa = False
        self.pair_k: nn.Parameter | None = None
        self.pair_v: nn.Parameter | None = None
        if pair_features is not None:
            self.pair_k = nn.Parameter(torch.zeros(d, pair_features))
            self.pair_v = nn.Parameter(torch.zeros(d, pair_features))

    def forward(self, xq: Tensor, xkv: Tensor, bias: Tensor, pairs: Tensor | None = None) -> Tensor:
        """`xq [N, Lq, D]`, `xkv [N, Lk, D]`, `bias [N, 1, 1, Lk]`, `pairs [N, Lq, Lk, F]`
        → `[N, Lq, D]`."""
        n, lq, d = xq.shape
        lk = xkv.shape[1]
        h = self.heads
        dh = d // h

        def split(t: Tensor, length: int) -> Tensor:
            return t.reshape(n, length, h, dh).transpose(1, 2)  # [N, H, L, dh]

        # candle scales q (after its bias), not the scores.
        q = split(self.q(xq) * (1.0 / math.sqrt(dh)), lq)  # [N, H, Lq, dh]
        k = split(self.k(xkv), lk)  # [N, H, Lk, dh]
        v = split(self.v(xkv), lk)  # [N, H, Lk, dh]
        if (self.pair_k is None) != (pairs is None):
            raise ValueError("pair features go with pair weights (agent attention of agent_pairs)")
        if self.sdpa and pairs is None:
            # The same softmax(q·kᵀ + bias)·v (q already scaled); a fully masked row is
            # uniform here as there (the bias is finite).
            out = nn.functional.scaled_dot_product_attention(
                q, k, v, attn_mask=bias.to(q.dtype), scale=1.0
            )  # [N, H, Lq, dh]
            return self.o(out.transpose(1, 2).reshape(n, lq, d))
        scores = q @ k.transpose(-1, -2)  # [N, H, Lq, Lk]
        if self.pair_k is not None and self.pair_v is not None and pairs is not None:
            f = pairs.shape[-1]
            # q_i · K_h r_ij = (K_hᵀ q_i) · r_ij: F (not dh) per pair.
            q_pair = torch.einsum("nhqd,hdf->nhqf", q, self.pair_k.reshape(h, dh, f))
            scores = scores + torch.einsum("nhqf,nqkf->nhqk", q_pair, pairs)
        attn = torch.softmax(scores + bias, dim=-1)  # [N, H, Lq, Lk]
        out = attn @ v  # [N, H, Lq, dh]
        if self.pair_v is not None and pairs is not None:
            f = pairs.shape[-1]
            # Σ_j a_ij V_h r_ij = V_h Σ_j a_ij r_ij.
            mean_pair = torch.einsum("nhqk,nqkf->nhqf", attn, pairs)  # [N, H, Lq, F]
            out = out + torch.einsum("nhqf,hdf->nhqd", mean_pair, self.pair_v.reshape(h, dh, f))
        out = out.transpose(1, 2).reshape(n, lq, d)  # [N, Lq, D]
        return self.o(out)


@dataclass
class MapKeys:
    """What the map cross-attention attends to: the scene's tokens (`[B, P, D]`, bias
    `[B, 1, 1, P]`) or, `per_agent`, each agent's own (`[B·A, K, D]`, `[B·A, 1, 1, K]`)."""

    tokens: Tensor
    bias: Tensor
    per_agent: bool


class Block(nn.Module):
    def __init__(self, c: ModelConfig) -> None:
        super().__init__()
        d = c.hidden
        self.ln_time = nn.LayerNorm(d, eps=LN_EPS)
        self.time = Attention(d, c.heads, None)
        self.ln_agents = nn.LayerNorm(d, eps=LN_EPS)
        self.agents = Attention(d, c.heads, PAIR_FEATURES if c.agent_pairs else None)
        self.ln_map = nn.LayerNorm(d, eps=LN_EPS)
        self.map = Attention(d, c.heads, None)
        self.ln_mlp = nn.LayerNorm(d, eps=LN_EPS)
        self.mlp_in = nn.Linear(d, d * c.mlp_ratio)
        self.mlp_out = nn.Linear(d * c.mlp_ratio, d)

    def forward(
        self,
        h: Tensor,
        time_bias: Tensor,
        agent_bias: Tensor,
        map_keys: MapKeys,
        pairs: Tensor | None,
    ) -> Tensor:
        """`h [B, A, W, D]` → `[B, A, W, D]`."""
        b, a, w, d = h.shape
        # Time attention within each agent: [B·A, W, D].
        x = self.ln_time(h).reshape(b * a, w, d)
        h = h + self.time(x, x, time_bias).reshape(b, a, w, d)
        # Agent attention within each slot: [B·W, A, D].
        x = self.ln_agents(h).transpose(1, 2).reshape(b * w, a, d)
        y = self.agents(x, x, agent_bias, pairs).reshape(b, w, a, d).transpose(1, 2)
        h = h + y
        # Map cross-attention: the scene's tokens ([B, A·W, D]) or each agent's ([B·A, W, D]).
        x = self.ln_map(h)
        x = x.reshape(b * a, w, d) if map_keys.per_agent else x.reshape(b, a * w, d)
        h = h + self.map(x, map_keys.tokens, map_keys.bias).reshape(b, a, w, d)
        x = self.ln_mlp(h)
        return h + self.mlp_out(torch.relu(self.mlp_in(x)))


@dataclass
class Frame:
    """Each agent's anchor pose (its noisy state at the anchor slot); agents not valid there
    keep the scene frame (model.rs, `AnchorFrame`)."""

    anchor: Tensor  # [B, A, 1, 3], zero where not valid
    anchor_valid: Tensor  # [B, A, 1, 1]
    cos: Tensor  # [B, A, 1, 1]
    sin: Tensor  # [B, A, 1, 1]
    step: Tensor | None  # [B, A, 1, 3]: anchor − (anchor − 1), positions only, heading 0

    def rotate_in(self, dx: Tensor, dy: Tensor) -> tuple[Tensor, Tensor]:
        """A scene-frame displacement → (forward, left) in the anchor heading."""
        forward = dx * self.cos + dy * self.sin
        left = dy * self.cos - dx * self.sin
        return forward, left


def anchor_frame(
    x: Tensor, valid: Tensor, slot: int, heading_scale: float, with_step: bool
) -> Frame:
    """`x [B, A, W, 3]`, `valid [B, A, W]` → the anchor frame of every agent row."""
    anchor_valid = valid[:, :, slot : slot + 1].unsqueeze(3)  # [B, A, 1, 1]
    anchor = x[:, :, slot : slot + 1] * anchor_valid  # [B, A, 1, 3]
    heading_rad = anchor[..., 2:3] / heading_scale
    step = None
    if with_step:
        both = valid[:, :, slot - 1 : slot].unsqueeze(3) * anchor_valid  # [B, A, 1, 1]
        delta = x[:, :, slot : slot + 1] - x[:, :, slot - 1 : slot]  # [B, A, 1, 3]
        positions = delta[..., 0:2] * both
        step = torch.cat([positions, torch.zeros_like(both)], dim=3)
    return Frame(anchor, anchor_valid, heading_rad.cos(), heading_rad.sin(), step)


def relative_features(frame: Frame, d: Tensor, scale: Tensor) -> Tensor:
    """`d [B, A, W, 3]` rotated into the anchor heading, times `scale [B, A, W, 1]`, and the
    anchor's validity: `[B, A, W, 4]`."""
    forward, left = frame.rotate_in(d[..., 0:1], d[..., 1:2])
    dh = d[..., 2:3]
    scale = scale * frame.anchor_valid
    flag = frame.anchor_valid.expand(dh.shape)
    return torch.cat([forward * scale, left * scale, dh * scale, flag], dim=3)


def step_features(frame: Frame, scale: float, w: int) -> Tensor:
    """The last observed step in the anchor heading, times `scale`, every slot: `[B, A, W, 2]`."""
    assert frame.step is not None
    forward, left = frame.rotate_in(frame.step[..., 0:1], frame.step[..., 1:2])
    b, a = frame.step.shape[:2]
    return (torch.cat([forward, left], dim=3) * scale).expand(b, a, w, 2)


@dataclass
class Residual:
    """The constant-velocity reference and the preconditioning at σ·scale (model.rs)."""

    reference: Tensor  # [B, A, W, 3]
    scale: Tensor  # [B, A, 1, 1]: s, or 1 without an anchor
    y: Tensor  # [B, A, W, 3]: scale · (x − reference)
    c_skip: Tensor  # [B, A, W, 1]
    c_out: Tensor  # [B, A, W, 1]
    c_in: Tensor  # [B, A, W, 1]


def residual_of(
    frame: Frame, x: Tensor, sigma: Tensor, anchor_slot: int, residual_scale: float, sd: float
) -> Residual:
    b, _, w, _ = x.shape
    assert frame.step is not None
    offsets = (torch.arange(w, device=x.device, dtype=torch.float32) - float(anchor_slot)).reshape(
        1, 1, w, 1
    )
    reference = frame.anchor + frame.step * offsets
    scale = frame.anchor_valid * (residual_scale - 1.0) + 1.0
    y = (x - reference) * scale
    sigma_y = sigma.reshape(b, 1, w, 1) * scale  # [B, A, W, 1]
    c_skip, c_out, c_in = skip_out_in(sigma_y, sd)
    return Residual(reference, scale, y, c_skip, c_out, c_in)


def anchors_of(
    x: Tensor, valid: Tensor, anchor_slot: int, heading_scale: float
) -> tuple[Tensor, ...]:
    """Every agent row's anchor (agent_map.rs, `anchors_of`): position (x, y) and the heading's
    (cos, sin), the scene centre with heading 0 without an anchor. Each `[B, A]`."""
    v = valid[:, :, anchor_slot]
    state = x[:, :, anchor_slot]  # [B, A, 3]
    heading = state[..., 2] * v / heading_scale
    return state[..., 0] * v, state[..., 1] * v, heading.cos(), heading.sin()


def agent_maps(
    anchors: tuple[Tensor, ...], points: Tensor, map_valid: Tensor, wanted: int
) -> tuple[Tensor, Tensor]:
    """Each agent's `K = min(wanted, P)` polylines nearest its anchor (least squared distance
    to any point; valid before padding; ties to the lower index) in its anchor frame
    (agent_map.rs, `agent_maps`). `points [B, P, Q, 2]`, `map_valid [B, P]` →
    (`[B, A, K, Q, 2]`, `[B, A, K]`). The pick is discrete: no gradient flows through it."""
    ax, ay, cos, sin = (t[:, :, None, None] for t in anchors)  # [B, A, 1, 1]
    px = points[:, None, :, :, 0]  # [B, 1, P, Q]
    py = points[:, None, :, :, 1]
    dx = px - ax  # [B, A, P, Q]
    dy = py - ay
    nearest = (dx * dx + dy * dy).amin(dim=3)  # [B, A, P]
    p = points.shape[1]
    k = min(wanted, p)
    # Lexicographic (padding last, distance, index) by two stable sorts: the second (on the
    # padding flag) keeps the first's distance order, which keeps index order among ties.
    by_distance = torch.sort(nearest, dim=2, stable=True).indices  # [B, A, P]
    padding = (map_valid <= 0.0).to(torch.int32)[:, None, :].expand_as(nearest)
    order = torch.gather(
        by_distance,
        2,
        torch.sort(torch.gather(padding, 2, by_distance), dim=2, stable=True).indices,
    )
    pick = order[:, :, :k]  # [B, A, K]
    b, a = pick.shape[:2]
    q = points.shape[2]
    gather_index = pick[..., None].expand(b, a, k, q)
    pdx = torch.gather(dx, 2, gather_index)  # [B, A, K, Q]
    pdy = torch.gather(dy, 2, gather_index)
    local = torch.stack([cos * pdx + sin * pdy, cos * pdy - sin * pdx], dim=4)  # [B, A, K, Q, 2]
    valid = torch.gather(map_valid[:, None, :].expand(b, a, p), 2, pick)  # [B, A, K]
    return local, valid


def round_to_f32(value: float) -> float:
    """`value` rounded to the nearest f32, as a Python float."""
    return struct.unpack("f", struct.pack("f", value))[0]


def pair_features(
    x: Tensor, anchors: tuple[Tensor, ...], c: ModelConfig, pairs: AgentPairs
) -> Tensor:
    """Every (query i, key j) pair of every slot (agent_pairs.rs, `pair_features_of`):
    `x [B, A, W, 3]` → `[B·W, A (query), A (key), F]`."""
    b, a, w, _ = x.shape
    # Length scales in state units, rounded to f32 as PairScales does (in plain Python: a
    # tensor's float() breaks torch.compile's graph).
    direction = round_to_f32(pairs.direction_scale_m / c.position_scale_m)
    near = round_to_f32(pairs.near_scale_m / c.position_scale_m)
    far = round_to_f32(pairs.far_scale_m / c.position_scale_m)
    xt = x.transpose(1, 2)  # [B, W, A, 3]
    query = xt[:, :, :, None, :]  # [B, W, A, 1, 3]
    key = xt[:, :, None, :, :]  # [B, W, 1, A, 3]
    dx = key[..., 0] - query[..., 0]  # [B, W, A, A]
    dy = key[..., 1] - query[..., 1]
    _, _, cos, sin = (t[:, None, :, None] for t in anchors)  # [B, 1, A, 1]: the query's anchor
    forward = dx * cos + dy * sin
    left = dy * cos - dx * sin
    distance = (forward * forward + left * left).sqrt()
    squash = 1.0 / (distance + direction)
    dh = (key[..., 2] - query[..., 2]) / c.heading_scale
    features = torch.stack(
        [
            forward * squash,
            left * squash,
            (-distance / near).exp(),
            (-distance / far).exp(),
            dh.cos(),
            dh.sin(),
        ],
        dim=4,
    )  # [B, W, A, A, F]
    return features.reshape(b * w, a, a, PAIR_FEATURES)


class Denoiser(nn.Module):
    """`D(x; σ)` with the parameter names of the checkpoint (`blocks.0.time.q.weight`, …)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        c = config
        d = c.hidden
        self.config = c
        self.embed_state = nn.Linear(3, d)
        self.embed_noise = nn.Linear(1, d)
        self.embed_agent = nn.Linear(AGENT_FEATURES, d)
        self.embed_relative = (
            nn.Linear(c.agent_frame.relative_features(), d) if c.agent_frame else None
        )
        self.slot_embedding = nn.Parameter(torch.zeros(c.window_slots, d))  # [W, D]
        self.map_point = nn.Linear(2, d)
        self.map_point_embedding = nn.Parameter(torch.zeros(c.polyline_points, d))  # [Q, D]
        self.map_mix = nn.Linear(d, d)
        self.ln_map_out = nn.LayerNorm(d, eps=LN_EPS)
        self.blocks = nn.ModuleList(Block(c) for _ in range(c.blocks))
        self.ln_out = nn.LayerNorm(d, eps=LN_EPS)
        self.head = nn.Linear(d, 3)

    def use_sdpa(self, on: bool = True) -> None:
        """Attention without pair features (over time, the map, and agents when the model
        has no pairs) through `scaled_dot_product_attention` instead of written-out
        products: the same function, rounded differently (a speed option for training)."""
        for module in self.modules():
            if isinstance(module, Attention):
                module.sdpa = on

    def encode_polylines(self, points: Tensor) -> Tensor:
        """`points [N, P, Q, 2]` → `[N, P, D]`: per-point MLP, max over Q, norm."""
        x = torch.relu(self.map_point(points) + self.map_point_embedding)  # [N, P, Q, D]
        x = self.map_mix(x).amax(dim=2)  # [N, P, D]
        return self.ln_map_out(x)

    def preconditioning(self, sigma: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`sigma [B, W]` → (c_skip, c_out, c_in, c_noise), each `[B, 1, W, 1]`."""
        b, w = sigma.shape
        s = sigma.reshape(b, 1, w, 1)
        c_skip, c_out, c_in = skip_out_in(s, self.config.sigma_data)
        c_noise = (sigma.log() * 0.25).reshape(b, 1, w, 1)
        return c_skip, c_out, c_in, c_noise

    def forward(
        self,
        x_noisy: Tensor,
        sigma: Tensor,
        valid: Tensor,
        agent_features: Tensor,
        map_points: Tensor,
        map_valid: Tensor,
    ) -> Tensor:
        """`D(x; σ)`: `x_noisy [B, A, W, 3]`, `sigma [B, W]` (> 0), `valid [B, A, W]` (0/1),
        `agent_features [B, A, 6]`, `map_points [B, P, Q, 2]` (scene frame), `map_valid [B, P]`
        → `[B, A, W, 3]`."""
        out = self.forward_parts(x_noisy, sigma, valid, agent_features, map_points, map_valid)
        return out.denoised(x_noisy)

    def forward_parts(
        self,
        x_noisy: Tensor,
        sigma: Tensor,
        valid: Tensor,
        agent_features: Tensor,
        map_points: Tensor,
        map_valid: Tensor,
    ) -> Outputs:
        """The network's output `F` and the preconditioning that forms `D` from it (the EDM
        loss is written on `F`: scripts/torch_train.py, model.rs `edm_error_sum`)."""
        c = self.config
        b, a, w, _ = x_noisy.shape
        if w != c.window_slots:
            raise ValueError(f"window of {w} slots, the model has {c.window_slots}")
        d = c.hidden
        c_skip, c_out, c_in, c_noise = self.preconditioning(sigma)
        # Invalid tokens carry zeros in, so that nothing of theirs leaks even before masking.
        valid4 = valid.unsqueeze(3)  # [B, A, W, 1]
        x_in = x_noisy * c_in * valid4
        h = self.embed_state(x_in)  # [B, A, W, D]
        noise = self.embed_noise(c_noise)  # [B, 1, W, D]
        agent = self.embed_agent(agent_features).unsqueeze(2)  # [B, A, 1, D]
        h = h + noise + agent + self.slot_embedding.reshape(1, 1, w, d)

        frame = None
        residual = None
        spec = c.agent_frame
        if spec is not None:
            assert self.embed_relative is not None
            frame = anchor_frame(
                x_noisy, valid, spec.anchor_slot, c.heading_scale, spec.residual_scale is not None
            )
            if spec.residual_scale is None:
                scale = c_in * spec.relative_scale * valid4
                rel = relative_features(frame, x_noisy - frame.anchor, scale)  # [B, A, W, 4]
            else:
                residual = residual_of(
                    frame, x_noisy, sigma, spec.anchor_slot, spec.residual_scale, c.sigma_data
                )
                scale = residual.c_in * spec.relative_scale * valid4
                rel = torch.cat(
                    [
                        relative_features(frame, residual.y, scale),  # [B, A, W, 4]
                        step_features(frame, spec.residual_scale, w),  # [B, A, W, 2]
                    ],
                    dim=3,
                )
            h = h + self.embed_relative(rel)

        time_bias = key_bias(valid).reshape(b * a, 1, 1, w)
        agent_bias = key_bias(valid.transpose(1, 2)).reshape(b * w, 1, 1, a)

        anchors = None
        if spec is not None:
            anchors = anchors_of(x_noisy, valid, spec.anchor_slot, c.heading_scale)
        if c.agent_map_polylines is None:
            p = map_valid.shape[1]
            map_keys = MapKeys(
                self.encode_polylines(map_points), key_bias(map_valid).reshape(b, 1, 1, p), False
            )
        else:
            assert anchors is not None
            local, local_valid = agent_maps(anchors, map_points, map_valid, c.agent_map_polylines)
            k, q = local.shape[2], local.shape[3]
            map_keys = MapKeys(
                self.encode_polylines(local.reshape(b * a, k, q, 2)),  # [B·A, K, D]
                key_bias(local_valid).reshape(b * a, 1, 1, k),
                True,
            )

        pairs = None
        if c.agent_pairs is not None:
            assert anchors is not None
            pairs = pair_features(x_noisy, anchors, c, c.agent_pairs)  # [B·W, A, A, F]

        for block in self.blocks:
            h = block(h, time_bias, agent_bias, map_keys, pairs)
        out = self.head(self.ln_out(h))  # [B, A, W, 3], the anchor frame's orientation
        if frame is not None:
            f0, f1, f2 = out[..., 0:1], out[..., 1:2], out[..., 2:3]
            out = torch.cat(
                [f0 * frame.cos - f1 * frame.sin, f0 * frame.sin + f1 * frame.cos, f2], dim=3
            )
        raw = out * valid4  # F, zero at invalid tokens
        return Outputs(raw, c_skip, c_out, residual)


@dataclass
class Outputs:
    """`F` (zero at invalid tokens) and what turns it into `D(x; σ)`."""

    raw: Tensor  # [B, A, W, 3]
    c_skip: Tensor  # [B, 1, W, 1]
    c_out: Tensor  # [B, 1, W, 1]
    residual: Residual | None

    def denoised(self, x_noisy: Tensor) -> Tensor:
        if self.residual is None:
            return x_noisy * self.c_skip + self.raw * self.c_out
        # D = reference + (c_skip(σ·s)·y + c_out(σ·s)·F) / s.
        r = self.residual
        y = r.y * r.c_skip + self.raw * r.c_out
        return r.reference + y / r.scale


def load_denoiser(checkpoint: Path, device: torch.device) -> Denoiser:
    """A checkpoint folder → the mirror with its EMA weights; every tensor's name and shape is
    checked (missing, unexpected or misshapen tensors are an error, as in checkpoint.rs)."""
    config = load_config(checkpoint)
    model = Denoiser(config)
    tensors = load_file(str(checkpoint / "weights.safetensors"))
    expected = {name: tuple(t.shape) for name, t in model.state_dict().items()}
    problems = [f"missing tensor `{n}`" for n in sorted(set(expected) - set(tensors))]
    problems += [f"unexpected tensor `{n}`" for n in sorted(set(tensors) - set(expected))]
    problems += [
        f"tensor `{n}` has shape {list(tensors[n].shape)}, the config needs {list(s)}"
        for n, s in sorted(expected.items())
        if n in tensors and tuple(tensors[n].shape) != s
    ]
    if problems:
        raise ValueError(f"{checkpoint}: weights do not match the config: " + "; ".join(problems))
    model.load_state_dict({n: t.to(torch.float32) for n, t in tensors.items()}, strict=True)
    return model.to(device).eval()


# --------------------------------------------------------------------------------------------
# Inputs: synthetic scenes of plausible shapes (bench, check) and the fixture.
# --------------------------------------------------------------------------------------------


@dataclass
class Inputs:
    x_noisy: Tensor  # [B, A, W, 3]
    valid: Tensor  # [B, A, W]
    agent_features: Tensor  # [B, A, 6]
    map_points: Tensor  # [B, P, Q, 2]
    map_valid: Tensor  # [B, P]

    def to(self, device: torch.device) -> Inputs:
        return Inputs(*(t.to(device) for t in vars(self).values()))

    def denoise(self, model: Denoiser | Any, sigma: Tensor) -> Tensor:
        """`model`'s denoised estimate of these inputs at noise levels `sigma` [B, W]."""
        return model(
            self.x_noisy, sigma, self.valid, self.agent_features, self.map_points, self.map_valid
        )


def synthetic_scenes(
    c: ModelConfig, scenes: int, agents: list[int], polylines: list[int], generator: torch.Generator
) -> tuple[Inputs, Tensor]:
    """Scenes of agents driving straight at 2–12 m/s (state units: 40 m, rad·heading_scale),
    some steps missing, padded to the largest agent and polyline counts; lane polylines as
    gently bending lines. Returns the clean-state inputs and the standard-normal draws `[B, A,
    W, 3]` to noise them with."""
    w, q = c.window_slots, c.polyline_points
    a_max, p_max = max(agents), max(polylines)
    g = generator
    unit = c.position_scale_m
    x0 = torch.zeros(scenes, a_max, w, 3)
    valid = torch.zeros(scenes, a_max, w)
    features = torch.zeros(scenes, a_max, AGENT_FEATURES)
    points = torch.zeros(scenes, p_max, q, 2)
    map_valid = torch.zeros(scenes, p_max)
    slots = torch.arange(w, dtype=torch.float32)
    for s in range(scenes):
        for i in range(agents[s]):
            start = (torch.rand(2, generator=g) * 2 - 1) * 1.0  # within ±40 m of the centre
            heading = float(torch.rand(1, generator=g)) * 2 * math.pi - math.pi
            speed = (2 + 10 * float(torch.rand(1, generator=g))) / unit * 0.1  # units per step
            turn = float(torch.randn(1, generator=g)) * 0.02  # rad per step
            headings = heading + turn * slots
            x0[s, i, :, 0] = start[0] + torch.cumsum(speed * torch.cos(headings), 0)
            x0[s, i, :, 1] = start[1] + torch.cumsum(speed * torch.sin(headings), 0)
            x0[s, i, :, 2] = headings * c.heading_scale
            valid[s, i] = 1.0
            features[s, i, 0] = 0.8 + 0.4 * float(torch.rand(1, generator=g))
            features[s, i, 1] = 0.7 + 0.2 * float(torch.rand(1, generator=g))
            features[s, i, 2 + int(torch.randint(0, 4, (1,), generator=g))] = 1.0
        for poly in range(polylines[s]):
            start = (torch.rand(2, generator=g) * 2 - 1) * 1.2
            heading = float(torch.rand(1, generator=g)) * 2 * math.pi
            bend = float(torch.randn(1, generator=g)) * 0.05
            along = torch.arange(q, dtype=torch.float32)
            headings = heading + bend * along
            points[s, poly, :, 0] = start[0] + torch.cumsum(0.05 * torch.cos(headings), 0)
            points[s, poly, :, 1] = start[1] + torch.cumsum(0.05 * torch.sin(headings), 0)
            map_valid[s, poly] = 1.0
    noise = torch.randn(scenes, a_max, w, 3, generator=g)
    return Inputs(x0, valid, features, points, map_valid), noise


def rolling_sigma(c: ModelConfig, scenes: int, obs_slots: int) -> Tensor:
    """A rolling-style σ row per scene: observed slots at σ_min 0.002, future slots rising
    geometrically to 10. `[B, W]`."""
    w = c.window_slots
    future = w - obs_slots
    row = [0.002] * obs_slots + [
        0.05 * (10.0 / 0.05) ** (i / max(future - 1, 1)) for i in range(future)
    ]
    return torch.tensor(row, dtype=torch.float32).expand(scenes, w).contiguous()


# --------------------------------------------------------------------------------------------
# make-fixture
# --------------------------------------------------------------------------------------------

FIXTURE_SIZES = {
    # A tiny model with every option road20-wide uses: agent frame with a constant-velocity
    # residual, agent maps and agent pairs; two blocks so that block indices are exercised.
    "run.model": {
        "hidden": 16,
        "heads": 2,
        "blocks": 2,
        "mlp_ratio": 2,
        "window_slots": 7,
        "polyline_points": 4,
        "map_polylines": 6,
    },
    "run.model.agent_frame": {"anchor_slot": 2},
    "run.model.agent_map": {"polylines": 3},
    "run.planner": {"obs_slots": 3, "future_slots": 4},  # K = 40 is a multiple of F
}


def fixture_config_toml(template: str, parameters: int) -> str:
    """A real checkpoint's config.toml with the tiny sizes: line edits inside the named tables,
    so that everything else (planner, train, data) stays what the Rust loader accepts."""
    out: list[str] = []
    table = ""
    edited: set[tuple[str, str]] = set()
    header = {
        "step": "0",
        "parameters": str(parameters),
        "wall_secs": "0.0",
        "hardware": '"none: weights drawn by scripts/torch_denoiser.py make-fixture"',
    }
    for line in template.splitlines():
        m = re.match(r"^\[([^\]]+)\]\s*$", line)
        if m:
            table = m.group(1)
        kv = re.match(r"^(\w+)\s*=", line)
        if kv and table == "" and kv.group(1) in ("validation_loss", "untrained_validation_loss"):
            continue  # no training happened
        if kv and table == "" and kv.group(1) in header:
            line = f"{kv.group(1)} = {header[kv.group(1)]}"
        elif kv and table == "run" and kv.group(1) == "name":
            line = 'name = "torch-parity"'
        elif kv and table == "run.train" and kv.group(1) == "init_from":
            continue
        elif kv and kv.group(1) in FIXTURE_SIZES.get(table, {}):
            line = f"{kv.group(1)} = {FIXTURE_SIZES[table][kv.group(1)]}"
            edited.add((table, kv.group(1)))
        out.append(line)
    wanted = {(t, k) for t, keys in FIXTURE_SIZES.items() for k in keys}
    if edited != wanted:
        raise ValueError(f"template lacks {sorted(wanted - edited)}")
    return (
        "# The torch-parity fixture: scripts/torch_denoiser.py make-fixture (random weights).\n"
        + "\n".join(out)
        + "\n"
    )


def random_weights(model: Denoiser, generator: torch.Generator) -> dict[str, Tensor]:
    """Every tensor drawn at a scale where no part is negligible: linear weights N(0, 1/fan_in),
    biases and embeddings N(0, 0.3²), layer norms 1 + N(0, 0.2²) and N(0, 0.2²), pair weights
    N(0, 0.5²) (not zero as in training's init: the parity must see them)."""
    out: dict[str, Tensor] = {}
    for name, t in model.state_dict().items():
        z = torch.randn(t.shape, generator=generator)
        leaf = name.rsplit(".", 2)[-2] if "." in name else ""
        if name.endswith((".pair_k", ".pair_v")):
            v = 0.5 * z
        elif leaf.startswith("ln_"):
            v = 1.0 + 0.2 * z if name.endswith(".weight") else 0.2 * z
        elif name.endswith(".weight"):
            v = z / math.sqrt(t.shape[1])
        else:
            v = 0.3 * z
        out[name] = v.contiguous()
    return out


def make_fixture(out: Path, template: Path, seed: int, checkpoint: Path | None) -> None:
    """The committed fixture (a tiny model, random weights from `template`'s config), or with
    `checkpoint` a fixture of that checkpoint's own config and weights (megabytes: for a one-off
    check of a shipped model, not for committing)."""
    g = torch.Generator().manual_seed(seed)
    out.mkdir(parents=True, exist_ok=True)
    if checkpoint is None:
        with open(template, "rb") as f:
            template_text = f.read().decode()
        # Build the model from the edited config, as the Rust loader will.
        probe = fixture_config_toml(template_text, 0)
        config = parse_model_config(tomllib.loads(probe)["run"]["model"])
        model = Denoiser(config)
        weights = random_weights(model, g)
        model.load_state_dict(weights, strict=True)
        model.eval()
        parameters = sum(t.numel() for t in weights.values())
        (out / "config.toml").write_text(fixture_config_toml(template_text, parameters))
        save_file(weights, str(out / "weights.safetensors"))
        # Three scenes of 4, 2 and 3 agents (padded to 4) and 5, 2 and 6 polylines (padded to
        # 6; scene 1 has fewer than K = 3, so its agents' maps hold padding).
        agents, polylines = [4, 2, 3], [5, 2, 6]
    else:
        model = load_denoiser(checkpoint, torch.device("cpu"))
        config = model.config
        parameters = sum(p.numel() for p in model.parameters())
        (out / "config.toml").write_bytes((checkpoint / "config.toml").read_bytes())
        # The tensors just loaded, not the file again: a training run may replace it meanwhile.
        save_file(
            {n: t.contiguous() for n, t in model.state_dict().items()},
            str(out / "weights.safetensors"),
        )
        agents, polylines = [9, 4, 6], [config.map_polylines, 5, config.map_polylines - 3]

    inputs, noise = synthetic_scenes(config, 3, agents, polylines, g)
    valid = inputs.valid
    w = config.window_slots
    anchor = config.agent_frame.anchor_slot if config.agent_frame else w // 2
    valid[0, 1, anchor] = 0.0  # no anchor: scene frame, no residual reference
    valid[0, 2, anchor - 1] = 0.0  # anchor but no previous step: zero constant velocity
    valid[0, 3, anchor + 2 :] = 0.0  # leaves the scene
    valid[1, 0, 0] = 0.0  # enters late
    valid[2, 2, :] = 0.0  # present in no slot (all keys of its time attention masked)
    # Noisy states: x0 + 0.05 ε everywhere, padding and invalid slots included (both sides
    # must mask them, whatever they hold). One x for every σ case, so σ alone tells them apart.
    x_noisy = inputs.x_noisy + 0.05 * noise
    inputs = Inputs(x_noisy, valid, inputs.agent_features, inputs.map_points, inputs.map_valid)
    b = 3
    obs = anchor + 1
    sigma = torch.stack(
        [
            rolling_sigma(config, b, obs),
            torch.full((b, w), 0.02),
            torch.full((b, w), 1.5),
            # A different σ row per scene.
            torch.tensor([[0.3] * w, [0.002] * obs + [4.0] * (w - obs), [80.0] * w]),
        ]
    )  # [C, B, W]
    with torch.no_grad():
        expected = torch.stack(
            [
                inputs.denoise(model, sigma[case])
                for case in range(sigma.shape[0])
            ]
        )  # [C, B, A, W, 3]
    save_file(
        {
            "x_noisy": inputs.x_noisy.contiguous(),
            "sigma": sigma.contiguous(),
            "valid": inputs.valid.contiguous(),
            "agent_features": inputs.agent_features.contiguous(),
            "map": inputs.map_points.contiguous(),
            "map_valid": inputs.map_valid.contiguous(),
        },
        str(out / "inputs.safetensors"),
    )
    save_file({"denoised": expected.contiguous()}, str(out / "expected.safetensors"))
    size = sum(p.stat().st_size for p in out.iterdir())
    print(
        f"wrote {out}: {parameters} parameters, sigma cases {sigma.shape[0]}, "
        f"denoised {list(expected.shape)}, {size} bytes"
    )


# --------------------------------------------------------------------------------------------
# check and bench
# --------------------------------------------------------------------------------------------


def bench_inputs(
    c: ModelConfig, batch: int, agents: int, device: torch.device
) -> tuple[Inputs, Tensor]:
    """`batch` scenes of `agents` agents (a few slots missing), the checkpoint's window and map
    sizes, noised along a rolling σ row."""
    g = torch.Generator().manual_seed(1234)
    # Generate a few distinct scenes and tile them: Python loops over 512 scenes take seconds.
    distinct = min(batch, 8)
    base, noise = synthetic_scenes(
        c, distinct, [agents] * distinct, [c.map_polylines] * distinct, g
    )
    repeat = (batch + distinct - 1) // distinct

    def tile(t: Tensor) -> Tensor:  # [distinct, …] → [batch, …]
        return t.repeat(repeat, *([1] * (t.dim() - 1)))[:batch].contiguous()

    inputs = Inputs(*(tile(t) for t in vars(base).values()))
    noise = tile(noise)
    inputs.valid[:, -1, : c.window_slots // 2] = 0.0  # one agent enters late
    obs = c.agent_frame.anchor_slot + 1 if c.agent_frame else c.window_slots // 2
    sigma = rolling_sigma(c, batch, obs)
    x_noisy = inputs.x_noisy + sigma[:, None, :, None] * noise
    inputs = Inputs(
        x_noisy, inputs.valid, inputs.agent_features, inputs.map_points, inputs.map_valid
    )
    return inputs.to(device), sigma.to(device)


def check(checkpoint: Path, device: torch.device) -> None:
    """Loads a real checkpoint and runs it on synthetic scenes: finite outputs along a rolling σ
    row, and on nearly clean states at σ_min everywhere (c_skip ≈ 1) the denoiser moves its
    input little (median over valid tokens under 0.02 units, 0.8 m; the synthetic scenes are
    not INTERACTION's, so single tokens move more): a smoke test of loading and wiring, not of
    quality (the parity fixture is the correctness test)."""
    model = load_denoiser(checkpoint, device)
    c = model.config
    inputs, sigma = bench_inputs(c, 4, 8, device)
    g = torch.Generator().manual_seed(99)
    clean, noise = synthetic_scenes(
        c, 4, [8, 5, 8, 3], [c.map_polylines, 10, 20, c.map_polylines], g
    )
    sigma_min = 0.002
    clean = Inputs(clean.x_noisy + sigma_min * noise, *list(vars(clean).values())[1:]).to(device)
    with torch.no_grad():
        d = inputs.denoise(model, sigma)
        small = torch.full((4, c.window_slots), sigma_min, device=device)
        d_small = clean.denoise(model, small)
    moved = (d_small - clean.x_noisy).abs().amax(dim=3)[clean.valid.bool()]  # per valid token
    report = {
        "checkpoint": str(checkpoint),
        "config": {k: str(v) for k, v in vars(c).items()},
        "parameters": sum(p.numel() for p in model.parameters()),
        "finite": bool(torch.isfinite(d).all() and torch.isfinite(d_small).all()),
        "max_abs_output": d[inputs.valid.bool()].abs().max().item(),
        "median_change_at_sigma_min": moved.median().item(),
        "max_change_at_sigma_min": moved.max().item(),
    }
    print(json.dumps(report, indent=2))
    if not report["finite"] or report["median_change_at_sigma_min"] > 0.02:
        raise SystemExit("check failed: non-finite outputs or D(x; σ_min) far from x")


def time_forward(
    model: Denoiser | Any, inputs: Inputs, sigma: Tensor, device: torch.device, min_secs: float
) -> float:
    """Seconds per denoiser evaluation (after warm-up), timed over at least `min_secs`."""

    def once() -> Tensor:
        return inputs.denoise(model, sigma)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    with torch.inference_mode():
        for _ in range(3):
            once()
        sync()
        # Chunks of calls between synchronisations, doubled until the time is long enough:
        # a sync per call would time the launch latency, not the throughput.
        chunk = 1
        while True:
            start = time.perf_counter()
            for _ in range(chunk):
                once()
            sync()
            elapsed = time.perf_counter() - start
            if elapsed >= min_secs:
                return elapsed / chunk
            chunk *= 2


def gemm_reference(
    config: Any, batches: list[int], agents: int, device: torch.device, min_secs: float
) -> list[dict[str, Any]]:
    """The vendor library's matrix product at the model's largest linear shape (the MLP's
    first layer over every agent slot: rows = batch x agents x W, D in, mlp_ratio x D out), in
    fp32 (TF32 as the bench's flag says) and f16, and at 8192^3: what a hand-written kernel is
    measured against (issue 40). CUDA only; a failure is a row with its error."""
    if device.type != "cuda":
        return []
    shapes = [
        (batch * agents * config.window_slots, config.hidden, config.hidden * config.mlp_ratio)
        for batch in batches
        if batch >= 64
    ]
    shapes.append((8192, 8192, 8192))
    rows: list[dict[str, Any]] = []
    for m, k, n in shapes:
        for dtype in (torch.float32, torch.float16):
            try:
                a = torch.randn(m, k, device=device, dtype=dtype)
                b = torch.randn(k, n, device=device, dtype=dtype)
                for _ in range(3):
                    torch.matmul(a, b)
                torch.cuda.synchronize(device)
                chunk = 1
                while True:
                    start = time.perf_counter()
                    for _ in range(chunk):
                        torch.matmul(a, b)
                    torch.cuda.synchronize(device)
                    elapsed = time.perf_counter() - start
                    if elapsed >= min_secs / 4:
                        break
                    chunk *= 2
                secs = elapsed / chunk
                rows.append(
                    {
                        "m": m,
                        "k": k,
                        "n": n,
                        "dtype": str(dtype).removeprefix("torch."),
                        "ms_per_product": secs * 1e3,
                        "tflops": 2.0 * m * k * n / secs / 1e12,
                    }
                )
                del a, b
            except Exception as e:  # out of memory at a large batch: say so, go on
                rows.append({"m": m, "k": k, "n": n, "error": f"{type(e).__name__}: {e}"[:300]})
            print(f"gemm {rows[-1]}", file=sys.stderr)
    return rows


def bench(
    checkpoint: Path,
    batches: list[int],
    agents: int,
    device: torch.device,
    compile_too: bool,
    min_secs: float,
    json_out: Path | None,
) -> None:
    """Prints a table and, as its last line, the JSON (also written to `json_out`)."""
    model = load_denoiser(checkpoint, device)
    variants: list[tuple[str, Any]] = [("eager", model)]
    if compile_too:
        variants.append(("compile", torch.compile(model)))
    rows = []
    for name, fn in variants:
        for batch in batches:
            inputs, sigma = bench_inputs(model.config, batch, agents, device)
            try:
                secs = time_forward(fn, inputs, sigma, device, min_secs)
            except Exception as e:  # torch.compile may fail to build on a machine: say so, go on
                rows.append(
                    {"variant": name, "batch": batch, "error": f"{type(e).__name__}: {e}"[:300]}
                )
                print(f"{name:8} {batch:6}  failed: {rows[-1]['error']}", file=sys.stderr)
                continue
            rows.append(
                {
                    "variant": name,
                    "batch": batch,
                    "agents": agents,
                    "ms_per_call": secs * 1e3,
                    "scene_evals_per_s": batch / secs,
                }
            )
    gemm_rows = gemm_reference(model.config, batches, agents, device, min_secs)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(
        f"# {checkpoint} on {name}, torch {torch.__version__}, fp32, {agents} agents, "
        f"W={model.config.window_slots}, P={model.config.map_polylines}"
    )
    print(f"{'variant':8} {'batch':>6} {'ms/call':>10} {'scene-evals/s':>14}")
    for r in rows:
        if "error" not in r:
            print(
                f"{r['variant']:8} {r['batch']:6} {r['ms_per_call']:10.3f}"
                f" {r['scene_evals_per_s']:14.1f}"
            )
    result = json.dumps(
        {
            "checkpoint": str(checkpoint),
            "device": name,
            "torch": torch.__version__,
            "tf32": torch.backends.cuda.matmul.allow_tf32,
            "rows": rows,
            "gemm": gemm_rows,
        }
    )
    print(result)
    if json_out is not None:
        json_out.write_text(result + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    fixture = sub.add_parser("make-fixture", help="write the torch-parity fixture")
    fixture.add_argument("--out", type=Path, required=True)
    fixture.add_argument(
        "--template",
        type=Path,
        default=Path("models/road20-wide4/config.toml"),
        help="a real checkpoint's config.toml whose sizes are replaced",
    )
    fixture.add_argument("--seed", type=int, default=15)
    fixture.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="use this checkpoint's config and weights instead (not committed)",
    )
    chk = sub.add_parser("check", help="run a real checkpoint on synthetic scenes")
    chk.add_argument("--checkpoint", type=Path, required=True)
    chk.add_argument("--device", default="cpu")
    bn = sub.add_parser("bench", help="time one denoiser evaluation over batch sizes")
    bn.add_argument("--checkpoint", type=Path, required=True)
    bn.add_argument("--batches", type=int, nargs="+", default=[1, 16, 128, 512])
    bn.add_argument("--agents", type=int, default=10)
    bn.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    bn.add_argument("--compile", action="store_true", help="also time torch.compile")
    bn.add_argument("--allow-tf32", action="store_true", help="TF32 matrix products (not fp32)")
    bn.add_argument("--min-secs", type=float, default=1.0, help="timing per batch size")
    bn.add_argument("--json-out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    # fp32 means fp32: the mirror's outputs are compared with candle's.
    torch.backends.cuda.matmul.allow_tf32 = bool(getattr(args, "allow_tf32", False))
    torch.backends.cudnn.allow_tf32 = bool(getattr(args, "allow_tf32", False))
    if args.command == "make-fixture":
        make_fixture(args.out, args.template, args.seed, args.checkpoint)
    elif args.command == "check":
        check(args.checkpoint, torch.device(args.device))
    else:
        bench(
            args.checkpoint,
            args.batches,
            args.agents,
            torch.device(args.device),
            args.compile,
            args.min_secs,
            args.json_out,
        )


if __name__ == "__main__":
    main()
