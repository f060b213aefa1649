//! The window edits every engine makes the same way: the emitted-slot gather, the shift after
//! an emission (with the plan turns a guard asks for) and the kept estimate's shift. These are
//! the references of the `window` WGSL kernels and what the CPU engines run.

pub use road_model::plan_turn::{NO_TURN, turn_plan};

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
