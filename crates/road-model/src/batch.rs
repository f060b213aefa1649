//! Scene windows → padded model inputs, and the training task's noise (math doc, "Training").

use candle_core::{Device, Tensor};
use rand::Rng;
use road_data::{AgentType, SceneWindow};
use road_sched::edm::{full_u, rolling_u, warmup_u};

use crate::Result;
use crate::config::{ModelConfig, TaskKind};

/// Per-agent static features: length/5 m, width/2.5 m, one-hot type (4).
pub const AGENT_FEATURES: usize = 6;

/// One scene cropped to the model's window, in model units, on the CPU (plain vectors).
#[derive(Debug, Clone)]
pub struct SceneInput {
    pub agents: usize,
    pub slots: usize,
    /// `[agents, slots, 3]`: x, y, heading·heading_scale.
    pub states: Vec<f32>,
    /// `[agents, slots]`.
    pub valid: Vec<bool>,
    /// `[agents, AGENT_FEATURES]`.
    pub agent_features: Vec<f32>,
    pub polylines: usize,
    pub points: usize,
    /// `[polylines, points, 2]`.
    pub map: Vec<f32>,
}

impl SceneInput {
    /// Crops `slots` steps from `start` of a window. Agents with no valid step in the crop
    /// stay (all invalid): padding is masked anyway.
    pub fn from_window(w: &SceneWindow, start: usize, slots: usize, config: &ModelConfig) -> Self {
        assert!(
            start + slots <= w.steps,
            "crop {start}+{slots} exceeds the window's {} steps",
            w.steps
        );
        let a = w.agents;
        let mut states = vec![0.0f32; a * slots * 3];
        let mut valid = vec![false; a * slots];
        for agent in 0..a {
            for s in 0..slots {
                if let Some([x, y, h]) = w.state(agent, start + s) {
                    let k = agent * slots + s;
                    valid[k] = true;
                    states[3 * k..3 * k + 3].copy_from_slice(&[
                        x,
                        y,
                        h * config.heading_scale as f32,
                    ]);
                }
            }
        }
        Self {
            agents: a,
            slots,
            states,
            valid,
            agent_features: agent_features(&w.length_m, &w.width_m, &w.agent_types),
            // The window lists polylines nearest first.
            polylines: w.polyline_count().min(config.map_polylines),
            points: w.polyline_points,
            map: w.polylines
                [..w.polyline_count().min(config.map_polylines) * w.polyline_points * 2]
                .to_vec(),
        }
    }
}

impl SceneInput {
    /// Rotates the scene about its centre (the frame's origin) by `angle_rad`: positions and
    /// map points turn, headings (state units: `heading_rad · heading_scale`) shift by the
    /// angle. Padding stays zero.
    pub fn rotate(&mut self, angle_rad: f32, heading_scale: f32) {
        let (sin, cos) = angle_rad.sin_cos();
        let turn = |p: &mut [f32]| {
            let (x, y) = (p[0], p[1]);
            p[0] = cos * x - sin * y;
            p[1] = sin * x + cos * y;
        };
        for (state, &valid) in self.states.chunks_exact_mut(3).zip(&self.valid) {
            if valid {
                turn(&mut state[..2]);
                state[2] += angle_rad * heading_scale;
            }
        }
        for point in self.map.chunks_exact_mut(2) {
            turn(point);
        }
    }

    /// Kink augmentation ([`crate::config::KinkAugmentation`]) of agent `agent`: its slots
    /// before `obs_slots − 2` turn by `angle_rad` about its position at slot `obs_slots − 2`
    /// (headings with them), so that its newest observed step runs as before from a history
    /// that approached at another angle. Needs slots `obs_slots − 2` and `obs_slots − 1` valid
    /// (else nothing changes); invalid slots stay as they are.
    pub fn kink_history(
        &mut self,
        agent: usize,
        obs_slots: usize,
        angle_rad: f32,
        heading_scale: f32,
    ) {
        let w = self.slots;
        if obs_slots < 3 || obs_slots > w {
            return;
        }
        let pivot_slot = obs_slots - 2;
        let valid = &self.valid[agent * w..(agent + 1) * w];
        if !(valid[pivot_slot] && valid[pivot_slot + 1]) {
            return;
        }
        let states = &mut self.states[3 * agent * w..3 * (agent + 1) * w];
        // The turn a lane guard's steer gives a plan, applied to the past instead.
        let turn = [
            states[3 * pivot_slot],
            states[3 * pivot_slot + 1],
            angle_rad,
            angle_rad * heading_scale,
        ];
        for t in (0..pivot_slot).filter(|&t| valid[t]) {
            crate::plan_turn::turn_plan(&mut states[3 * t..3 * t + 3], &turn);
        }
    }

