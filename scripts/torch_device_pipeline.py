"""The device-resident batch pipeline of `torch_train.py` (`train --pipeline device`, and `bench`'s
`+device` variants): the training split materialised on the device once, each step's batch
gathered there by index. The same sampling as torch_train.py's `sample_scenes` and the same
collation as its `collate`, with other random streams (numpy's drawn per batch, not per scene;
the noise torch's, on the device), so a run of this pipeline is not the host pipeline's run.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch_denoiser as td
from torch import Tensor
from torch_train_data import AgentBuckets, Edm, ExportedSplit, Run, step_rng


def edm_sigma(e: Edm, u: np.ndarray) -> np.ndarray:
    """`Edm.sigma` of an f64 array."""
    u = np.clip(u, 0.0, 1.0)
    inv_rho = 1.0 / e.rho
    lo = e.sigma_min**inv_rho
    hi = e.sigma_max**inv_rho
    return np.where(u == 0.0, 0.0, (lo + u * (hi - lo)) ** e.rho)


def task_sigmas(run: Run, warmup: np.ndarray, tau: np.ndarray, u_ca: np.ndarray) -> np.ndarray:
    """`task_sigma_of` of a batch of tasks: `[B, W]` f32."""
    w, n = run.model.window_slots, run.obs_slots
    f = w - n
    e = run.edm
    k = np.arange(f, dtype=np.float64)[None, :]
    tau = tau[:, None]
    if run.rolling:
        u = np.where(warmup[:, None], k / f + tau, (k + tau) / f)
    else:
        u = np.broadcast_to(tau, (len(tau), f))
    obs = np.maximum(edm_sigma(e, u_ca), e.sigma_min)[:, None]
    future = np.maximum(edm_sigma(e, np.clip(u, 0.0, 1.0)), e.sigma_min)
    return np.concatenate([np.broadcast_to(obs, (len(tau), n)), future], axis=1).astype(np.float32)


@dataclass
class BatchDraw:
    """One batch's draws (`sample_scenes`' choices, vectorised): `[B]` each."""

    window: np.ndarray  # i64
    start: np.ndarray  # i64
    angle: np.ndarray  # f64, 0 without rotations
    sigma: np.ndarray  # [B, W] f32


def draw_batch(
    run: Run,
    windows: int,
    steps: int,
    buckets: AgentBuckets | None,
    rng: np.random.Generator,
    rotate: bool,
    first: int | None = None,
) -> BatchDraw:
    """`sample_scenes`' draws for a whole batch at once: the first window uniform (or
    `first`), the others uniform within its agent-count bucket, a uniform crop, an optional
    rotation, the task."""
    t = run.train
    b, w = t.batch_scenes, run.model.window_slots
    drawn = int(rng.integers(windows))
    first = drawn if first is None else first
    if buckets is not None:
        members = buckets.members[buckets.bucket_of[first]]
        rest = members[rng.integers(len(members), size=b - 1)]
    else:
        rest = rng.integers(windows, size=b - 1)
    window = np.concatenate([[first], rest]).astype(np.int64)
    start = rng.integers(steps - w + 1, size=b).astype(np.int64)
    angle = rng.uniform(0.0, 2.0 * math.pi, b) if rotate else np.zeros(b)
    tau = rng.random(b)
    warmup = rng.random(b) < t.warmup_task_prob if run.rolling else np.zeros(b, bool)
    u_ca = rng.uniform(0.0, t.augmentation_ratio, b) if t.augmentation_ratio > 0 else np.zeros(b)
    return BatchDraw(window, start, angle, task_sigmas(run, warmup, tau, u_ca))


class DeviceData:
    """The training split materialised on `device`: every window's agents over all its
    steps (`ExportedSplit.scenes`' arithmetic: a crop of them is what `scenes` makes of that
    crop, bit for bit) and its nearest `map_polylines` lanelets, as flat arrays; the
    per-window counts and the validity stay on the host as well, for the index work."""

    def __init__(self, ds: ExportedSplit, c: td.ModelConfig, device: torch.device) -> None:
        started = time.monotonic()
        n = len(ds)
        self.windows = n
        self.steps = ds.steps
        self.heading_scale = c.heading_scale
        self.map_polylines = c.map_polylines
        self.agent_counts = ds.agent_counts.astype(np.int64)
        self.agent_offsets = (ds.window_agent_offsets - ds.window_agent_offsets[0]).astype(
            np.int64
        )
        rows = int(self.agent_offsets[-1])
        states = np.zeros((rows, ds.steps, 3), np.float32)
        valid = np.zeros((rows, ds.steps), bool)
        features = np.zeros((rows, td.AGENT_FEATURES), np.float32)
        q = ds.points
        polylines = np.zeros((n, c.map_polylines, q, 2), np.float32)
        counts = np.minimum(np.diff(ds.window_polyline_offsets), c.map_polylines)
        chunk = 2048
        for lo in range(0, n, chunk):
            hi = min(lo + chunk, n)
            r0, r1 = self.agent_offsets[lo], self.agent_offsets[hi]
            states[r0:r1], valid[r0:r1], features[r0:r1] = self._agents(ds, c, lo, hi)
            polylines[lo:hi] = self._polylines(ds, c, lo, hi, counts[lo:hi])
        self.valid_host = valid
        self.polyline_counts = counts.astype(np.int64)
        self.device = device
        self.states = torch.from_numpy(states).to(device).reshape(rows * ds.steps, 3)
        self.valid = torch.from_numpy(valid).to(device).reshape(rows * ds.steps)
        self.features = torch.from_numpy(features).to(device)
        self.polylines = torch.from_numpy(polylines).to(device)
        self.polyline_counts_device = torch.from_numpy(self.polyline_counts).to(device)
        size = sum(
            t.numel() * t.element_size()
            for t in (self.states, self.valid, self.features, self.polylines)
        )
        print(
            f"the training split on {device}: {n} windows, {rows} agent rows, "
            f"{size / 2**20:.0f} MiB, materialised in {time.monotonic() - started:.1f} s",
            flush=True,
        )

    @staticmethod
    def _agents(
        ds: ExportedSplit, c: td.ModelConfig, lo: int, hi: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Windows `lo..hi`'s agents over all steps (`ExportedSplit.agent_steps`)."""
        indices_a = np.arange(lo, hi, dtype=np.int64)
        agent_rows = np.arange(ds.window_agent_offsets[lo], ds.window_agent_offsets[hi])
        valid, xy, heading, features = ds.agent_steps(
            indices_a, agent_rows, ds.steps, c.heading_scale
        )
        states = np.zeros((*valid.shape, 3), np.float32)
        states[..., 0] = np.where(valid, xy[..., 0], 0.0)
        states[..., 1] = np.where(valid, xy[..., 1], 0.0)
        states[..., 2] = np.where(valid, heading, 0.0)
        return states, valid, features

    @staticmethod
    def _polylines(
        ds: ExportedSplit, c: td.ModelConfig, lo: int, hi: int, counts: np.ndarray
    ) -> np.ndarray:
        """Windows `lo..hi`'s nearest lanelets, `[n, map_polylines, Q, 2]`, zero-padded."""
        n = hi - lo
        index = np.zeros((n, c.map_polylines), np.int64)
        for j, i in enumerate(range(lo, hi)):
            lanelets = ds.window_polylines[
                ds.window_polyline_offsets[i] : ds.window_polyline_offsets[i + 1]
            ][: c.map_polylines]
            first = ds.map_lanelet_offsets[ds.recording_map[ds.window_recording[i]]]
            index[j, : len(lanelets)] = first + lanelets
        centres = ds.lanelet_centres[index]  # [n, P, Q, 2] f64
        origin = ds.window_origin_m[lo:hi][:, None, None, :]
        out = ((centres - origin) / ds.scale_m).astype(np.float32)
        out[np.arange(c.map_polylines)[None, :] >= counts[:, None]] = 0.0
        return out

    def batch(
        self, run: Run, draw: BatchDraw, noise: torch.Generator | Tensor
    ) -> dict[str, Tensor]:
        """`collate(sample_scenes(…))` of `draw`'s scenes, gathered on the device; `noise` a
        generator for the standard-normal draws or (the tests) the `[B, A, W, 3]` draws
        themselves. The index work (which agents, which rows) is the host's, from its own
        copies: nothing here waits for the device."""
        w = run.model.window_slots
        b = len(draw.window)
        window, start = draw.window, draw.start
        counts = self.agent_counts[window]
        a_win = max(1, int(counts.max()))
        slot = np.arange(a_win)
        in_window = slot[None, :] < counts[:, None]  # [B, A_w]
        rows = np.where(in_window, self.agent_offsets[window][:, None] + slot, 0)
        crop = start[:, None, None] + np.arange(w)  # [B, 1, W]
        # drop_absent_agents: agents without a valid slot in the crop go, unless none is valid.
        keep = self.valid_host[rows[:, :, None], crop].any(axis=2) & in_window
        none = ~keep.any(axis=1)
        keep[none] = in_window[none]
        kept = keep.sum(axis=1)
        a = max(1, int(kept.max()))
        order = np.argsort(~keep, axis=1, kind="stable")[:, :a]
        real = np.arange(a)[None, :] < kept[:, None]  # [B, A]
        rows = np.where(real, np.take_along_axis(rows, order, axis=1), 0)
        p = max(1, int(self.polyline_counts[window].max()))
        ints = np.concatenate([rows.reshape(-1), real.reshape(-1).astype(np.int64), window, start])
        floats = np.concatenate([draw.sigma.reshape(-1), draw.angle.astype(np.float32)]).astype(
            np.float32
        )
        dev = self.device
        pin = dev.type == "cuda"
        ints_t = torch.from_numpy(ints)
        floats_t = torch.from_numpy(floats)
        if pin:
            ints_t, floats_t = ints_t.pin_memory(), floats_t.pin_memory()
        ints_t = ints_t.to(dev, non_blocking=pin)
        floats_t = floats_t.to(dev, non_blocking=pin)
        rows_t, real_t, window_t, start_t = torch.split(ints_t, [b * a, b * a, b, b])
        rows_t = rows_t.reshape(b, a)
        real_t = real_t.reshape(b, a).bool()
        sigma_t = floats_t[: b * w].reshape(b, w)
        angle_t = floats_t[b * w :]
        flat = rows_t[:, :, None] * self.steps + (
            start_t[:, None, None] + torch.arange(w, device=dev)
        )  # [B, A, W]
        valid = self.valid[flat] & real_t[:, :, None]
        states = torch.where(valid[..., None], self.states[flat], 0.0)
        features = torch.where(real_t[..., None], self.features[rows_t], 0.0)
        points = self.polylines[window_t, :p]  # [B, P, Q, 2]
        map_valid = (
            torch.arange(p, device=dev)[None, :] < self.polyline_counts_device[window_t][:, None]
        ).float()
        if run.train.rotation_augmentation:
            # SceneInput.rotate: valid states and every map point turn.
            sin = angle_t.sin().reshape(b, 1, 1)
            cos = angle_t.cos().reshape(b, 1, 1)
            x, y, h = states[..., 0], states[..., 1], states[..., 2]
            turned = torch.stack(
                [
                    torch.where(valid, cos * x - sin * y, x),
                    torch.where(valid, sin * x + cos * y, y),
                    torch.where(
                        valid, h + angle_t.reshape(b, 1, 1) * np.float32(self.heading_scale), h
                    ),
                ],
                dim=3,
            )
            states = turned
            mx, my = points[..., 0], points[..., 1]
            s4, c4 = sin.reshape(b, 1, 1), cos.reshape(b, 1, 1)
            points = torch.stack([c4 * mx - s4 * my, s4 * mx + c4 * my], dim=3)
        if isinstance(noise, Tensor):
            eps = noise.to(dev)
        else:
            eps = torch.randn(b, a, w, 3, generator=noise, device=dev)
        x_noisy = torch.where(
            real_t[:, :, None, None], states + sigma_t[:, None, :, None] * eps, 0.0
        )
        return {
            "x0": states,
            "x_noisy": x_noisy,
            "sigma": sigma_t,
            "valid": valid.float(),
            "agent_features": features,
            "map": points,
            "map_valid": map_valid,
        }


def noise_seed(seed: int, step: int) -> int:
    """The torch generator's seed of step `step`'s noise (deterministic: exact resume)."""
    state = np.random.SeedSequence([seed, step, 0x5EED]).generate_state(2, np.uint32)
    return (int(state[0]) << 31) ^ int(state[1])


class DeviceBatches:
    """Training batches by step, gathered on the device from `DeviceData`."""

    def __init__(self, run: Run, data: DeviceData) -> None:
        self.run = run
        self.data = data
        self.buckets = AgentBuckets(data.agent_counts) if run.train.bucket_by_agents else None
        self.generator = torch.Generator(device=data.device)

    def get(self, step: int, last: int = 0, first: int | None = None) -> dict[str, Tensor]:
        """Step `step`'s batch (`first`: its first window instead of a drawn one)."""
        t = self.run.train
        draw = draw_batch(
            self.run,
            self.data.windows,
            self.data.steps,
            self.buckets,
            step_rng(t.seed, step),
            t.rotation_augmentation,
            first,
        )
        self.generator.manual_seed(noise_seed(t.seed, step))
        return self.data.batch(self.run, draw, self.generator)

    def close(self) -> None:
        pass
