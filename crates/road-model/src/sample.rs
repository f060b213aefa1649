//! Sampling rollouts: the scheduler drives the per-slot noise levels, an engine evaluates the
//! denoiser and takes a deterministic Heun step (EDM Algorithm 1 with a per-slot σ) of every
//! slot, and the driver ([`RolloutDriver`], `driver.rs`) emits, shifts and rebuilds windows.
//! Here: what the driver needs of an engine ([`StepEngine`]), the window edits every engine
//! makes the same way (their references), and whole open-loop rollouts. The engines:
//! [`CpuEngine`] (candle, the reference every engine must match) and [`FastCpuEngine`] (the CPU
//! path for users without a GPU) in `cpu_engine.rs`, the WGSL engine in `road-gpu`.

use rand::rngs::StdRng;
use road_sched::PlannerSpec;

use crate::batch::SceneInput;
pub use crate::cpu_engine::{CpuEngine, FastCpuEngine};
pub use crate::driver::{RolloutDriver, batch_seeds, stream_seed};
use crate::model::Denoiser;
use crate::{Error, Result};

/// One scene to roll out: its observed history (the last `n` slots of `history` are the
/// window's observations) and static features, in model units.
#[derive(Debug, Clone)]
pub struct RolloutScene {
    /// History and map; `history.slots ≥ n`, the newest step last.
    pub history: SceneInput,
}

/// Emitted states of every scene: `[scenes][agents, steps, 3]` in model units.
#[derive(Debug, Clone, PartialEq)]
pub struct Rollout {
    pub agents: Vec<usize>,
    pub steps: usize,
    pub states: Vec<Vec<f32>>,
    /// Model evaluations per scene over the whole rollout.
    pub nfe: u64,
}

/// What the rollout driver needs of an engine: static inputs once, then batched Heun steps on
/// device-resident windows, each scene with its own per-slot σ row (scenes at different phases,
/// or under different planners, share a batch; a scene with σ_cur = σ_next everywhere holds
/// still). Windows stay on the device from tick to tick: a scene's window is loaded only when
/// it is (re)built, a tick reads back only the emitted slots, and the shift after an emission
/// happens on the device.
pub trait StepEngine {
    /// W of the model.
    fn window_slots(&self) -> usize;
    /// Metres per model position unit (the model's `position_scale_m`), for planner options
    /// given in metres (without it `jerk_tracking.max_acceleration_mps2` cannot apply); None for
    /// an engine that does not know it. Engines that wrap another pass its answer on.
    fn position_scale_m(&self) -> Option<f64> {
        None
    }
    /// State units per radian of heading (the model's `heading_scale`), for planner options
    /// that need an agent's direction (least-jerk tracking's reversal check and slip bound);
    /// None for an engine that does not know it. Engines that wrap another pass its answer on.
    fn heading_scale(&self) -> Option<f64> {
        None
    }
    /// `features [B, A, 6]`, `map [B, P, Q, 2]`, `map_valid [B, P]`.
    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()>;
    /// Replaces the static inputs of scene `scene` of the prepared batch, `features [A, 6]`,
    /// `map [P, Q, 2]`, `map_valid [P]` (A, P: the batch's), leaving every other scene's inputs
    /// and window as they are: how a scene joins a batch that keeps running (a server's pool).
    /// Its window follows with [`Self::load_scene`].
    fn prepare_scene(
        &mut self,
        scene: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        let _ = (scene, features, map, map_valid);
        Err(Error::data(
            "this engine cannot admit a scene into a running batch (prepare_scene)".into(),
        ))
    }
    /// Every window `[B, A, W, 3]` and validity `[B, A, W]`, once after `prepare`.
    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()>;
    /// One scene's window `[A, W, 3]` and validity `[A, W]` (at the start of its stage).
    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()>;
    /// One Heun step of every scene, σ `[B, W]` per scene and slot (EDM Algorithm 1, per slot).
    /// Without `second_evaluation` every changing slot takes the Euler step.
    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()>;
    /// Each scene's emitted states `[B, A, 3]` from window slot `slots[b]` (`None`: not read,
    /// zeros): a tick's only readback, unless a scene's planner or client needs its plan
    /// (`read_denoised`).
    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()>;
    /// The last denoiser estimates D(x; σ) of `scenes`, `[scenes, A, W, 3]` (A: the batch's),
    /// each from the last step that moved its scene (zeros before one): the model's plan of
    /// the window, read in one go for every scene that needs it this round. Engines that do
    /// not keep it say so.
    fn read_denoised(&mut self, scenes: &[usize], out: &mut [f32]) -> Result<()> {
        let _ = (scenes, out);
        Err(Error::data(
            "this engine does not keep its denoiser estimate (read_denoised)".into(),
        ))
    }
    /// One step of the multistep sampler (`road_sched::Sampler::Multistep`), one evaluation:
    /// with D = D(x; σ_cur), the Euler step of [`Self::step`], then `x += γ·(D − D_prev)` per
    /// scene and slot, `gamma [B, W]` (0: no correction), D_prev being the kept estimate of
    /// [`Self::read_denoised`] (moved along with each shift, [`estimate_shift`]); then D is
    /// kept. Scenes whose σ row does not change hold still and keep their estimate.
    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
    ) -> Result<()> {
        let _ = (sigma_cur, sigma_next, gamma);
        Err(Error::data(
            "this engine does not implement the multistep sampler (step_multistep)".into(),
        ))
    }
    /// After an emission, on the device: every scene with an edit shifts its window by one
    /// slot (see [`window_shift`]) and takes the edit's validity `[A, W]`; its kept estimate
    /// moves with it ([`estimate_shift`]).
    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()>;
}