    /// Adds `noise` (`[agents, obs_slots, 2]`, model units) to the positions of the first
    /// `obs_slots` slots of every agent, where valid (`train.history_noise_m`).
    pub fn perturb_history(&mut self, obs_slots: usize, noise: &[f32]) {
        let w = self.slots;
        let n = obs_slots.min(w);
        for a in 0..self.agents {
            for t in (0..n).filter(|&t| self.valid[a * w + t]) {
                let k = 3 * (a * w + t);
                let e = 2 * (a * n + t);
                self.states[k] += noise[e];
                self.states[k + 1] += noise[e + 1];
            }
        }
    }

    /// Drops agents with no valid slot in the crop, and their rows of `noise`
    /// (`[agents, slots, 3]`); keeps every agent when none is valid. Padding is masked, so the
    /// loss does not change; the batch just pads to fewer agents.
    pub fn drop_absent_agents(&mut self, noise: &mut Vec<f32>) {
        let w = self.slots;
        let keep: Vec<usize> = (0..self.agents)
            .filter(|&a| self.valid[a * w..(a + 1) * w].iter().any(|&v| v))
            .collect();
        if keep.is_empty() || keep.len() == self.agents {
            return;
        }
        let gather = |v: &[f32], per: usize| -> Vec<f32> {
            keep.iter()
                .flat_map(|&a| v[a * per..(a + 1) * per].iter().copied())
                .collect()
        };
        self.states = gather(&self.states, w * 3);
        *noise = gather(noise, w * 3);
        self.agent_features = gather(&self.agent_features, AGENT_FEATURES);
        self.valid = keep
            .iter()
            .flat_map(|&a| self.valid[a * w..(a + 1) * w].iter().copied())
            .collect();
        self.agents = keep.len();
    }
}

pub fn agent_features(length_m: &[f32], width_m: &[f32], types: &[AgentType]) -> Vec<f32> {
    let mut out = Vec::with_capacity(types.len() * AGENT_FEATURES);
    for i in 0..types.len() {
        let mut one_hot = [0.0f32; 4];
        one_hot[types[i].index() as usize] = 1.0;
        out.extend([length_m[i] / 5.0, width_m[i] / 2.5]);
        out.extend(one_hot);
    }
    out
}

/// A padded batch of scenes as tensors.
#[derive(Debug, Clone)]
pub struct Batch {
    /// `[B, A, W, 3]` clean states (targets).
    pub x0: Tensor,
    /// `[B, A, W, 3]` noised states.
    pub x_noisy: Tensor,
    /// `[B, W]` noise level of every slot, or `[B, A, W]` of every agent's slot (a batch with
    /// an initialisation task).
    pub sigma: Tensor,
    /// `[B, A, W]` 1 = valid, 0 = padding or absent.
    pub valid: Tensor,
    /// `[B, A, AGENT_FEATURES]`.
    pub agent_features: Tensor,
    /// `[B, P, Q, 2]`.
    pub map: Tensor,
    /// `[B, P]`.
    pub map_valid: Tensor,
}

