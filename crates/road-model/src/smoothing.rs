//! Acceleration smoothing of emitted states (a planner option, `acceleration_smoothing`): a
//! deviation from the paper, measured in `docs/results.md`.
//!
//! Each emitted slot ends its own denoising at σ_min, independently of its neighbours, so a
//! position error of a few centimetres changes from step to step; differentiated three times
//! at 10 Hz that is jerk of tens of m/s³ (the "jitter" of issue 13). The smoothing low-passes
//! each agent's acceleration (the second difference of its positions, both axes) before the
//! state joins the history and the window: `a = a_prev + α · (a_model − a_prev)`, so the
//! emitted position is `2·p₂ − p₁ + a`. α = 1 is the model's state unchanged; smaller α damps
//! step-to-step noise and delays a change of acceleration by about 1/α steps. Headings are the
//! model's. (Smoothing only the longitudinal part, along the direction of travel, was tried and
//! measured worse: more collisions; `docs/results.md`.)

/// Smooths `emitted` (`[agents, 3]`: x, y, heading) against each agent's history (its last
/// three states must be valid; other agents are left as they are).
pub fn smooth_accelerations(
    history: &[Vec<[f32; 3]>],
    history_valid: &[Vec<bool>],
    emitted: &mut [f32],
    alpha: f32,
) {
    for (a, (states, valid)) in history.iter().zip(history_valid).enumerate() {
        let t = states.len();
        if t < 3 || !valid[t - 3..].iter().all(|&v| v) {
            continue;
        }
        let (p0, p1, p2) = (states[t - 3], states[t - 2], states[t - 1]);
        for d in 0..2 {
            let previous = p2[d] - 2.0 * p1[d] + p0[d];
            let model = emitted[3 * a + d] - 2.0 * p2[d] + p1[d];
            let smoothed = previous + alpha * (model - previous);
            emitted[3 * a + d] = 2.0 * p2[d] - p1[d] + smoothed;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(speed: f32, steps: usize) -> Vec<[f32; 3]> {
        (0..steps).map(|t| [speed * t as f32, 1.0, 0.3]).collect()
    }

    #[test]
    fn constant_velocity_passes_unchanged_and_alpha_one_is_the_identity() {
        let history = vec![line(0.1, 5)];
        let valid = vec![vec![true; 5]];
        let mut emitted = [0.5, 1.0, 0.3];
        smooth_accelerations(&history, &valid, &mut emitted, 0.3);
        assert!((emitted[0] - 0.5).abs() < 1e-6 && (emitted[1] - 1.0).abs() < 1e-6);
        let mut noisy = [0.53, 0.98, 0.2];
        smooth_accelerations(&history, &valid, &mut noisy, 1.0);
        assert_eq!(noisy, [0.53, 0.98, 0.2]);
    }

    #[test]
    fn a_jump_is_damped_by_alpha_and_the_heading_kept() {
        let history = vec![line(0.1, 5)];
        let valid = vec![vec![true; 5]];
        // Constant velocity would put it at 0.5; the model says 0.6 (an acceleration of 0.1).
        let mut emitted = [0.6, 1.0, 0.7];
        smooth_accelerations(&history, &valid, &mut emitted, 0.25);
        assert!((emitted[0] - 0.525).abs() < 1e-6, "{emitted:?}");
        assert_eq!(emitted[2], 0.7);
    }

    #[test]
    fn a_stopped_agent_is_smoothed_in_both_directions() {
        let history = vec![vec![[0.2, 0.2, 0.0]; 4]];
        let valid = vec![vec![true; 4]];
        let mut emitted = [0.21, 0.19, 0.0];
        smooth_accelerations(&history, &valid, &mut emitted, 0.5);
        assert!((emitted[0] - 0.205).abs() < 1e-6 && (emitted[1] - 0.195).abs() < 1e-6);
    }

    #[test]
    fn agents_without_three_valid_states_are_left_alone() {
        let history = vec![line(0.1, 2), line(0.1, 5)];
        let valid = vec![vec![true; 2], vec![true, true, false, true, true]];
        let mut emitted = [0.9, 0.0, 0.0, 0.9, 0.0, 0.0];
        smooth_accelerations(&history, &valid, &mut emitted, 0.1);
        assert_eq!(emitted, [0.9, 0.0, 0.0, 0.9, 0.0, 0.0]);
    }
}
