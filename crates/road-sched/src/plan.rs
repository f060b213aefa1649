//! Planners as noise policies: per-step plans `(σ_cur[W], σ_next[W])` for every stage a planner
//! runs, precomputed once per planner so that the hot path only indexes tables.

use serde::{Deserialize, Serialize};

use crate::edm::{EdmSchedule, full_u, rolling_u, warmup_u};
use crate::{Error, Result};

/// Which noise policy a planner follows (math doc, "The planners").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PlannerKind {
    /// RoAD-W: warm-up once, then one rolling stage per simulated step.
    Rolling,
    /// Autoregressive diffusion: one future slot (`F = 1`), fully diffused every step.
    Autoregressive,
    /// DJINN-F MPC-X: fully diffuse all F future slots every X steps, execute X of them.
    Mpc,
    /// DJINN one-shot: one full diffusion of the horizon, then open loop.
    OneShot,
}

/// How a step moves a slot from σ_cur to σ_next (math doc, "Sampling").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampler {
    /// Deterministic Heun (EDM Algorithm 1) per slot: 2 model evaluations per step, 1 where
    /// every changing slot lands on σ = 0. The paper's.
    #[default]
    Heun,
    /// DPM-Solver++(2M) (Lu et al., 2022) per slot: 1 model evaluation per step. The Euler step
    /// `x + (σ_next − σ)·(x − D)/σ` plus `γ·(D − D_prev)`, where `D_prev` is the slot's estimate
    /// from its previous step (kept through the window's shift: a slot's σ falls continuously
    /// from stage to stage) and `γ = (1 − σ_next/σ)/(2r)`, `r = ln(σ_prev/σ)/ln(σ/σ_next)`. A
    /// slot without a previous estimate (a fresh slot, a rebuilt window) or landing on 0 takes
    /// the Euler step. A deviation from the paper: half the evaluations of Heun at equal K.
    Multistep,
}

impl Sampler {
    pub fn is_heun(&self) -> bool {
        *self == Sampler::Heun
    }

    /// γ of one slot's multistep correction (see [`Sampler::Multistep`]): `sigma_prev` is the
    /// σ the slot's kept estimate was made at (0: none). 0 where the slot takes the Euler step.
    pub fn multistep_gamma(sigma_prev: f32, sigma_cur: f32, sigma_next: f32) -> f32 {
        // A second-order step needs a previous, noisier estimate and a step that stays noisy.
        if !(sigma_next > 0.0 && sigma_next < sigma_cur && sigma_prev > sigma_cur) {
            return 0.0;
        }
        let h = (sigma_cur / sigma_next).ln();
        let h_prev = (sigma_prev / sigma_cur).ln();
        let r = h_prev / h;
        (1.0 - sigma_next / sigma_cur) / (2.0 * r)
    }
}

/// The collision guard's longest look-ahead: 5 s at 10 Hz (its cost grows with it).
pub const MAX_GUARD_HORIZON_STEPS: usize = 50;

/// The widest plan smoothing: 5 committed states and 5 planned slots either side.
pub const MAX_PLAN_SMOOTHING_STEPS: usize = 5;