impl Batch {
    /// Every tensor with its field name, in declaration order (the names the PyTorch export
    /// and its parity fixture use).
    pub fn named_tensors(&self) -> [(&'static str, &Tensor); 7] {
        [
            ("x0", &self.x0),
            ("x_noisy", &self.x_noisy),
            ("sigma", &self.sigma),
            ("valid", &self.valid),
            ("agent_features", &self.agent_features),
            ("map", &self.map),
            ("map_valid", &self.map_valid),
        ]
    }
}

/// Pads scenes to the batch's largest agent and polyline counts. `sigma` is `[B][W]` (every
/// agent's slots alike) or, scene by scene, `[A_b·W]` (per agent); the batch's σ is `[B, W]`
/// when every scene's is per slot, else `[B, A, W]` (padding rows at 1). `noise` is
/// `[B][A_b·W·3]` standard normal (or `None` for clean inputs).
pub fn collate(
    scenes: &[SceneInput],
    sigma: &[Vec<f32>],
    noise: Option<&[Vec<f32>]>,
    device: &Device,
) -> Result<Batch> {
    let b = scenes.len();
    let w = scenes[0].slots;
    let a = scenes.iter().map(|s| s.agents).max().unwrap_or(1).max(1);
    let p = scenes.iter().map(|s| s.polylines).max().unwrap_or(1).max(1);
    let q = scenes[0].points;
    let mut x0 = vec![0.0f32; b * a * w * 3];
    let mut xn = vec![0.0f32; b * a * w * 3];
    let mut valid = vec![0.0f32; b * a * w];
    let mut feats = vec![0.0f32; b * a * AGENT_FEATURES];
    let mut map = vec![0.0f32; b * p * q * 2];
    let mut map_valid = vec![0.0f32; b * p];
    let per_agent = sigma.iter().any(|row| row.len() != w);
    let mut sig = vec![1.0f32; if per_agent { b * a * w } else { b * w }];
    for (i, s) in scenes.iter().enumerate() {
        assert_eq!(s.slots, w, "scenes of one batch share the window length");
        let rows = &sigma[i];
        assert!(
            rows.len() == w || rows.len() == s.agents * w,
            "σ of {} values for a scene of {} agents × {w} slots",
            rows.len(),
            s.agents
        );
        // Agent `agent`'s σ per slot.
        let row = |agent: usize| {
            if rows.len() == w {
                &rows[..]
            } else {
                &rows[agent * w..(agent + 1) * w]
            }
        };
        if per_agent {
            for agent in 0..s.agents {
                let dst = (i * a + agent) * w;
                sig[dst..dst + w].copy_from_slice(row(agent));
            }
        } else {
            sig[i * w..(i + 1) * w].copy_from_slice(rows);
        }
        for agent in 0..s.agents {
            for (slot, &slot_sigma) in row(agent).iter().enumerate() {
                let src = agent * w + slot;
                let dst = (i * a + agent) * w + slot;
                valid[dst] = f32::from(u8::from(s.valid[src]));
                for d in 0..3 {
                    let clean = s.states[3 * src + d];
                    x0[3 * dst + d] = clean;
                    let eps = noise.map_or(0.0, |n| n[i][3 * src + d]);
                    xn[3 * dst + d] = clean + slot_sigma * eps;
                }
            }
            let fa = (i * a + agent) * AGENT_FEATURES;
            feats[fa..fa + AGENT_FEATURES].copy_from_slice(
                &s.agent_features[agent * AGENT_FEATURES..(agent + 1) * AGENT_FEATURES],
            );
        }
        for poly in 0..s.polylines {
            map_valid[i * p + poly] = 1.0;
            let src = poly * q * 2;
            let dst = (i * p + poly) * q * 2;
            map[dst..dst + q * 2].copy_from_slice(&s.map[src..src + q * 2]);
        }
    }
    Ok(Batch {
        x0: Tensor::from_vec(x0, (b, a, w, 3), device)?,
        x_noisy: Tensor::from_vec(xn, (b, a, w, 3), device)?,
        sigma: if per_agent {
            Tensor::from_vec(sig, (b, a, w), device)?
        } else {
            Tensor::from_vec(sig, (b, w), device)?
        },
        valid: Tensor::from_vec(valid, (b, a, w), device)?,
        agent_features: Tensor::from_vec(feats, (b, a, AGENT_FEATURES), device)?,
        map: Tensor::from_vec(map, (b, p, q, 2), device)?,
        map_valid: Tensor::from_vec(map_valid, (b, p), device)?,
    })
}

/// Standard normal draws (Box–Muller).
pub fn normal_vec(rng: &mut impl Rng, n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n + 1);
    while out.len() < n {
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random_range(0.0..1.0);
        let r = (-2.0 * u1.ln()).sqrt();
        let t = 2.0 * std::f64::consts::PI * u2;
        out.push((r * t.cos()) as f32);
        out.push((r * t.sin()) as f32);
    }
    out.truncate(n);
    out
}

