//! The engine's speed proxies, which need no GPU to measure (issue 40: "Without a GPU"): how
//! many compute dispatches one denoiser evaluation records (with its share of the step's
//! sampler update and of a compact sub-batch's row moves), how many bytes their bindings read
//! and write, and how much of the work computed is padding. Fusing kernels and keeping the
//! map's keys between evaluations lower the first two on any adapter, lavapipe included;
//! packing scenes of mixed agent counts lowers the third.
//!
//! The dispatch and byte counts are counted as the engine records its dispatches
//! ([`crate::kernels::Dispatch::record_counted`]), so they follow whatever kernels it runs; the
//! work is [`flops_per_evaluation`] of each scene at its own size against the same at the
//! shape the engine computes (agents padded to the batch's, or to a compact sub-batch's, idle
//! and padding scenes included).

use road_model::ModelConfig;

use crate::kernels::Traffic;

/// Multiply-adds ×2 of one denoiser evaluation of one scene of `agents` agents and `polylines`
/// polylines: projections, attention, MLP, the agent maps' point encoder and keys. Not counted:
/// the agent-pair features, layer norms and elementwise kernels, and (without agent maps) the
/// map encoder, which runs once per scene set. The one FLOP model of `road bench engine` and
/// `road bench serve` (their GFLOP/s) and of [`Work::computed_over_useful`]; of it,
/// [`map_key_flops`] is what an evaluation that keeps the map's keys leaves out.
pub fn flops_per_evaluation(c: &ModelConfig, agents: usize, polylines: usize) -> f64 {
    let (a, p, w, d) = (
        agents as f64,
        polylines as f64,
        c.window_slots as f64,
        c.hidden as f64,
    );
    let m = d * c.mlp_ratio as f64;
    let t = a * w;
    let linear = |rows: f64, i: f64, o: f64| 2.0 * rows * i * o;
    // With agent maps each agent attends to its own K polylines; without, every token to the
    // scene's P. The keys' own work (encoder, k, v) is `map_key_flops`.
    let map_keys = match &c.agent_map {
        Some(spec) => road_model::agent_map::polylines_per_agent(spec.polylines, polylines) as f64,
        None => p,
    };
    let per_block = 2.0 * 4.0 * linear(t, d, d) // time and agent attention projections
        + 2.0 * 2.0 * t * w * d // time attention scores and weighted sums
        + 2.0 * 2.0 * t * a * d // agent attention
        + 2.0 * linear(t, d, d) // map q, o
        + 2.0 * 2.0 * t * map_keys * d // map attention
        + linear(t, d, m) + linear(t, m, d); // MLP
    c.blocks as f64 * per_block
        + map_key_flops(c, agents, polylines)
        + linear(t, 3.0, d)
        + linear(t, d, 3.0)
}

/// The part of [`flops_per_evaluation`] that makes the map's keys: with agent maps the point
/// encoder (its D × D layer over K·Q points per agent, in the agent's frame) and every block's
/// map k, v of the agents' polylines, else every block's map k, v of the scene's (the scene
/// map's encoder runs once per scene set and is not counted). The engine makes them only in evaluations whose map inputs changed (the
/// windows' anchors, the maps; `HeunPlan`), and counts them only there.
pub fn map_key_flops(c: &ModelConfig, agents: usize, polylines: usize) -> f64 {
    let d = c.hidden as f64;
    let linear = |rows: f64, i: f64, o: f64| 2.0 * rows * i * o;
    let (map_kv_rows, map_encoder) = match &c.agent_map {
        Some(spec) => {
            let k = road_model::agent_map::polylines_per_agent(spec.polylines, polylines) as f64;
            let q = c.polyline_points as f64;
            let a = agents as f64;
            (a * k, linear(a * k * q, d, d))
        }
        None => (polylines as f64, 0.0),
    };
    c.blocks as f64 * 2.0 * linear(map_kv_rows, d, d) + map_encoder
}

/// What an engine's steps did, summed since it was last taken
/// ([`crate::step_engine::GpuStepEngine::take_work`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Work {
    /// Denoiser evaluations of the batch (a Heun step with its second evaluation makes 2).
    pub evaluations: u64,
    /// The dispatches recorded: every evaluation's and its sampler update's, and a compact
    /// sub-batch's row moves (its gathers and scatters, once a step).
    pub traffic: Traffic,
    /// FLOPs at the shape computed: scenes and agents as the engine padded them, the map's
    /// keys counted only in the evaluations that made them ([`map_key_flops`]).
    pub computed_flops: f64,
    /// FLOPs of the moving scenes at their own agents and polylines, counted alike.
    pub useful_flops: f64,
    /// Evaluations that made the map's keys (the rest kept those of an earlier one).
    pub map_key_evaluations: u64,
}

impl Work {
    /// Dispatches recorded per evaluation (its share of the sampler update and of a compact
    /// sub-batch's row moves included).
    pub fn dispatches_per_evaluation(&self) -> f64 {
        self.traffic.dispatches as f64 / self.evaluations.max(1) as f64
    }

    /// Bytes read and written by the bindings of an evaluation's dispatches.
    pub fn bytes_per_evaluation(&self) -> f64 {
        self.traffic.bytes() as f64 / self.evaluations.max(1) as f64
    }

    /// Work computed (padding included) over the scenes' own: 1 without padding.
    pub fn computed_over_useful(&self) -> f64 {
        if self.useful_flops > 0.0 {
            self.computed_flops / self.useful_flops
        } else {
            f64::NAN
        }
    }
}

impl std::ops::AddAssign for Work {
    fn add_assign(&mut self, other: Self) {
        self.evaluations += other.evaluations;
        self.traffic += other.traffic;
        self.computed_flops += other.computed_flops;
        self.useful_flops += other.useful_flops;
        self.map_key_evaluations += other.map_key_evaluations;
    }
}