/// One planner: its window and its step budget. `Default` is RoAD-20 with K = 40.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlannerSpec {
    pub kind: PlannerKind,
    /// `n`: observed slots at the start of the window.
    pub obs_slots: usize,
    /// `F`: future slots after the observations (`W = n + F`); the horizon for one-shot.
    pub future_slots: usize,
    /// `K`: steps that take one slot from u = 1 to u = 0.
    pub steps_per_diffusion: usize,
    /// `X`: simulated steps executed between replans (MPC only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replan_every: Option<usize>,
    /// Noise level of observed slots at test time; EDM's σ_min when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_sigma: Option<f64>,
    /// Standard deviation of the noise actually added to observations at test time; `obs_sigma`
    /// when absent (the paper's minimal augmentation). 0 feeds the observations clean while the
    /// model is still told `obs_sigma`, the lowest level it was trained on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_noise: Option<f64>,
    /// α in (0, 1]: each emitted state's acceleration is low-passed,
    /// `a = a_prev + α · (a_model − a_prev)`, before it joins the history and the window
    /// (`road_planner::smoothing`; a deviation from the paper against jitter). Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acceleration_smoothing: Option<f64>,
    /// Least-jerk tracking (`road_planner::smoothing`; a deviation from the paper against jitter):
    /// each emitted position becomes the first of the jerk-penalised path from the agent's
    /// committed motion through the emitted position and the model's plan. Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jerk_tracking: Option<JerkTracking>,
    /// h in 1..=`MAX_PLAN_SMOOTHING_STEPS`: each emitted position is replaced by the value at
    /// the emission step of the least-squares quadratic through the agent's last h committed
    /// positions, the emitted one and the model's denoised estimate of the next h slots of its
    /// window (`road_planner::smoothing`; a deviation from the paper against jitter that, unlike
    /// `acceleration_smoothing`, adds no lag). Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan_smoothing: Option<usize>,
    /// How many of the window's planned slots the plan-smoothing fit takes, 0..=h (absent: h).
    /// The far slots are still at high noise, so their estimate is near the model's mean
    /// continuation: fitting through them pulls every sample towards it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan_smoothing_ahead: Option<usize>,
    /// τ in (0, 2]: the pure noise a future slot starts from is `τ · σ_max · z` instead of
    /// `σ_max · z` (the window's first build and each new slot of a rolling or replanned
    /// window): below 1 a lower sampling temperature, above 1 a wider spread than the model
    /// draws (a deviation from the paper: the model is still told σ_max). Absent: 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_temperature: Option<f64>,
    /// The collision guard in closed loop (`road_planner::collision_guard`; a deviation from the paper, a
    /// safety layer after the model). Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub collision_guard: Option<CollisionGuard>,
    /// The lane guard in closed loop (`road_planner::lane_guard`; a deviation from the paper, a
    /// lane-keeping layer after the model). Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lane_guard: Option<LaneGuard>,
    /// The stall release in closed loop (a deviation from the paper, for long sessions): a
    /// model-driven vehicle that stood still with free road ahead pulls away. Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stall_release: Option<StallRelease>,
    /// The stuck removal in closed loop (a deviation from the paper, the last resort of long
    /// sessions): a model-driven vehicle that stood stuck for its time leaves the scene.
    /// Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stuck_removal: Option<StuckRemoval>,
    /// The give-way rule in closed loop (a deviation from the paper, for long sessions): model
    /// vehicles heed the map's right-of-way and all-way-stop elements. Absent: off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub give_way: Option<GiveWay>,
    /// The step rule; Heun (the paper's) when absent.
    #[serde(default, skip_serializing_if = "Sampler::is_heun")]
    pub sampler: Sampler,
    #[serde(default)]
    pub edm: EdmSchedule,
}

/// Least-jerk tracking's settings. Each tick, every agent with three committed positions takes
/// the path `p_0 … p_f` that continues its committed position, velocity and acceleration and
/// minimises `Σ_k |p_k − r_k|² + jerk_cost_m² · Σ_k |j_k|²` (metres; jerk `j_k` in m/s³, the
/// third difference of the positions over 0.1 s steps), where `r_0` is the emitted position and
/// `r_1 … r_f` are the model's denoised estimate of the next `ahead` slots; `p_0` is emitted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JerkTracking {
    /// Metres of tracking error that 1 m/s³ of jerk costs as much as: larger is smoother and
    /// follows the model less closely.
    pub jerk_cost_m: f64,
    /// Planned slots the path tracks beyond the emitted one, 0..=`MAX_JERK_TRACKING_AHEAD`.
    pub ahead: usize,
    /// The largest committed acceleration (m/s²) the path carries on: a bigger one (a guard's
    /// correction, a step off the map) is scaled down to it first. Absent: unbounded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_acceleration_mps2: Option<f64>,
    /// The tracked step moves sideways of the model's heading no more than the model's own
    /// emitted step does, plus this angle's tangent times its forward motion (degrees): the path
    /// may not carry a lateral correction on (a lane guard's) while the car heads elsewhere,
    /// which slides it sideways. Absent: unbounded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_slip_deg: Option<f64>,
    /// A vehicle moving at 2 m/s or more heads within this angle (degrees) of its tracked step's
    /// course: its emitted heading is turned that far towards the course, as a car's body
    /// follows its wheels. The model's heading may disagree with its own step; without this the
    /// box then moves sideways. Absent: the model's heading stands.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_course_offset_deg: Option<f64>,
    /// A vehicle turns no tighter than a circle of this radius (metres): its emitted heading
    /// turns from its last one by at most the step's length over the radius, as a car's does,
    /// and a standing car not at all. The model may rotate a slow vehicle's heading by any angle,
    /// which in long sessions turned vehicles across or against their lanes where the guards
    /// then held them. Absent: unbounded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_turn_radius_m: Option<f64>,
}

/// The speed from which `JerkTracking::max_course_offset_deg` holds (m/s): the one from which
/// the suites read a course of motion (`road_sim::kinematics`).
pub const COURSE_MIN_SPEED_MPS: f64 = 2.0;

/// The most planned slots least-jerk tracking looks at.
pub const MAX_JERK_TRACKING_AHEAD: usize = 10;

impl JerkTracking {
    /// The jerk's weight λ for positions in any unit and jerk as the third difference per step of
    /// `step_secs`: `(jerk_cost_m / step_secs³)²` (the position unit cancels).
    pub fn jerk_weight(&self, step_secs: f64) -> f64 {
        (self.jerk_cost_m / step_secs.powi(3)).powi(2)
    }
}