/// The training task's σ per slot: observed slots at σ(u_ca), u_ca ~ U(0, r) (at least
/// σ_min); future slots along the task's profile at τ ~ U(0, 1).
pub fn task_sigma(
    rng: &mut impl Rng,
    config: &ModelConfig,
    obs_slots: usize,
    task: TaskKind,
    warmup_prob: f64,
    aug_ratio: f64,
) -> Vec<f32> {
    let tau: f64 = rng.random_range(0.0..1.0);
    let profile: fn(usize, usize, f64) -> f64 = match task {
        TaskKind::Full => full_u,
        TaskKind::Rolling if rng.random_bool(warmup_prob) => warmup_u,
        TaskKind::Rolling => rolling_u,
    };
    let u_ca: f64 = if aug_ratio > 0.0 {
        rng.random_range(0.0..aug_ratio)
    } else {
        0.0
    };
    task_sigma_of(config, obs_slots, profile, tau, u_ca)
}

/// The σ per slot of one drawn task: observed slots at σ(u_ca) (at least σ_min), future slot k
/// at σ(profile(k, F, τ)) (at least σ_min). `profile` is `road_sched::edm`'s `rolling_u`,
/// `warmup_u` or `full_u`.
pub fn task_sigma_of(
    config: &ModelConfig,
    obs_slots: usize,
    profile: fn(usize, usize, f64) -> f64,
    tau: f64,
    u_ca: f64,
) -> Vec<f32> {
    let w = config.window_slots;
    let f = w - obs_slots;
    let edm = &config.edm;
    let sigma_obs = edm.sigma(u_ca).max(edm.sigma_min);
    (0..w)
        .map(|slot| {
            let s = if slot < obs_slots {
                sigma_obs
            } else {
                edm.sigma(profile(slot - obs_slots, f, tau))
                    .max(edm.sigma_min)
            };
            s as f32
        })
        .collect()
}

