//! Model and training configuration: one TOML file per shipped config under `configs/`
//! (`[model]`, `[planner]`, `[train]`), saved next to every checkpoint's weights.

use std::path::Path;

use road_sched::{EdmSchedule, PlannerKind, PlannerSpec};
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// The denoiser's shape. `Default` is the default (RoAD-20) model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// Token width D.
    pub hidden: usize,
    pub heads: usize,
    /// Transformer blocks (time attention, agent attention, map cross-attention, MLP).
    pub blocks: usize,
    /// MLP width as a multiple of `hidden`.
    pub mlp_ratio: usize,
    /// Window slots W = n + F the model is trained on (slot embeddings are learned per slot).
    pub window_slots: usize,
    /// Points per map polyline (must match the data's `polyline_points`).
    pub polyline_points: usize,
    /// Map polylines per scene the model attends to: the nearest ones to the scene centre.
    pub map_polylines: usize,
    /// State units per radian of heading: the state is (x, y, heading_rad · heading_scale),
    /// heading unwrapped along the window so that it never jumps at ±π.
    pub heading_scale: f64,
    /// Metres per normalised position unit (the data's `position_scale_m`).
    pub position_scale_m: f64,
    pub edm: EdmSchedule,
    /// Per-agent frame features (see [`AgentFrame`]). Absent from a file means none: the
    /// checkpoints trained before it saw the scene frame only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent_frame: Option<AgentFrame>,
    /// Agent-centric map tokens (see [`AgentMap`]). Absent = one scene-frame token per
    /// polyline, shared by every agent (the paper's and every checkpoint's before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent_map: Option<AgentMap>,
    /// Pair features in agent attention (see [`AgentPairs`]). Absent = agents see each other
    /// only through their tokens (every checkpoint's before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent_pairs: Option<AgentPairs>,
}

/// Agent attention also sees where each other agent is, and how it heads, relative to the
/// querying agent: per pair (query i, key j) at the same slot, [`crate::agent_pairs`]'s
/// features of j's position in i's anchor frame and of their heading difference enter the
/// attention as a key offset and a value offset, linear in the features, per head (docs/
/// checkpoint.md). Scene-frame tokens leave "the car 6 m ahead in my lane" to be worked out
/// from two absolute positions 40 m to the unit; this hands it to every pair. Needs an agent
/// frame (its anchors orient the pairs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentPairs {
    /// Direction features `(forward, left) / (distance + scale)`: about the unit direction
    /// beyond this distance, proportional to the offset within it. Metres.
    pub direction_scale_m: f64,
    /// Proximity features `exp(−distance / scale)` at a near and a far length scale. Metres.
    pub near_scale_m: f64,
    pub far_scale_m: f64,
}

/// Each agent attends to its own map: the `polylines` lane polylines (of the scene's
/// `map_polylines`) nearest its anchor position, their points translated and rotated into its
/// anchor frame before the point encoder. "The lane ahead bends left" then reads the same in
/// every orientation and at every place of the scene, where scene-frame tokens leave it to
/// dot-product attention to find the agent's lane among all of them. The same weights as the
/// scene-frame map (`map_point`, `map_mix`, …); only their input changes. Needs an agent frame.
/// Agents without an anchor get the polylines nearest the scene centre, in the scene frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentMap {
    /// Polylines per agent K (≤ `map_polylines`).
    pub polylines: usize,
}