/// The collision guard's settings: model-driven agents closing in on another agent within
/// `horizon_steps` (every agent's step of this tick extrapolated at constant velocity) brake
/// by `brake_mps2`; no model-driven agent steps into another's box.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CollisionGuard {
    /// Look-ahead in simulated steps (0: only the no-overlap rule).
    pub horizon_steps: usize,
    /// Deceleration a braking agent takes this tick, m/s².
    pub brake_mps2: f64,
    /// Agents that are not the model's (an ego stack, scripted and replayed agents) do not react
    /// to the NPCs: a model-driven agent also brakes for a predicted collision with one of them
    /// that closes in on it (a crossing ego that does not yield) when braking from this tick on
    /// keeps it clear over the horizon. Off: only the agent closing in brakes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub yield_to_unreactive: bool,
    /// A model-driven agent the guard has held (braked or stopped short) for this long, seconds,
    /// stops braking for other model-driven agents for the next
    /// [`DEADLOCK_RELEASE_HOLD_SECS`]: only the no-overlap rule holds it then. Two vehicles that
    /// brake for each other (each predicted to run into the other) otherwise wait for good
    /// (issue 39's deadlocks on the intersection). Absent: never.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release_deadlock_after_secs: Option<f64>,
    /// After the no-overlap rule has settled, each step it cut is tried again whole against
    /// everyone as settled and kept where the rule lets it through: the rule's passes shorten
    /// steps in agent order against the others' steps before those are cut, so a vehicle pulling
    /// away from one about to drive into it stood with it (`road_planner::collision_guard`).
    /// Off unless set.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub regrow_cut_steps: bool,
}

/// How long an agent that breaks a deadlock (`CollisionGuard::release_deadlock_after_secs`)
/// goes on without braking for other model-driven agents, seconds.
pub const DEADLOCK_RELEASE_HOLD_SECS: f64 = 5.0;

/// The lane guard's settings: a model-driven agent whose step would take it off every lanelet
/// steers towards the point `lookahead_m` ahead on its lane's centre line, at the model's speed,
/// and stops at the road's edge if that is not enough.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaneGuard {
    /// Pure-pursuit look-ahead along the lane's centre line, metres.
    pub lookahead_m: f64,
    /// Whether a steer (or a nudge, `anticipation`) turns the agent's plan with its step: the
    /// window's future slots rotate about the agent's position before the tick by the angle
    /// its step turned, their headings with them, so that the model plans on from the
    /// corrected state rather than back towards where it had meant to go. Off unless set.
    #[serde(default)]
    pub turn_plan: bool,
    /// Nudges ahead of the road's edge: a step that stays on the road but whose
    /// constant-velocity continuation would leave it within `steps` turns towards the lane's
    /// pure-pursuit target by at most `max_turn_rad_per_m` per metre of step, its heading with
    /// it. Off unless set.
    #[serde(default)]
    pub anticipation: Option<LaneAnticipation>,
    /// A step (of 2 m/s or more) onto a lanelet running against it, more than 135° off, and
    /// onto none running its way is treated as leaving the road: steered back to its lane, or
    /// stopped short. Without it the model could take a roundabout's exit through the entry
    /// beside it and stand there, against the lane, for good (issue 39's long sessions). Off
    /// unless set.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub keep_off_opposing_lanes: bool,
}

/// The lane guard's nudges ahead of the road's edge ([`LaneGuard::anticipation`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaneAnticipation {
    /// How many steps of the constant-velocity continuation are checked (1 ..= 50).
    pub steps: usize,
    /// The largest turn of a nudge, radians per metre of step (a curvature; (0, 1]).
    pub max_turn_rad_per_m: f64,
}