/// The initialisation task's σ per agent and slot (`[A·W]`; `TrainConfig::
/// initialisation_task_prob`): of the agents present at `anchor_slot` (flags
/// `valid [A·W]`), each is kept with probability q ~ U(0, ½), at least one of them drawn
/// (none kept when only one is present); a kept agent's observed slots sit at σ(u_ca),
/// u_ca ~ U(0, r) (at least σ_min), every other slot of the scene, of kept agents' futures
/// and of drawn agents' whole windows, at one σ(u), u ~ U(0, 1).
pub fn initialisation_sigma(
    rng: &mut impl Rng,
    config: &ModelConfig,
    obs_slots: usize,
    anchor_slot: usize,
    valid: &[bool],
    aug_ratio: f64,
) -> Vec<f32> {
    let w = config.window_slots;
    let agents = valid.len() / w;
    let edm = &config.edm;
    let u: f64 = rng.random_range(0.0..1.0);
    let sigma_drawn = edm.sigma(u).max(edm.sigma_min) as f32;
    let u_ca: f64 = if aug_ratio > 0.0 {
        rng.random_range(0.0..aug_ratio)
    } else {
        0.0
    };
    let sigma_obs = edm.sigma(u_ca).max(edm.sigma_min) as f32;
    let present: Vec<usize> = (0..agents)
        .filter(|&agent| valid[agent * w + anchor_slot])
        .collect();
    let q: f64 = rng.random_range(0.0..0.5);
    let mut kept = vec![false; agents];
    for &agent in &present {
        kept[agent] = rng.random_bool(q);
    }
    if !present.is_empty() && present.iter().all(|&agent| kept[agent]) {
        kept[present[rng.random_range(0..present.len())]] = false;
    }
    let mut sigma = vec![sigma_drawn; agents * w];
    for agent in (0..agents).filter(|&agent| kept[agent]) {
        sigma[agent * w..agent * w + obs_slots.min(w)].fill(sigma_obs);
    }
    sigma
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kinked_history_turns_about_the_second_newest_observation() {
        // One agent along +x at 0.1 per slot, heading 0; 5 observed slots of 7, slot 1 invalid.
        let slots = 7;
        let mut input = SceneInput {
            agents: 1,
            slots,
            states: (0..slots)
                .flat_map(|t| [0.1 * t as f32, 0.0, 0.0])
                .collect(),
            valid: vec![true, false, true, true, true, true, true],
            agent_features: vec![0.0; AGENT_FEATURES],
            polylines: 0,
            points: 20,
            map: vec![],
        };
        let before = input.clone();
        let (angle, heading_scale) = (std::f32::consts::FRAC_PI_2, 0.25);
        input.kink_history(0, 5, angle, heading_scale);
        let state = |i: &SceneInput, t: usize| i.states[3 * t..3 * t + 3].to_vec();
        // Slots 3 (the pivot) onwards, and the invalid slot 1, as they were.
        for t in [1, 3, 4, 5, 6] {
            assert_eq!(state(&input, t), state(&before, t), "slot {t}");
        }
        // Slots 0 and 2, 0.3 and 0.1 behind the pivot (0.3, 0), turned a quarter left: below it.
        for (t, behind) in [(0, 0.3f32), (2, 0.1)] {
            let s = state(&input, t);
            assert!(
                (s[0] - 0.3).abs() < 1e-6 && (s[1] + behind).abs() < 1e-6,
                "{s:?}"
            );
            assert!((s[2] - angle * heading_scale).abs() < 1e-6);
        }
        // Without a valid pivot and newest step, nothing changes.
        let mut gap = before.clone();
        gap.valid[3] = false;
        let unchanged = gap.clone();
        gap.kink_history(0, 5, angle, heading_scale);
        assert_eq!(gap.states, unchanged.states);
    }

    #[test]
    fn history_noise_moves_only_valid_observed_positions() {
        let (agents, slots) = (2, 4);
        let mut input = SceneInput {
            agents,
            slots,
            states: vec![0.0; agents * slots * 3],
            valid: vec![true, true, true, true, true, false, true, true],
            agent_features: vec![0.0; agents * AGENT_FEATURES],
            polylines: 0,
            points: 20,
            map: vec![],
        };
        // 2 observed slots: [agents, 2, 2] noise values 1, 2, 3, ...
        let noise: Vec<f32> = (1..=agents * 2 * 2).map(|v| v as f32).collect();
        input.perturb_history(2, &noise);
        let state = |a: usize, t: usize| input.states[3 * (a * slots + t)..][..3].to_vec();
        assert_eq!(state(0, 0), vec![1.0, 2.0, 0.0]);
        assert_eq!(state(0, 1), vec![3.0, 4.0, 0.0]);
        assert_eq!(state(1, 0), vec![5.0, 6.0, 0.0]);
        // Agent 1's slot 1 is invalid; the future slots and headings never move.
        assert_eq!(state(1, 1), vec![0.0; 3]);
        for (a, t) in [(0, 2), (0, 3), (1, 2), (1, 3)] {
            assert_eq!(state(a, t), vec![0.0; 3]);
        }
    }

    #[test]
    fn absent_agents_are_dropped_with_their_noise() {
        let (agents, slots) = (3, 2);
        let mut input = SceneInput {
            agents,
            slots,
            states: (0..agents * slots * 3).map(|v| v as f32).collect(),
            valid: vec![true, false, false, false, false, true],
            agent_features: (0..agents * AGENT_FEATURES).map(|v| v as f32).collect(),
            polylines: 0,
            points: 20,
            map: vec![],
        };
        let mut noise: Vec<f32> = (0..agents * slots * 3).map(|v| -(v as f32)).collect();
        let before = input.clone();
        input.drop_absent_agents(&mut noise);
        assert_eq!(input.agents, 2);
        let row = |v: &[f32], a: usize, len: usize| v[a * len..(a + 1) * len].to_vec();
        for (new, old) in [(0, 0), (1, 2)] {
            assert_eq!(row(&input.states, new, 6), row(&before.states, old, 6));
            assert_eq!(
                row(&input.agent_features, new, AGENT_FEATURES),
                row(&before.agent_features, old, AGENT_FEATURES)
            );
            assert_eq!(
                row(&noise, new, 6),
                (0..6).map(|k| -((old * 6 + k) as f32)).collect::<Vec<_>>()
            );
        }
        assert_eq!(input.valid, vec![true, false, false, true]);
        // Nobody valid: nothing to drop to.
        let mut empty = SceneInput {
            valid: vec![false; agents * slots],
            ..before.clone()
        };
        let mut noise = vec![0.0; agents * slots * 3];
        empty.drop_absent_agents(&mut noise);
        assert_eq!(empty.agents, agents);
    }
}