/// Each token also sees its state relative to its agent's anchor pose (translated and rotated
/// so that the agent heads along +x), and the network's output is rotated back from that
/// frame. "Follow my lane" and "keep my speed" then look the same for every orientation, and
/// motion is seen at a finer scale than the scene's. A deviation from the paper (which feeds
/// scene-frame states only); the EDM preconditioning is unchanged: the frame is a function of
/// the noisy input, so `D(x; σ)` is still a denoiser of the scene-frame state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentFrame {
    /// The slot whose (noisy) state anchors each agent's frame: the newest observation, n − 1.
    /// Agents not valid there keep the scene frame and get zero relative features.
    pub anchor_slot: usize,
    /// Multiplier of the relative features after `c_in`: 2 shows motion at 20 m per unit
    /// (where the scene-frame input has 40 m).
    pub relative_scale: f64,
    /// Denoise each agent's deviation from its constant-velocity extrapolation instead of its
    /// scene-frame state (see [`AgentFrame::residual_scale`] in `docs/checkpoint.md`): the
    /// reference for slot `w` is the anchor pose moved by `(w − anchor)` times the last observed
    /// step (positions; heading held), a function of the noisy input like the frame itself,
    /// so `D(x; σ)` stays a denoiser of the scene-frame state. The residual is multiplied by
    /// this scale (40 = metres) and preconditioned at the matching σ·scale, so that its spread
    /// sits near `sigma_data`. Absent = no reference (the frame's features only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_scale: Option<f64>,
    /// An agent whose anchor slot is noisier than this (σ, scene units) has no anchor yet: it
    /// keeps the scene frame, the map nearest the scene centre and no reference, as an agent
    /// not valid there. What a model that generates whole agents from noise needs
    /// (`TrainConfig::initialisation_task_prob`): a pose drawn at σ = 80 is no frame. Only the
    /// candle model reads it, with σ per agent (`[B, A, W]`); the fast CPU and WGSL engines
    /// take σ per slot and keep every frame, which is the same where the anchor slot is
    /// observed below it (the rolling planners' observations sit at σ(r) ≈ 0.02). Absent: every
    /// valid anchor counts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_anchor_sigma: Option<f64>,
}

impl AgentFrame {
    /// Width of the relative features: (forward, left, heading, anchor valid), plus the last
    /// observed step (forward, left) with a constant-velocity reference.
    pub fn relative_features(&self) -> usize {
        if self.residual_scale.is_some() { 6 } else { 4 }
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            hidden: 64,
            heads: 4,
            blocks: 3,
            mlp_ratio: 2,
            window_slots: 20,
            polyline_points: 20,
            map_polylines: 32,
            heading_scale: 0.25,
            position_scale_m: 40.0,
            edm: EdmSchedule::default(),
            agent_frame: None,
            agent_map: None,
            agent_pairs: None,
        }
    }
}