/// The stall release's settings ([`PlannerSpec::stall_release`]): a model-driven vehicle
/// slower than 0.3 m/s over its last tick or on average over 2 s (or than 1 m/s with the map's
/// open end within 10 m ahead) for `after_secs` with no vehicle within 15 m ahead of it (3 m
/// either side of its axis) pulls away along its heading at `acceleration_mps2` until it
/// drives `release_speed_mps`, or the model drives it faster (on a step that keeps clear of
/// everyone; faster than `hand_back_speed_mps` too, when set), or something comes within 15 m
/// ahead; it is handed back only once its heading turned no more than 23° over the last second
/// (the model carries on a turn it sees); the lane and collision guards still apply to its
/// steps (while it backs and fills at 2 m/s, turns in place or starts off straight, the
/// collision guard by its no-overlap rule alone: the release kept those moves clear of
/// everyone as they stand). The recordings' model stops vehicles where traffic ahead of them
/// lies beyond its map crop; on an open road that stop never ends. A gridlock (standing
/// vehicles each in the path of the one before, round to the first:
/// `road_sim::free_road::BlockedPaths`) has no free road: after `gridlock_after_secs`
/// (`after_secs` when unset) one of its vehicles is pulled away all the same, not braking
/// ahead of the others, and those standing in its path make room (2 m at 2 m/s, one pointing
/// 20° or more off its lane backing with its nose turned towards it, and each step, where that
/// one would leave the road or run into a vehicle, straight back or at either full lock; none
/// over the road's edge, where a lane guard keeps vehicles on the road; one being pulled away
/// only where the release finds it wedged). The way goes to the lowest-numbered
/// of those each nearest in the path of the one before (a vehicle queued behind one of them
/// never has it); one that stands 4 s with that way (backing and filling within 2 m counts as
/// standing) passes it to the next for 10 s.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StallRelease {
    /// Seconds stood still with free road ahead before pulling away, (0, 600].
    pub after_secs: f64,
    /// Acceleration of the pull-away, m/s², (0, 5].
    pub acceleration_mps2: f64,
    /// The speed at which the model takes over again, m/s, (0, 20].
    pub release_speed_mps: f64,
    /// Seconds a gridlock's vehicle with the way out stands before it is pulled away, (0, 600];
    /// unset: `after_secs`. No brake undoes a gridlock, so there is nothing to wait for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gridlock_after_secs: Option<f64>,
    /// The least speed the model must ask for to take a pulled-away vehicle back, m/s, (0,
    /// `release_speed_mps`]; unset: the speed the release has reached. Handed back at the
    /// first step the model asked to crawl on, a vehicle the model kept stopping on free road
    /// went 1.5 m every 5 s, and its queue behind it (issue 39).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hand_back_speed_mps: Option<f64>,
    /// A vehicle that backed off for one the release finds wedged, and now stands giving way,
    /// is asked again while that one stays wedged, and backs off again (default false: asked
    /// once, it gives way 3 s). 2 m left one beside the tail of a vehicle wedged at a kerb, and
    /// the release then pulled it away forwards back beside it (11 s on FT under τ = 1;
    /// docs/experiments/2026-11-30-make-room-again.md).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub make_room_again: bool,
}

/// The stuck removal's settings ([`PlannerSpec::stuck_removal`]), the last resort of long
/// sessions, as SUMO's teleport of vehicles stuck in a jam: a model-driven vehicle that has
/// stood (slower than 0.3 m/s) with free road ahead (no vehicle within 15 m ahead, 3 m either
/// side of its axis, but for one coming towards it clear of its path) or in a gridlock (see
/// [`StallRelease`]) for `after_secs` of ticks in which the closed loop's guards or releases
/// acted on it (a wedge or gridlock their rules did not undo), or wherever it stood in ticks a
/// release's own move (a pull-away, a back-off to make room) left it standing, without moving
/// in between, leaves the scene, when no client-driven agent is within `clear_of_external_m`
/// (nobody near the ego sees a vehicle vanish). Vehicles the model keeps queued behind another
/// are never taken out. Only in scenes whose vehicles leave (served scenes, `road demo`, the
/// long suite).
///
/// With `disoriented_after_secs`, a vehicle that stood pointing across or against every
/// lanelet under it (more than 60° off each, or on none) in ticks a guard or release acted on
/// it leaves after that many seconds of such ticks in a row, whatever is ahead: no driver stands
/// across a roundabout's ring, and 7 of 8 clusters of gridlocked vehicles that stood 10 s or
/// more in issue 39's long sessions on FT and MA held such a vehicle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StuckRemoval {
    /// Seconds stood stuck before leaving, (0, 600].
    pub after_secs: f64,
    /// No client-driven agent within this distance, metres, [0, 10 000].
    pub clear_of_external_m: f64,
    /// Seconds stood across or against its lanes before leaving, (0, 600]; none: such a
    /// vehicle waits for `after_secs` like any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disoriented_after_secs: Option<f64>,
}

/// The give-way rule's settings ([`PlannerSpec::give_way`]): a model-driven vehicle on a
/// lanelet that a map's regulatory element makes give way (`road_data::rules`) stops before
/// the lanelet's end (its stop line), braking at no more than `brake_mps2` (one that cannot
/// stop by the line goes on), unless the way is clear:
/// - at a right of way, no vehicle on a priority lanelet or the lanelets leading into one is
///   due at that lanelet's end within `gap_secs`, and no vehicle stands just beyond the line;
/// - at an all-way stop, it stood at the line for `stop_secs`, everyone who stood at the
///   element's lines before it and would cross its way has gone, and nobody is in the junction
///   in its way (vehicles from its own lane ahead of it aside).
///
/// Once it goes it keeps going until it leaves the lanelet. A vehicle waiting so is no stall
/// for the stall release and never stuck for the stuck removal.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GiveWay {
    /// How far before its stop line a vehicle heeds it, metres, (0, 100].
    pub approach_m: f64,
    /// A priority vehicle due at its lanelet's end within this many seconds has the way, (0, 30].
    pub gap_secs: f64,
    /// The most deceleration to stop at the line, m/s², (0, 10].
    pub brake_mps2: f64,
    /// Seconds stood at an all-way stop's line before going, [0, 30].
    pub stop_secs: f64,
}