/// One scene's window shift after an emission.
#[derive(Debug, Clone, Copy)]
pub struct ShiftEdit<'a> {
    pub scene: usize,
    /// The emitted states as they join the observations (controllers' overrides applied),
    /// `[agents, 3]`.
    pub emitted: &'a [f32],
    /// Standard normal draws `[agents, 6]`: observation noise (3), then the new slot's (3).
    pub noise: &'a [f32],
    /// The window's validity after the shift, `[A, W]`.
    pub valid: &'a [f32],
    /// Per agent, how its plan turns with a correction of its emitted state, `[agents, 4]`:
    /// pivot x, pivot y (model units), angle (radians), heading change (model units); empty
    /// when nothing turns ([`turn_plan`]).
    pub turns: &'a [f32],
}

/// The values of one agent in [`ShiftEdit::turns`]: its plan left as it is.
pub const NO_TURN: [f32; 4] = [0.0; 4];

/// One future slot's state `[3]` turned by `turn` ([`ShiftEdit::turns`]): the position
/// rotated by the angle about the pivot, the heading changed by as much. The reference of the
/// turn in the `window_shift` kernel (which computes in the same order). A zero turn leaves
/// the state bit for bit as it is.
pub fn turn_plan(state: &mut [f32], turn: &[f32]) {
    let [pivot_x, pivot_y, angle_rad, heading_change] = [turn[0], turn[1], turn[2], turn[3]];
    if angle_rad == 0.0 && heading_change == 0.0 {
        return;
    }
    let (sin, cos) = angle_rad.sin_cos();
    let (dx, dy) = (state[0] - pivot_x, state[1] - pivot_y);
    state[0] = pivot_x + (cos * dx - sin * dy);
    state[1] = pivot_y + (sin * dx + cos * dy);
    state[2] += heading_change;
}

/// What a shift needs to know of the planner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShiftShape {
    /// n: observed slots.
    pub observed: usize,
    pub obs_noise: f32,
    pub sigma_max: f32,
}

/// Gathers slot `slots[b]` of every scene's window `[B, A, W, 3]` into `out [B, A, 3]` (zeros
/// where `None`). The reference of the `window_emitted` kernel.
pub fn window_emitted(
    windows: &[f32],
    agents: usize,
    w: usize,
    slots: &[Option<usize>],
    out: &mut [f32],
) {
    for (b, slot) in slots.iter().enumerate() {
        for a in 0..agents {
            let o = &mut out[3 * (b * agents + a)..][..3];
            match slot {
                Some(s) => o.copy_from_slice(&windows[3 * ((b * agents + a) * w + s)..][..3]),
                None => o.fill(0.0),
            }
        }
    }
}

