//! What the rollout driver needs of an engine ([`StepEngine`]), and what a rollout is made of.
//! The engines: `road_cpu::CpuEngine` (candle, the reference every engine must match) and
//! `road_cpu::FastCpuEngine` (the CPU path for users without a GPU), the WGSL engine in
//! `road-gpu`.

use road_model::batch::SceneInput;
use road_model::{Error, Result};

use crate::window::{ShiftEdit, ShiftShape};

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
    /// A round's readback: [`Self::read_emitted`] into `out`, then, when `scenes` is not
    /// empty, [`Self::read_denoised`] of them into `denoised`. An engine on a device overrides
    /// it to read both in one submission and one wait.
    fn read_emitted_and_denoised(
        &mut self,
        slots: &[Option<usize>],
        out: &mut [f32],
        scenes: &[usize],
        denoised: &mut [f32],
    ) -> Result<()> {
        self.read_emitted(slots, out)?;
        if !scenes.is_empty() {
            self.read_denoised(scenes, denoised)?;
        }
        Ok(())
    }
    /// One step of the multistep sampler (`road_sched::Sampler::Multistep`), one evaluation:
    /// with D = D(x; σ_cur), the Euler step of [`Self::step`], then `x += γ·(D − D_prev)` per
    /// scene and slot, `gamma [B, W]` (0: no correction), D_prev being the kept estimate of
    /// [`Self::read_denoised`] (moved along with each shift, [`estimate_shift`](crate::window::estimate_shift)); then D is
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
    /// slot (see [`window_shift`](crate::window::window_shift)) and takes the edit's validity `[A, W]`; its kept estimate
    /// moves with it ([`estimate_shift`](crate::window::estimate_shift)).
    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()>;
}