/// The longest lane-guard look-ahead accepted, metres (a few lanelets of an INTERACTION map).
pub const MAX_LANE_GUARD_LOOKAHEAD_M: f64 = 50.0;

impl Default for PlannerSpec {
    fn default() -> Self {
        Self {
            kind: PlannerKind::Rolling,
            obs_slots: 10,
            future_slots: 10,
            steps_per_diffusion: 40,
            replan_every: None,
            obs_sigma: None,
            obs_noise: None,
            acceleration_smoothing: None,
            jerk_tracking: None,
            plan_smoothing: None,
            plan_smoothing_ahead: None,
            noise_temperature: None,
            collision_guard: None,
            lane_guard: None,
            stall_release: None,
            stuck_removal: None,
            give_way: None,
            sampler: Sampler::Heun,
            edm: EdmSchedule::default(),
        }
    }
}

impl PlannerSpec {
    /// `W = n + F`.
    pub fn window_slots(&self) -> usize {
        self.obs_slots + self.future_slots
    }

    pub fn obs_sigma(&self) -> f64 {
        self.obs_sigma.unwrap_or(self.edm.sigma_min)
    }

    /// τ of the pure noise future slots start from (`noise_temperature`; 1 when absent).
    pub fn noise_temperature(&self) -> f64 {
        self.noise_temperature.unwrap_or(1.0)
    }

    /// The noise added to observations: `obs_noise`, else `obs_sigma()`.
    pub fn obs_noise(&self) -> f64 {
        self.obs_noise.unwrap_or_else(|| self.obs_sigma())
    }

    /// Plan smoothing's fit, when on: (committed positions, planned slots) it takes beside the
    /// emitted one.
    pub fn plan_smoothing_fit(&self) -> Option<(usize, usize)> {
        self.plan_smoothing
            .map(|h| (h, self.plan_smoothing_ahead.unwrap_or(h)))
    }

    /// Steps of a rolling stage: `K/F`.
    pub fn rolling_steps(&self) -> usize {
        self.steps_per_diffusion / self.future_slots
    }