/// The window after an emission from slot n of scene `scene` (`window [A, W, 3]` of that scene):
/// slots move up by one, slot n − 1 = emitted + obs_noise·noise, slot W − 1 = σ_max·noise (agents past
/// `emitted`'s count are padding and untouched but for the move); then each agent's future
/// slots n … W − 2 (its plan, not the fresh slot) turn by its entry of `edit.turns`
/// ([`turn_plan`]). The reference of the `window_shift` kernel.
pub fn window_shift(window: &mut [f32], w: usize, edit: &ShiftEdit<'_>, shape: ShiftShape) {
    let agents = window.len() / (3 * w);
    let real = edit.emitted.len() / 3;
    for a in 0..agents {
        let row = a * w;
        window.copy_within(3 * (row + 1)..3 * (row + w), 3 * row);
        for d in 0..3 {
            let (e, obs, new) = if a < real {
                (
                    edit.emitted[3 * a + d],
                    edit.noise[6 * a + d],
                    edit.noise[6 * a + 3 + d],
                )
            } else {
                (0.0, 0.0, 0.0)
            };
            window[3 * (row + shape.observed - 1) + d] = e + shape.obs_noise * obs;
            window[3 * (row + w - 1) + d] = shape.sigma_max * new;
        }
        if a < real && !edit.turns.is_empty() {
            let turn = &edit.turns[4 * a..4 * a + 4];
            for slot in shape.observed..w - 1 {
                turn_plan(&mut window[3 * (row + slot)..3 * (row + slot) + 3], turn);
            }
        }
    }
}

/// A scene's kept denoiser estimate `[A, W, 3]` after its window shifted: each slot's estimate
/// moves up with the slot, so that the multistep sampler finds it where the slot now is; the
/// slots that are new to their place (the joining observation n − 1 and the fresh slot W − 1)
/// get zeros (the sampler does not correct them), and the plan turns as the window's does
/// (`turns`, [`ShiftEdit::turns`]). [`window_shift`] with zeros emitted and no noise: the GPU
/// engines run the same kernel on their estimate.
pub fn estimate_shift(estimate: &mut [f32], w: usize, observed: usize, turns: &[f32]) {
    let zeros = vec![0.0; turns.len() / 4 * 3];
    let no_noise = vec![0.0; turns.len() / 4 * 6];
    let edit = ShiftEdit {
        scene: 0,
        emitted: &zeros,
        noise: &no_noise,
        valid: &[],
        turns,
    };
    let shape = ShiftShape {
        observed,
        obs_noise: 0.0,
        sigma_max: 0.0,
    };
    window_shift(estimate, w, &edit, shape);
}

/// Rolls out `steps` simulated steps of every scene with `planner` on the candle reference
/// (open loop: every agent is the model's). `rng` draws all noise.
pub fn rollout(
    model: &Denoiser,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    rng: &mut StdRng,
) -> Result<Rollout> {
    rollout_with(&mut CpuEngine::new(model), planner, scenes, steps, rng)
}

/// Rolls out `steps` simulated steps of every scene with `planner` on `engine`. The noise draws
/// depend only on `rng`, so two engines given the same seed sample the same futures (to their
/// numerical agreement).
pub fn rollout_with(
    engine: &mut dyn StepEngine,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    rng: &mut StdRng,
) -> Result<Rollout> {
    let seeds = crate::driver::batch_seeds(rng, scenes.len());
    rollout_seeded(engine, planner, scenes, steps, &seeds)
}

/// [`rollout_with`] with each scene's noise stream seeded by the caller (`seeds[i]` for scene
/// `i`; see `RolloutDriver::with_seeds`).
pub fn rollout_seeded(
    engine: &mut dyn StepEngine,
    planner: &PlannerSpec,
    scenes: &[RolloutScene],
    steps: usize,
    seeds: &[u64],
) -> Result<Rollout> {
    if scenes.is_empty() {
        return Ok(Rollout {
            agents: vec![],
            steps,
            states: vec![],
            nfe: 0,
        });
    }
    let mut driver = RolloutDriver::with_seeds(engine, planner, scenes, seeds, steps)?;
    for _ in 0..steps {
        driver.tick(engine, &mut |_, _, _| Ok(()))?;
    }
    driver.into_rollout()
}

impl From<road_sched::Error> for Error {
    fn from(e: road_sched::Error) -> Self {
        Error::data(format!("scheduler: {e}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quarter_turn_rotates_about_the_pivot_and_changes_the_heading() {
        let mut state = [3.0f32, 2.0, 0.1];
        turn_plan(&mut state, &[2.0, 2.0, std::f32::consts::FRAC_PI_2, 0.4]);
        let expected = [2.0f32, 3.0, 0.5];
        for (got, want) in state.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{state:?} against {expected:?}");
        }
    }

    #[test]
    fn no_turn_leaves_a_state_bit_for_bit() {
        let mut state = [0.1f32, -7.3, 1e-3];
        turn_plan(&mut state, &NO_TURN);
        assert_eq!(state, [0.1f32, -7.3, 1e-3]);
    }
}
