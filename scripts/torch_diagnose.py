#!/usr/bin/env python3
"""Diagnostics of full-diffusion (DJINN, AR) checkpoints in the PyTorch mirror of the denoiser,
on the exported validation split (`road data export-torch`; docs/torch-training.md).

  history-noise  one-shot Heun samples of the future slots from the logged history, with and
                 without i.i.d. noise added to the observed positions (the model told they are
                 clean): how much an error in its history moves its first planned steps.
  closed-loop    DJINN MPC-1 in closed loop: every simulated step a fresh Heun sample of all
                 future slots from the emitted history, its first slot emitted; the distance to
                 the log and the size of the emitted acceleration against the log's.

docs/experiments/2026-11-26-baselines-d96.md, "DJINN-10 MPC-1 with road20-wide's recipe: why it
jitters", reads these (its djinn10-from-wide is retired: docs/experiments/models/djinn10-from-wide/).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torch_denoiser as td  # noqa: E402
import torch_train as tt  # noqa: E402
import torch_train_data as ttd  # noqa: E402

STEP_S = 0.1  # INTERACTION's frame interval


def heun_levels(edm: ttd.Edm, steps: int) -> list[float]:
    """EDM's Karras levels from σ_max to σ_min, then 0 (the Heun sampler's schedule)."""
    lo, hi = edm.sigma_min ** (1 / edm.rho), edm.sigma_max ** (1 / edm.rho)
    return [(hi + i / (steps - 1) * (lo - hi)) ** edm.rho for i in range(steps)] + [0.0]


def sample_future(
    model: td.Denoiser,
    batch: dict[str, torch.Tensor],
    obs_slots: int,
    edm: ttd.Edm,
    steps: int,
    generator: torch.Generator,
) -> torch.Tensor:
    """A Heun sample of the future slots of `batch["x0"]` (observed slots kept, told σ_min):
    `[B, A, W, 3]`."""
    levels = heun_levels(edm, steps)
    future = torch.zeros_like(batch["x0"])
    future[:, :, obs_slots:] = 1.0
    x = batch["x0"] + future * levels[0] * torch.randn(batch["x0"].shape, generator=generator)
    sigma = batch["sigma"].clone()
    sigma[:, :obs_slots] = edm.sigma_min

    def denoise(x: torch.Tensor, level: float) -> torch.Tensor:
        sigma[:, obs_slots:] = max(level, edm.sigma_min)
        return model(
            x, sigma, batch["valid"], batch["agent_features"], batch["map"], batch["map_valid"]
        )

    for s0, s1 in zip(levels[:-1], levels[1:]):
        d0 = (x - denoise(x, s0)) / s0
        x1 = x + future * (s1 - s0) * d0
        if s1 > 0:
            d1 = (x1 - denoise(x1, s1)) / s1
            x1 = x + future * (s1 - s0) * 0.5 * (d0 + d1)
        x = x1
    return x


def collate(scenes: list[ttd.SceneInput], window_slots: int) -> dict[str, torch.Tensor]:
    draw = tt.Draw(inputs=scenes)
    for s in scenes:
        draw.sigma.append(np.zeros(window_slots, np.float32))
        draw.noise.append(np.zeros_like(s.states))
    return {k: torch.from_numpy(v) for k, v in tt.collate(draw).items()}


def load(args: argparse.Namespace) -> tuple[ttd.Run, ttd.ExportedSplit]:
    run = ttd.load_run(Path(args.config), [])
    split = ttd.ExportedSplit(Path(args.export) / "validation.safetensors")
    if run.rolling:
        raise SystemExit(f"{args.config}: a rolling planner; these diagnostics are for full diffusion")
    return run, split


def history_noise(args: argparse.Namespace) -> None:
    run, split = load(args)
    n, w, scale_m = run.obs_slots, run.model.window_slots, run.model.position_scale_m
    rng = np.random.default_rng(args.seed)
    windows = [int(i) for i in rng.choice(len(split), args.scenes, replace=False)]
    starts = [int(rng.integers(split.steps - w + 1)) for _ in windows]
    print(f"{args.scenes} validation windows, K = {args.steps}; mean distance (m) of the sampled "
          f"future to the log at future slots 1, 2, 5, {w - n}")
    for checkpoint in args.checkpoints:
        model = td.load_denoiser(Path(checkpoint), torch.device("cpu"))
        for noise_m in args.noise_m:
            scenes = split.scenes(windows, starts, w, run.model)
            batch = collate(scenes, w)
            g = torch.Generator().manual_seed(args.seed)
            jitter = torch.randn(batch["x0"].shape, generator=g) * (noise_m / scale_m)
            jitter[:, :, n:] = 0.0
            jitter[..., 2] = 0.0
            clean = batch["x0"]
            batch["x0"] = clean + jitter * batch["valid"].unsqueeze(3)
            with torch.no_grad():
                x = sample_future(model, batch, n, run.edm, args.steps, g)
            both = batch["valid"][:, :, n - 1]
            row = []
            for k in (0, 1, 4, w - n - 1):
                m = batch["valid"][:, :, n + k] * both
                d = (x[:, :, n + k, :2] - clean[:, :, n + k, :2]).norm(dim=-1) * scale_m
                row.append(float((d * m).sum() / m.sum()))
            print(f"{checkpoint}, history noise {noise_m:.2f} m: " + " ".join(f"{v:.3f}" for v in row))


def closed_loop(args: argparse.Namespace) -> None:
    run, split = load(args)
    n, w, scale_m = run.obs_slots, run.model.window_slots, run.model.position_scale_m
    horizon = args.horizon
    if split.steps < n + horizon:
        raise SystemExit(f"the export's windows have {split.steps} steps; {n} + {horizon} needed")
    rng = np.random.default_rng(args.seed)
    windows = [int(i) for i in rng.choice(len(split), args.scenes, replace=False)]
    print(f"{args.scenes} validation windows, MPC-1 over {horizon} steps, K = {args.steps}")
    for checkpoint in args.checkpoints:
        model = td.load_denoiser(Path(checkpoint), torch.device("cpu"))
        logs = split.scenes(windows, [0] * len(windows), n + horizon, run.model)
        # Agents seen at the last observed step are model-driven; the others replay the log.
        driven = [s.valid[:, n - 1].copy() for s in logs]
        history = [s.states[:, :n].copy() for s in logs]
        history_valid = [s.valid[:, :n].copy() for s in logs]
        emitted: list[list[np.ndarray]] = [[] for _ in logs]
        g = torch.Generator().manual_seed(args.seed)
        for t in range(horizon):
            windows_now = []
            for s, states, valid, d in zip(logs, history, history_valid, driven):
                x = np.zeros((states.shape[0], w, 3), np.float32)
                x[:, :n] = states
                v = np.concatenate([valid, np.repeat(d[:, None], w - n, 1)], 1)
                windows_now.append(ttd.SceneInput(x, v, s.features, s.map))
            batch = collate(windows_now, w)
            with torch.no_grad():
                x = sample_future(model, batch, n, run.edm, args.steps, g)
            for j, s in enumerate(logs):
                a = s.states.shape[0]
                state = np.where(driven[j][:, None], x[j, :a, n].numpy(), s.states[:, n + t])
                emitted[j].append(state)
                history[j] = np.concatenate([history[j][:, 1:], state[:, None]], 1)
                now_valid = driven[j] | s.valid[:, n + t]
                history_valid[j] = np.concatenate([history_valid[j][:, 1:], now_valid[:, None]], 1)
        ade, accel, accel_log = [], [], []
        for j, s in enumerate(logs):
            path = np.stack(emitted[j], 1)[..., :2] * scale_m  # [A, T, 2] metres
            logged = s.states[:, : n + horizon, :2] * scale_m
            valid = s.valid[:, n : n + horizon] & driven[j][:, None]
            dist = np.linalg.norm(path - logged[:, n:], axis=-1)
            ade.append((dist * valid).sum() / max(valid.sum(), 1))
            whole = np.concatenate([logged[:, :n], path], 1)

            def accel_mps2(p: np.ndarray) -> np.ndarray:
                second = p[:, 2:] - 2 * p[:, 1:-1] + p[:, :-2]
                return np.linalg.norm(second, axis=-1)[:, n - 2 :] / STEP_S**2

            seen = s.valid[:, : n + horizon].all(1) & driven[j]
            if seen.any():
                accel.append(np.median(accel_mps2(whole)[seen]))
                accel_log.append(np.median(accel_mps2(logged)[seen]))
        print(
            f"{checkpoint}: ADE {np.mean(ade):.3f} m; median |acceleration| "
            f"{np.mean(accel):.2f} m/s² (the log: {np.mean(accel_log):.2f})"
        )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    for name, fn in (("history-noise", history_noise), ("closed-loop", closed_loop)):
        c = sub.add_parser(name)
        c.set_defaults(fn=fn)
        c.add_argument("checkpoints", nargs="+", help="checkpoint folders of one window shape")
        c.add_argument("--config", required=True, help="a run config of their model and planner")
        c.add_argument("--export", default=".road-cache/torch", help="`road data export-torch` output")
        c.add_argument("--scenes", type=int, default=48)
        c.add_argument("--steps", type=int, default=20, help="Heun steps K per sample")
        c.add_argument("--seed", type=int, default=7)
    sub.choices["history-noise"].add_argument(
        "--noise-m", type=float, nargs="+", default=[0.0, 0.05, 0.15],
        help="standard deviations (m) of the noise added to each observed position",
    )
    sub.choices["closed-loop"].add_argument("--horizon", type=int, default=30)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.fn(args)


if __name__ == "__main__":
    main()