    /// Checks the combination; `name` goes into the error.
    pub fn validate(&self, name: &str) -> Result<()> {
        let bad = |reason: String| {
            Err(Error::InvalidPlanner {
                name: name.to_owned(),
                reason,
            })
        };
        if self.obs_slots == 0 {
            return bad("obs_slots must be at least 1".into());
        }
        if self.future_slots == 0 {
            return bad("future_slots must be at least 1".into());
        }
        if self.steps_per_diffusion == 0 {
            return bad("steps_per_diffusion (K) must be at least 1".into());
        }
        let obs_sigma = self.obs_sigma();
        if !(obs_sigma.is_finite() && obs_sigma > 0.0) {
            return bad(format!(
                "obs_sigma must be positive and finite, got {obs_sigma}"
            ));
        }
        let obs_noise = self.obs_noise();
        if !(obs_noise.is_finite() && obs_noise >= 0.0) {
            return bad(format!(
                "obs_noise must be zero or positive and finite, got {obs_noise}"
            ));
        }
        if let Some(alpha) = self.acceleration_smoothing {
            if !(alpha > 0.0 && alpha <= 1.0) {
                return bad(format!(
                    "acceleration_smoothing must be in (0, 1], got {alpha}"
                ));
            }
        }
        if let Some(tracking) = self.jerk_tracking {
            if !(tracking.jerk_cost_m.is_finite() && tracking.jerk_cost_m > 0.0) {
                return bad(format!(
                    "jerk_tracking.jerk_cost_m must be positive and finite, got {}",
                    tracking.jerk_cost_m
                ));
            }
            if let Some(bound) = tracking.max_acceleration_mps2 {
                if !(bound.is_finite() && bound > 0.0) {
                    return bad(format!(
                        "jerk_tracking.max_acceleration_mps2 must be positive and finite, got {bound}"
                    ));
                }
            }
            if let Some(slip) = tracking.max_slip_deg {
                if !(slip.is_finite() && (0.0..90.0).contains(&slip)) {
                    return bad(format!(
                        "jerk_tracking.max_slip_deg must be 0 to below 90 degrees, got {slip}"
                    ));
                }
            }
            if let Some(offset) = tracking.max_course_offset_deg {
                if !(offset.is_finite() && (0.0..90.0).contains(&offset)) {
                    return bad(format!(
                        "jerk_tracking.max_course_offset_deg must be 0 to below 90 degrees, got {offset}"
                    ));
                }
            }
            if let Some(radius) = tracking.min_turn_radius_m {
                if !(radius.is_finite() && radius > 0.0 && radius <= 50.0) {
                    return bad(format!(
                        "jerk_tracking.min_turn_radius_m must be above 0 and at most 50 metres, got {radius}"
                    ));
                }
            }
            if tracking.ahead > MAX_JERK_TRACKING_AHEAD.min(self.future_slots) {
                return bad(format!(
                    "jerk_tracking.ahead must be 0 to {} slots, got {}",
                    MAX_JERK_TRACKING_AHEAD.min(self.future_slots),
                    tracking.ahead
                ));
            }
        }
        if let Some(h) = self.plan_smoothing {
            if !(1..=MAX_PLAN_SMOOTHING_STEPS).contains(&h) {
                return bad(format!(
                    "plan_smoothing must be 1 to {MAX_PLAN_SMOOTHING_STEPS} steps, got {h}"
                ));
            }
        }
        match (self.plan_smoothing, self.plan_smoothing_ahead) {
            (None, Some(_)) => {
                return bad("plan_smoothing_ahead needs plan_smoothing".to_owned());
            }
            (Some(h), Some(ahead)) if ahead > h => {
                return bad(format!(
                    "plan_smoothing_ahead must be 0 to plan_smoothing ({h}), got {ahead}"
                ));
            }
            _ => {}
        }
        if let Some(tau) = self.noise_temperature {
            if !(tau > 0.0 && tau <= 2.0) {
                return bad(format!("noise_temperature must be in (0, 2], got {tau}"));
            }
        }
        if let Some(guard) = self.collision_guard {
            if !(guard.brake_mps2.is_finite() && guard.brake_mps2 > 0.0) {
                return bad(format!(
                    "collision_guard.brake_mps2 must be positive and finite, got {}",
                    guard.brake_mps2
                ));
            }
            if guard.horizon_steps > MAX_GUARD_HORIZON_STEPS {
                return bad(format!(
                    "collision_guard.horizon_steps must be at most {MAX_GUARD_HORIZON_STEPS} \
                     ({} s), got {}",
                    MAX_GUARD_HORIZON_STEPS / 10,
                    guard.horizon_steps
                ));
            }
            if let Some(secs) = guard.release_deadlock_after_secs {
                if !(secs.is_finite() && secs > 0.0 && secs <= 600.0) {
                    return bad(format!(
                        "collision_guard.release_deadlock_after_secs must be above 0 and at most 600 seconds, got {secs}"
                    ));
                }
            }
        }
        if let Some(anticipation) = self.lane_guard.and_then(|g| g.anticipation) {
            let turn = anticipation.max_turn_rad_per_m;
            if !((1..=50).contains(&anticipation.steps) && turn > 0.0 && turn <= 1.0) {
                return bad(format!(
                    "lane_guard.anticipation: steps must be in 1..=50 and max_turn_rad_per_m in \
                     (0, 1], got {} and {}",
                    anticipation.steps, anticipation.max_turn_rad_per_m
                ));
            }
        }
        if let Some(release) = self.stall_release {
            let ok = release.after_secs > 0.0
                && release.after_secs <= 600.0
                && release.acceleration_mps2 > 0.0
                && release.acceleration_mps2 <= 5.0
                && release.release_speed_mps > 0.0
                && release.release_speed_mps <= 20.0
                && release
                    .gridlock_after_secs
                    .is_none_or(|secs| secs > 0.0 && secs <= 600.0)
                && release
                    .hand_back_speed_mps
                    .is_none_or(|mps| mps > 0.0 && mps <= release.release_speed_mps);
            if !ok {
                return bad(format!(
                    "stall_release: after_secs must be in (0, 600], acceleration_mps2 in (0, 5], \
                     release_speed_mps in (0, 20], gridlock_after_secs, when set, in (0, 600] \
                     and hand_back_speed_mps, when set, in (0, release_speed_mps], got \
                     {release:?}"
                ));
            }
        }
        if let Some(rule) = self.give_way {
            let ok = rule.approach_m > 0.0
                && rule.approach_m <= 100.0
                && rule.gap_secs > 0.0
                && rule.gap_secs <= 30.0
                && rule.brake_mps2 > 0.0
                && rule.brake_mps2 <= 10.0
                && (0.0..=30.0).contains(&rule.stop_secs);
            if !ok {
                return bad(format!(
                    "give_way: approach_m must be in (0, 100], gap_secs in (0, 30], brake_mps2 \
                     in (0, 10] and stop_secs in [0, 30], got {rule:?}"
                ));
            }
        }
        if let Some(removal) = self.stuck_removal {
            let in_range = |secs: f64| secs > 0.0 && secs <= 600.0;
            let ok = in_range(removal.after_secs)
                && removal.disoriented_after_secs.is_none_or(in_range)
                && (0.0..=10_000.0).contains(&removal.clear_of_external_m);
            if !ok {
                return bad(format!(
                    "stuck_removal: after_secs and disoriented_after_secs must be in (0, 600] and \
                     clear_of_external_m in [0, 10000], got {removal:?}"
                ));
            }
        }
        if let Some(guard) = self.lane_guard {
            if !(guard.lookahead_m > 0.0 && guard.lookahead_m <= MAX_LANE_GUARD_LOOKAHEAD_M) {
                return bad(format!(
                    "lane_guard.lookahead_m must be in (0, {MAX_LANE_GUARD_LOOKAHEAD_M}] m, got {}",
                    guard.lookahead_m
                ));
            }
        }
        let e = &self.edm;
        if !(e.sigma_min > 0.0 && e.sigma_max > e.sigma_min && e.rho > 0.0 && e.sigma_data > 0.0) {
            return bad(format!("EDM constants out of range: {e:?}"));
        }
        match self.kind {
            PlannerKind::Rolling => {
                if !self.steps_per_diffusion.is_multiple_of(self.future_slots) {
                    return bad(format!(
                        "steps_per_diffusion (K = {}) must be a multiple of future_slots (F = {})",
                        self.steps_per_diffusion, self.future_slots
                    ));
                }
            }
            PlannerKind::Autoregressive => {
                if self.future_slots != 1 {
                    return bad(format!(
                        "autoregressive needs future_slots = 1, got {}",
                        self.future_slots
                    ));
                }
            }
            PlannerKind::Mpc => match self.replan_every {
                Some(x) if x >= 1 && x <= self.future_slots => {}
                Some(x) => {
                    return bad(format!(
                        "replan_every must be in 1..={}, got {x}",
                        self.future_slots
                    ));
                }
                None => return bad("mpc needs replan_every (X)".into()),
            },
            PlannerKind::OneShot => {}
        }
        if self.kind != PlannerKind::Mpc && self.replan_every.is_some() {
            return bad("replan_every only applies to kind = \"mpc\"".into());
        }
        Ok(())
    }