impl ModelConfig {
    /// How scenes are windowed for this model (its position scale and polyline points; the
    /// rest as the data pipeline's default): what a closed loop on a built scene needs.
    pub fn window_config(&self) -> road_data::WindowConfig {
        road_data::WindowConfig {
            position_scale_m: self.position_scale_m,
            polyline_points: self.polyline_points,
            ..road_data::WindowConfig::default()
        }
    }

    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.hidden == 0 || self.heads == 0 || !self.hidden.is_multiple_of(self.heads) {
            return Err(format!(
                "hidden ({}) must be a positive multiple of heads ({})",
                self.hidden, self.heads
            ));
        }
        if self.blocks == 0
            || self.mlp_ratio == 0
            || self.window_slots < 2
            || self.polyline_points < 2
            || self.map_polylines == 0
        {
            return Err(
                "blocks, mlp_ratio, map_polylines ≥ 1; window_slots, polyline_points ≥ 2".into(),
            );
        }
        if !(self.heading_scale > 0.0 && self.position_scale_m > 0.0) {
            return Err("heading_scale and position_scale_m must be positive".into());
        }
        if let Some(frame) = &self.agent_frame {
            if frame.anchor_slot >= self.window_slots {
                return Err(format!(
                    "agent_frame.anchor_slot ({}) must be a slot of the window (< {})",
                    frame.anchor_slot, self.window_slots
                ));
            }
            if !(frame.relative_scale > 0.0 && frame.relative_scale.is_finite()) {
                return Err("agent_frame.relative_scale must be positive".into());
            }
            if let Some(scale) = frame.residual_scale {
                if !(scale > 0.0 && scale.is_finite()) {
                    return Err(format!(
                        "agent_frame.residual_scale must be positive and finite, got {scale}"
                    ));
                }
                if frame.anchor_slot == 0 {
                    return Err(
                        "agent_frame.residual_scale needs an observed slot before the anchor \
                         (anchor_slot ≥ 1) for the constant-velocity reference"
                            .into(),
                    );
                }
            }
        }
        if let Some(map) = &self.agent_map {
            if self.agent_frame.is_none() {
                return Err("agent_map needs an agent_frame (its anchors place the maps)".into());
            }
            if map.polylines == 0 || map.polylines > self.map_polylines {
                return Err(format!(
                    "agent_map.polylines ({}) must lie in 1..=map_polylines ({})",
                    map.polylines, self.map_polylines
                ));
            }
        }
        if let Some(pairs) = &self.agent_pairs {
            if self.agent_frame.is_none() {
                return Err(
                    "agent_pairs needs an agent_frame (its anchors orient the pairs)".into(),
                );
            }
            for (key, value) in [
                ("direction_scale_m", pairs.direction_scale_m),
                ("near_scale_m", pairs.near_scale_m),
                ("far_scale_m", pairs.far_scale_m),
            ] {
                if !(value > 0.0 && value.is_finite()) {
                    return Err(format!(
                        "agent_pairs.{key} must be positive and finite, got {value}"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Optimisation and task sampling. `Default` matches `configs/road20.toml`'s `[train]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Scenes per optimiser step.
    pub batch_scenes: usize,
    pub steps: u64,
    pub learning_rate: f64,
    /// Linear warm-up of the learning rate, then cosine decay to `min_learning_rate`.
    pub warmup_steps: u64,
    pub min_learning_rate: f64,
    pub weight_decay: f64,
    /// Global gradient-norm clip.
    pub grad_clip: f64,
    /// EMA of the weights (what inference uses).
    pub ema_decay: f64,
    /// β: probability of the warm-up task (rolling planners only).
    pub warmup_task_prob: f64,
    /// r: observed slots get σ(u), u ~ U(0, r) (conditioning augmentation); 0 turns it off.
    pub augmentation_ratio: f64,
    pub seed: u64,
    pub val_every_steps: u64,
    pub val_batches: usize,
    pub checkpoint_every_secs: u64,
    /// Fill each training batch with scenes of similar agent counts (less padding, the same
    /// per-window sampling probability); validation batches never are.
    pub bucket_by_agents: bool,
    /// Data-parallel worker threads: each differentiates a shard of the batch (candle's own
    /// matrix products single-threaded; `road train` sets `RAYON_NUM_THREADS=1` unless given).
    /// Part of the run: the gradient is summed shard by shard, so it fixes the float rounding.
    pub workers: usize,
    /// Rotate every training scene about its centre by a uniform random angle (positions, map
    /// and headings together): the scene frame has no preferred orientation at inference.
    pub rotation_augmentation: bool,
    /// Start from another checkpoint's (EMA) weights instead of a fresh initialisation: a
    /// folder under `models/`, relative to the working directory. Every tensor there must be
    /// one of this model's, with its shape; this model's tensors it lacks (a part the config
    /// adds, e.g. `agent_pairs`) keep their initialisation, and are logged; added blocks start
    /// as the identity (their residual branches' output projections at zero). The optimiser's
    /// moments and the schedule start afresh.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init_from: Option<std::path::PathBuf>,
    /// Histories with a kink, as a lane guard's steer leaves them (absent: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kink_augmentation: Option<KinkAugmentation>,
    /// Standard deviation (metres) of Gaussian noise added to the observed positions of every
    /// training window, the model not told (its observed σ stays the task's): the noise an
    /// MPC-1 planner feeds back, where every step's fresh first slot becomes history, so that
    /// the model learns not to amplify it
    /// (`docs/experiments/2026-11-26-baselines-d96.md`). Training batches only. Absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub history_noise_m: Option<f64>,
    /// Probability of the initialisation task (issue 39): a scene's agents drawn whole from
    /// noise around the ones it keeps. Each agent present at the anchor slot is kept with a
    /// probability q ~ U(0, ½) drawn per scene (at least one is drawn); the kept ones'
    /// observed slots sit at the conditioning augmentation's σ, every other slot of the scene
    /// at one σ = σ(u), u ~ U(0, 1): what `road_sim::populate::initialise_histories` asks of
    /// the model. Needs `model.agent_frame.max_anchor_sigma`. 0: never.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub initialisation_task_prob: f64,
}

fn is_zero(value: &f64) -> bool {
    *value == 0.0
}

/// Kink augmentation: with probability `prob` per agent, the agent's observed slots before its
/// newest step turn about the second-newest observation by an angle drawn uniformly within
/// ±`max_deg` (headings with them). The history then approached at another angle and the
/// newest step runs as logged, into the logged future: the situation after a lane guard
/// steered a vehicle back into its lane, which the model, never having seen one, answered by
/// turning its heading back to where it had been going
/// (`docs/experiments/2026-11-26-sliding-sideways.md`). Training batches only; validation batches are left as recorded.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KinkAugmentation {
    pub prob: f64,
    pub max_deg: f64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            batch_scenes: 16,
            steps: 20_000,
            learning_rate: 1e-3,
            warmup_steps: 200,
            min_learning_rate: 1e-5,
            weight_decay: 0.0,
            grad_clip: 1.0,
            ema_decay: 0.999,
            warmup_task_prob: 0.1,
            augmentation_ratio: 0.5,
            seed: 0,
            val_every_steps: 250,
            val_batches: 8,
            checkpoint_every_secs: 300,
            bucket_by_agents: true,
            workers: 2,
            rotation_augmentation: false,
            init_from: None,
            kink_augmentation: None,
            history_noise_m: None,
            initialisation_task_prob: 0.0,
        }
    }
}

/// A whole run: what `road train --config` reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    pub name: String,
    #[serde(default)]
    pub model: ModelConfig,
    pub planner: PlannerSpec,
    #[serde(default)]
    pub train: TrainConfig,
}

impl Default for RunConfig {
    /// RoAD-20, as in `configs/road20.toml`.
    fn default() -> Self {
        Self {
            name: "road20".into(),
            model: ModelConfig::default(),
            planner: PlannerSpec::default(),
            train: TrainConfig::default(),
        }
    }
}

impl RunConfig {
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let config: Self = toml::from_str(text).map_err(|e| Error::Config {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        config.validate().map_err(|reason| Error::Config {
            path: path.to_owned(),
            reason,
        })?;
        Ok(config)
    }

    pub fn validate(&self) -> std::result::Result<(), String> {
        self.model.validate()?;
        self.planner
            .validate(&self.name)
            .map_err(|e| e.to_string())?;
        if self.planner.window_slots() != self.model.window_slots {
            return Err(format!(
                "model.window_slots ({}) must equal planner obs_slots + future_slots ({})",
                self.model.window_slots,
                self.planner.window_slots()
            ));
        }
        if self.planner.edm != self.model.edm {
            return Err("planner.edm and model.edm differ".into());
        }
        let t = &self.train;
        if t.batch_scenes == 0
            || t.learning_rate.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || !(0.0..1.0).contains(&t.ema_decay)
        {
            return Err("train: batch_scenes ≥ 1, learning_rate > 0, 0 ≤ ema_decay < 1".into());
        }
        if !(0.0..=1.0).contains(&t.warmup_task_prob)
            || !(0.0..=1.0).contains(&t.augmentation_ratio)
        {
            return Err("train: warmup_task_prob and augmentation_ratio lie in [0, 1]".into());
        }
        if t.workers == 0 {
            return Err("train: workers ≥ 1".into());
        }
        if !(0.0..=1.0).contains(&t.initialisation_task_prob) {
            return Err(format!(
                "train.initialisation_task_prob lies in [0, 1], got {}",
                t.initialisation_task_prob
            ));
        }
        let bound = self
            .model
            .agent_frame
            .as_ref()
            .and_then(|f| f.max_anchor_sigma);
        if t.initialisation_task_prob > 0.0 && self.model.agent_frame.is_some() && bound.is_none() {
            return Err(
                "train.initialisation_task_prob > 0 needs model.agent_frame.max_anchor_sigma (a pose drawn from noise is no frame)"
                    .into(),
            );
        }
        if let Some(bound) = bound
            && !(bound > 0.0 && bound.is_finite())
        {
            return Err(format!(
                "model.agent_frame.max_anchor_sigma must be a finite σ > 0, got {bound}"
            ));
        }
        if let Some(noise_m) = t.history_noise_m
            && !(noise_m >= 0.0 && noise_m.is_finite())
        {
            return Err(format!(
                "train.history_noise_m must be a finite number of metres ≥ 0, got {noise_m}"
            ));
        }
        if let Some(k) = t.kink_augmentation
            && !((0.0..=1.0).contains(&k.prob) && (0.0..=180.0).contains(&k.max_deg))
        {
            return Err(format!(
                "train.kink_augmentation: prob in [0, 1] and max_deg in [0, 180], got {k:?}"
            ));
        }
        if let Some(frame) = &self.model.agent_frame {
            if frame.anchor_slot + 1 != self.planner.obs_slots {
                return Err(format!(
                    "model.agent_frame.anchor_slot ({}) must be the newest observed slot ({})",
                    frame.anchor_slot,
                    self.planner.obs_slots.saturating_sub(1)
                ));
            }
        }
        Ok(())
    }

    /// Which σ profile the training tasks follow.
    pub fn task_kind(&self) -> TaskKind {
        match self.planner.kind {
            PlannerKind::Rolling => TaskKind::Rolling,
            PlannerKind::Autoregressive | PlannerKind::Mpc | PlannerKind::OneShot => TaskKind::Full,
        }
    }
}

/// Training task families (math doc, "Training").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaskKind {
    /// Warm-up with probability β, else rolling.
    Rolling,
    /// Every future slot at the same u = τ (AR, DJINN).
    Full,
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    #[test]
    fn agent_pairs_need_an_agent_frame_and_positive_scales() {
        let pairs = AgentPairs {
            direction_scale_m: 10.0,
            near_scale_m: 5.0,
            far_scale_m: 20.0,
        };
        let mut model = ModelConfig {
            agent_pairs: Some(pairs.clone()),
            ..ModelConfig::default()
        };
        assert!(model.validate().unwrap_err().contains("agent_frame"));
        model.agent_frame = Some(AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: None,
            max_anchor_sigma: None,
        });
        assert_eq!(model.validate(), Ok(()));
        model.agent_pairs = Some(AgentPairs {
            near_scale_m: 0.0,
            ..pairs
        });
        assert!(
            model
                .validate()
                .unwrap_err()
                .contains("agent_pairs.near_scale_m")
        );
    }