    /// The stage a tick runs and what it emits, for tick number `tick` (0-based) of a scene.
    pub fn tick_program(&self, tick: u64) -> Option<TickProgram> {
        let f = self.future_slots as u64;
        match self.kind {
            PlannerKind::Rolling | PlannerKind::Autoregressive => Some(TickProgram {
                stage: Some(if tick == 0 {
                    StageKind::Warmup
                } else {
                    StageKind::Rolling
                }),
                emit_future_slot: 0,
                then: WindowUpdate::Shift,
            }),
            PlannerKind::Mpc => {
                let x = self.replan_every.unwrap_or(1) as u64;
                let pos = tick % x;
                Some(TickProgram {
                    stage: (pos == 0).then_some(StageKind::Full),
                    emit_future_slot: pos as usize,
                    then: if pos + 1 == x {
                        WindowUpdate::Rebuild
                    } else {
                        WindowUpdate::Hold
                    },
                })
            }
            PlannerKind::OneShot => (tick < f).then(|| TickProgram {
                stage: (tick == 0).then_some(StageKind::Full),
                emit_future_slot: tick as usize,
                then: if tick + 1 == f {
                    WindowUpdate::Exhausted
                } else {
                    WindowUpdate::Hold
                },
            }),
        }
    }

    /// NFE per simulated step predicted by the math doc's table, averaged over `ticks` ticks.
    pub fn expected_nfe_per_step(&self, ticks: u64) -> f64 {
        let k = self.steps_per_diffusion as f64;
        let f = self.future_slots as f64;
        let t = ticks as f64;
        if self.sampler == Sampler::Multistep {
            // One evaluation per step, whatever the step.
            return match self.kind {
                PlannerKind::Rolling | PlannerKind::Autoregressive => (k + (t - 1.0) * k / f) / t,
                PlannerKind::Mpc => {
                    let x = self.replan_every.unwrap_or(1) as u64;
                    ticks.div_ceil(x) as f64 * k / t
                }
                PlannerKind::OneShot => k / t,
            };
        }
        match self.kind {
            // Warm-up: K steps, 2 NFE each (slot 0 lands on 0 while the others stay noisy,
            // except when F = 1). Rolling stage: K/F steps of 2 NFE, the same exception.
            PlannerKind::Rolling | PlannerKind::Autoregressive => {
                let last_step_single = self.future_slots == 1;
                let warm = 2.0 * k - f64::from(u8::from(last_step_single));
                let roll = 2.0 * k / f - f64::from(u8::from(last_step_single));
                (warm + (t - 1.0) * roll) / t
            }
            PlannerKind::Mpc => {
                let x = self.replan_every.unwrap_or(1) as u64;
                let replans = ticks.div_ceil(x) as f64;
                replans * (2.0 * k - 1.0) / t
            }
            PlannerKind::OneShot => (2.0 * k - 1.0) / t,
        }
    }
}

/// Which σ profile a stage follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum StageKind {
    Warmup,
    Rolling,
    Full,
}

/// What the caller must do to the window after a tick's emission.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WindowUpdate {
    /// Drop the oldest observation, the emitted slot joins the observations, append a
    /// pure-noise slot at the end (RoAD, AR).
    Shift,
    /// Keep the plan; the next tick emits the next future slot without a model evaluation.
    Hold,
    /// Discard the plan: the next tick rebuilds the window from the newest `n` states and fresh
    /// noise and replans (MPC).
    Rebuild,
    /// The one-shot horizon is spent: the scene cannot tick again.
    Exhausted,
}

/// One tick of one scene: the stage to run (none when the state is already planned), which
/// future slot holds the emitted state, and the window update that follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TickProgram {
    pub stage: Option<StageKind>,
    pub emit_future_slot: usize,
    pub then: WindowUpdate,
}

/// One step of a stage: noise levels of every window slot before and after it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepPlan<'a> {
    /// `[W]`: σ of each slot now (observed slots first).
    pub sigma_cur: &'a [f32],
    /// `[W]`: σ of each slot after the step; 0 = clean.
    pub sigma_next: &'a [f32],
    /// Model evaluations this step costs: 2 (Heun), 1 when every changing slot lands on 0 or
    /// under the multistep sampler.
    pub nfe: u8,
}

/// Every step of one stage of one planner, flattened: `[steps, W]` row-major.
#[derive(Debug, Clone)]
pub struct StageTable {
    pub kind: StageKind,
    window_slots: usize,
    sigma_cur: Vec<f32>,  // [steps, W]
    sigma_next: Vec<f32>, // [steps, W]
    nfe: Vec<u8>,         // [steps]
}

impl StageTable {
    /// Builds the table of `steps` uniform steps of τ from 1 to 0 along `kind`'s profile.
    pub fn build(spec: &PlannerSpec, kind: StageKind, steps: usize) -> Self {
        let (n, f) = (spec.obs_slots, spec.future_slots);
        let w = n + f;
        let profile: fn(usize, usize, f64) -> f64 = match kind {
            StageKind::Warmup => warmup_u,
            StageKind::Rolling => rolling_u,
            StageKind::Full => full_u,
        };
        let obs_sigma = spec.obs_sigma() as f32;
        let mut sigma_cur = Vec::with_capacity(steps * w);
        let mut sigma_next = Vec::with_capacity(steps * w);
        let mut nfe = Vec::with_capacity(steps);
        for step in 0..steps {
            let tau_cur = 1.0 - step as f64 / steps as f64;
            // Exactly 0 at the last step so that slot 0 ends clean without rounding.
            let tau_next = if step + 1 == steps {
                0.0
            } else {
                1.0 - (step + 1) as f64 / steps as f64
            };
            let mut any_noisy_change = false;
            for slot in 0..w {
                let (cur, next) = if slot < n {
                    (obs_sigma, obs_sigma)
                } else {
                    let k = slot - n;
                    (
                        spec.edm.sigma(profile(k, f, tau_cur)) as f32,
                        spec.edm.sigma(profile(k, f, tau_next)) as f32,
                    )
                };
                if cur != next && next > 0.0 {
                    any_noisy_change = true;
                }
                sigma_cur.push(cur);
                sigma_next.push(next);
            }
            let second_evaluation = any_noisy_change && spec.sampler == Sampler::Heun;
            nfe.push(if second_evaluation { 2 } else { 1 });
        }
        Self {
            kind,
            window_slots: w,
            sigma_cur,
            sigma_next,
            nfe,
        }
    }

    pub fn steps(&self) -> usize {
        self.nfe.len()
    }

    pub fn step(&self, step: usize) -> StepPlan<'_> {
        let w = self.window_slots;
        StepPlan {
            sigma_cur: &self.sigma_cur[step * w..(step + 1) * w],
            sigma_next: &self.sigma_next[step * w..(step + 1) * w],
            nfe: self.nfe[step],
        }
    }

    /// Model evaluations the whole stage costs.
    pub fn nfe(&self) -> u32 {
        self.nfe.iter().map(|&n| u32::from(n)).sum()
    }
}

/// All stage tables of one planner.
#[derive(Debug, Clone)]
pub struct PlannerTables {
    pub spec: PlannerSpec,
    pub warmup: StageTable,
    pub rolling: StageTable,
    pub full: StageTable,
}

impl PlannerTables {
    pub fn new(name: &str, spec: PlannerSpec) -> Result<Self> {
        spec.validate(name)?;
        let k = spec.steps_per_diffusion;
        Ok(Self {
            warmup: StageTable::build(&spec, StageKind::Warmup, k),
            rolling: StageTable::build(&spec, StageKind::Rolling, spec.rolling_steps().max(1)),
            full: StageTable::build(&spec, StageKind::Full, k),
            spec,
        })
    }

    pub fn stage(&self, kind: StageKind) -> &StageTable {
        match kind {
            StageKind::Warmup => &self.warmup,
            StageKind::Rolling => &self.rolling,
            StageKind::Full => &self.full,
        }
    }
}