    /// Every run config under `configs/` (the files with a `name`) parses and validates.
    #[test]
    fn every_shipped_run_config_validates() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let mut runs = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            // configs/ also holds folders (zenoh/) and other formats.
            if path.extension().is_none_or(|e| e != "toml") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            if text.lines().any(|l| l.starts_with("name = ")) {
                RunConfig::parse(&text, &path).unwrap_or_else(|e| panic!("{e}"));
                runs += 1;
            }
        }
        assert!(runs >= 7, "{runs} run configs in {}", dir.display());
    }

    /// Every checkpoint under `models/` ships with its model card and the run config that made
    /// it (`configs/<name>.toml`, named as the folder).
    #[test]
    fn every_shipped_checkpoint_has_its_card_and_run_config() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let mut checkpoints = 0;
        for entry in std::fs::read_dir(root.join("models")).unwrap() {
            let folder = entry.unwrap().path();
            if !folder.is_dir() {
                continue;
            }
            let name = folder.file_name().unwrap().to_str().unwrap().to_owned();
            assert!(folder.join("README.md").is_file(), "{name}: no model card");
            for file in ["config.toml", "weights.safetensors"] {
                assert!(folder.join(file).is_file(), "{name}: no {file}");
            }
            let run = root.join("configs").join(format!("{name}.toml"));
            assert!(run.is_file(), "{name}: no run config {}", run.display());
            checkpoints += 1;
        }
        assert!(checkpoints >= 1, "no checkpoint under models/");
    }

    #[test]
    fn agent_maps_need_an_agent_frame_and_at_most_the_scene_s_polylines() {
        let mut model = ModelConfig {
            agent_map: Some(AgentMap { polylines: 8 }),
            ..ModelConfig::default()
        };
        assert!(model.validate().unwrap_err().contains("agent_frame"));
        model.agent_frame = Some(AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
            max_anchor_sigma: None,
        });
        assert_eq!(model.validate(), Ok(()));
        model.agent_map = Some(AgentMap { polylines: 33 });
        assert!(model.validate().unwrap_err().contains("map_polylines (32)"));
    }
}
