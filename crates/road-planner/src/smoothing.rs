//! Smoothing of emitted states, two planner options, both deviations from the paper measured in
//! `docs/results.md`: acceleration smoothing (`acceleration_smoothing`, a low-pass over the
//! past) and plan smoothing (`plan_smoothing`, a local fit over the past and the model's plan).
//!
//! Acceleration smoothing:
//! Each emitted slot ends its own denoising at σ_min, independently of its neighbours, so a
//! position error of a few centimetres changes from step to step; differentiated three times
//! at 10 Hz that is jerk of tens of m/s³ (the "jitter" of issue 13). The smoothing low-passes
//! each agent's acceleration (the second difference of its positions, both axes) before the
//! state joins the history and the window: `a = a_prev + α · (a_model − a_prev)`, so the
//! emitted position is `2·p₂ − p₁ + a`. α = 1 is the model's state unchanged; smaller α damps
//! step-to-step noise and delays a change of acceleration by about 1/α steps. Headings are the
//! model's. (Smoothing only the longitudinal part, along the direction of travel, was tried and
//! measured worse: more collisions; `docs/experiments/2026-11-24-steps-finished-acceleration-smoothing.md`.)

use road_sched::MAX_JERK_TRACKING_AHEAD;

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

/// Plan smoothing (`plan_smoothing = h`, `plan_smoothing_ahead = f`): each agent's emitted
/// position becomes the value at the emission step of the least-squares quadratic through its
/// last `h` committed positions (steps −h…−1), the emitted one (step 0) and the denoised
/// estimate of the next `f` slots of its window (steps 1…f, from `first_planned_slot`). A
/// quadratic is exact for constant acceleration, so steady turns and speed changes pass without
/// the lag of [`smooth_accelerations`] (whose low-pass, inside the closed loop, makes vehicles
/// weave); what the fit removes is the step-to-step scatter of independently finished slots.
/// Points are taken while they are valid, nearest first; an agent with fewer than 4 points is
/// left as it is, and headings stay the model's.
///
/// `denoised` and `window_valid` are the scene's `[agents, slots, 3]` estimate and
/// `[agents, slots]` flags (at least as many agents as `emitted` holds).
#[allow(clippy::too_many_arguments)] // one scene's history, window and emission
pub fn smooth_with_plan(
    history: &[Vec<[f32; 3]>],
    history_valid: &[Vec<bool>],
    denoised: &[f32],
    window_valid: &[f32],
    slots: usize,
    first_planned_slot: usize,
    (past_steps, planned_steps): (usize, usize),
    emitted: &mut [f32],
) {
    for (a, state) in emitted.chunks_exact_mut(3).enumerate() {
        let mut fit = QuadraticFit::default();
        fit.add(0.0, &state[..2]);
        let (past, past_valid) = (&history[a], &history_valid[a]);
        for k in 1..=past_steps.min(past.len()) {
            let t = past.len() - k;
            if !past_valid[t] {
                break;
            }
            fit.add(-(k as f64), &past[t][..2]);
        }
        for k in 1..=planned_steps {
            let slot = first_planned_slot + k - 1;
            if slot >= slots || window_valid[a * slots + slot] <= 0.0 {
                break;
            }
            fit.add(k as f64, &denoised[3 * (a * slots + slot)..][..2]);
        }
        if fit.points < 4 {
            continue;
        }
        if let Some(at_zero) = fit.at_zero() {
            state[0] = at_zero[0] as f32;
            state[1] = at_zero[1] as f32;
        }
    }
}

/// Least-jerk tracking (`jerk_tracking`, [`road_sched::JerkTracking`]): each agent with its last
/// three committed positions valid continues from their position `x`, velocity `v` and
/// acceleration `a` (first and second differences) along the path `p_k = x + (k+1)·v +
/// (k+1)(k+2)/2·a + Σ_{i≤k} (k−i+1)(k−i+2)/2·j_i` of jerks `j_0 … j_H−1` (third differences,
/// per step), chosen to minimise `Σ_k |p_k − r_k|² + jerk_weight · Σ_k |j_k|²` over the emitted
/// position `r_0` and the model's denoised estimate `r_1 …` of up to `planned_steps` slots from
/// `first_planned_slot` (while valid); `p_0` replaces the emitted position. Unlike
/// [`smooth_accelerations`], which low-passes the past, the path looks ahead along the model's
/// plan, so a turn or a braking the model plans is taken smoothly but without lag. Headings
/// stay the model's; agents without three valid committed positions are left as they are.
///
/// A path that carries a braking on past standstill runs backwards (vehicles stopped hard by
/// the collision guard reversed at up to 2 m/s, and the model, seeing them reverse, planned
/// on backwards): given `heading_scale` (state units per radian), the tracked step loses any
/// component backwards along the agent's committed heading. NPCs in traffic do not reverse.
///
/// `denoised` and `window_valid` are the scene's `[agents, slots, 3]` estimate and
/// `[agents, slots]` flags; `jerk_weight` is [`road_sched::JerkTracking::jerk_weight`];
/// `max_acceleration` (position units per step², the planner's `max_acceleration_mps2`) bounds
/// the committed acceleration's magnitude before the path carries it on; without
/// `heading_scale` there is no reversal check.
///
/// With `max_slip_tan` (the tangent of the planner's `max_slip_deg`; it needs `heading_scale`)
/// the tracked step moves sideways of the model's emitted heading no more than the model's own
/// step does, plus `max_slip_tan` times its forward motion: the path may carry a lateral
/// correction on (a lane guard's) only as far as the car heads that way. Without it 8 % of the
/// default's moving steps went more than 10° off the heading
/// (`docs/experiments/2026-11-26-sliding-sideways.md`).
#[allow(clippy::too_many_arguments)] // one scene's history, window and emission
pub fn track_least_jerk(
    history: &[Vec<[f32; 3]>],
    history_valid: &[Vec<bool>],
    denoised: &[f32],
    window_valid: &[f32],
    slots: usize,
    first_planned_slot: usize,
    planned_steps: usize,
    jerk_weight: f64,
    max_acceleration: Option<f64>,
    heading_scale: Option<f64>,
    max_slip_tan: Option<f64>,
    emitted: &mut [f32],
) {
    // Per agent and tick on the serving path: fixed-size buffers, no allocation.
    let mut targets = [[0.0f64; 2]; MAX_PATH];
    for (a, state) in emitted.chunks_exact_mut(3).enumerate() {
        let (past, past_valid) = (&history[a], &history_valid[a]);
        let t = past.len();
        if t < 3 || !past_valid[t - 3..].iter().all(|&v| v) {
            continue;
        }
        targets[0] = [f64::from(state[0]), f64::from(state[1])];
        let mut h = 1;
        for k in 0..planned_steps.min(MAX_PATH - 1) {
            let slot = first_planned_slot + k;
            if slot >= slots || window_valid[a * slots + slot] <= 0.0 {
                break;
            }
            let p = &denoised[3 * (a * slots + slot)..][..2];
            targets[h] = [f64::from(p[0]), f64::from(p[1])];
            h += 1;
        }
        // G[k][i] = (k−i+1)(k−i+2)/2 for i ≤ k: how jerk i moves position k.
        let g = |k: usize, i: usize| {
            if i > k {
                0.0
            } else {
                let d = (k - i) as f64;
                (d + 1.0) * (d + 2.0) / 2.0
            }
        };
        // Normal equations (GᵀG + λI)·j = Gᵀ(r − b), both axes sharing the matrix.
        let mut normal = [0.0f64; MAX_PATH * MAX_PATH];
        for i in 0..h {
            for l in 0..h {
                normal[i * h + l] = (i.max(l)..h).map(|k| g(k, i) * g(k, l)).sum::<f64>()
                    + if i == l { jerk_weight } else { 0.0 };
            }
        }
        let Some(factor) = cholesky(&normal, h) else {
            continue;
        };
        let (p0, p1, p2) = (past[t - 1], past[t - 2], past[t - 3]);
        let committed_acceleration =
            |d: usize| f64::from(p0[d]) - 2.0 * f64::from(p1[d]) + f64::from(p2[d]);
        let magnitude = committed_acceleration(0).hypot(committed_acceleration(1));
        let acceleration_scale = match max_acceleration {
            Some(bound) if magnitude > bound => bound / magnitude,
            _ => 1.0,
        };
        let mut step = [0.0f64; 2];
        for (d, step) in step.iter_mut().enumerate() {
            let x = f64::from(p0[d]);
            let v = x - f64::from(p1[d]);
            let acc = committed_acceleration(d) * acceleration_scale;
            let mut residual = [0.0f64; MAX_PATH];
            for (k, r) in residual.iter_mut().enumerate().take(h) {
                let kf = k as f64;
                *r = targets[k][d] - (x + (kf + 1.0) * v + (kf + 1.0) * (kf + 2.0) / 2.0 * acc);
            }
            let mut rhs = [0.0f64; MAX_PATH];
            for (i, r) in rhs.iter_mut().enumerate().take(h) {
                *r = (i..h).map(|k| g(k, i) * residual[k]).sum();
            }
            let jerks = cholesky_solve(&factor, h, &rhs);
            *step = v + acc + jerks[0];
        }
        if let Some(scale) = heading_scale {
            let heading_rad = f64::from(p0[2]) / scale;
            let forward = [heading_rad.cos(), heading_rad.sin()];
            let along = step[0] * forward[0] + step[1] * forward[1];
            if along < 0.0 {
                for d in 0..2 {
                    step[d] -= along * forward[d];
                }
            }
        }
        if let (Some(scale), Some(slip_tan)) = (heading_scale, max_slip_tan) {
            // Sideways of the model's heading, no more than the model's own step goes.
            let model_rad = f64::from(state[2]) / scale;
            let forward = [model_rad.cos(), model_rad.sin()];
            let left = [-forward[1], forward[0]];
            let model_step = [
                targets[0][0] - f64::from(p0[0]),
                targets[0][1] - f64::from(p0[1]),
            ];
            let along = step[0] * forward[0] + step[1] * forward[1];
            let lateral = step[0] * left[0] + step[1] * left[1];
            let model_lateral = model_step[0] * left[0] + model_step[1] * left[1];
            let bound = model_lateral.abs() + slip_tan * along.abs();
            if lateral.abs() > bound {
                let excess = lateral - lateral.signum() * bound;
                for d in 0..2 {
                    step[d] -= excess * left[d];
                }
            }
        }
        let from = [f64::from(p0[0]), f64::from(p0[1])];
        for d in 0..2 {
            state[d] = (from[d] + step[d]) as f32;
        }
    }
}

/// Turns each agent's emitted heading to within `max_offset_rad` of its step's course (from its
/// newest history position to the emitted one) when the step is at least `min_step` position
/// units long: a car's body follows its wheels, so at speed the box points where it moves.
/// The heading moves by the least angle that does it and keeps the model's winding (no 2π
/// jumps). Agents without a valid newest history position, and slower steps, keep the model's
/// heading. `emitted` is `[agents, 3]` with headings in `heading_scale` units per radian.
pub fn align_heading_to_course(
    history: &[Vec<[f32; 3]>],
    history_valid: &[Vec<bool>],
    emitted: &mut [f32],
    heading_scale: f64,
    min_step: f64,
    max_offset_rad: f64,
) {
    for (a, state) in emitted.chunks_exact_mut(3).enumerate() {
        let (Some(p0), Some(true)) = (history[a].last(), history_valid[a].last()) else {
            continue;
        };
        let step = [
            f64::from(state[0]) - f64::from(p0[0]),
            f64::from(state[1]) - f64::from(p0[1]),
        ];
        if step[0].hypot(step[1]) < min_step {
            continue;
        }
        let course = step[1].atan2(step[0]);
        let heading = f64::from(state[2]) / heading_scale;
        // The heading's offset from the course in (−π, π].
        let offset = (heading - course + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        let excess = offset - offset.clamp(-max_offset_rad, max_offset_rad);
        if excess != 0.0 {
            state[2] = ((heading - excess) * heading_scale) as f32;
        }
    }
}

/// Turns each agent's emitted heading from its newest history heading by at most its step's
/// length over `min_radius` (position units): a car turns no tighter than its turning circle,
/// and a standing one not at all. Agents without a valid newest history state keep the
/// model's heading. `emitted` is `[agents, 3]`, headings in `heading_scale` units per radian
/// (unwrapped: the history's and the emitted heading differ by the turn itself).
pub fn limit_turn_to_radius(
    history: &[Vec<[f32; 3]>],
    history_valid: &[Vec<bool>],
    emitted: &mut [f32],
    heading_scale: f64,
    min_radius: f64,
) {
    for (a, state) in emitted.chunks_exact_mut(3).enumerate() {
        let (Some(p0), Some(true)) = (history[a].last(), history_valid[a].last()) else {
            continue;
        };
        let step =
            (f64::from(state[0]) - f64::from(p0[0])).hypot(f64::from(state[1]) - f64::from(p0[1]));
        let max_turn_rad = step / min_radius;
        let from_rad = f64::from(p0[2]) / heading_scale;
        let turn_rad = f64::from(state[2]) / heading_scale - from_rad;
        if turn_rad.abs() > max_turn_rad {
            state[2] =
                ((from_rad + turn_rad.clamp(-max_turn_rad, max_turn_rad)) * heading_scale) as f32;
        }
    }
}

/// The longest tracked path: the emitted position and `MAX_JERK_TRACKING_AHEAD` planned slots.
const MAX_PATH: usize = MAX_JERK_TRACKING_AHEAD + 1;

/// The lower Cholesky factor `L` (row-major `[n, n]`, n ≤ [`MAX_PATH`]) of a symmetric positive
/// definite matrix; None when it is not.
fn cholesky(matrix: &[f64], n: usize) -> Option<[f64; MAX_PATH * MAX_PATH]> {
    let mut l = [0.0f64; MAX_PATH * MAX_PATH];
    for i in 0..n {
        for j in 0..=i {
            let sum: f64 = (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum();
            if i == j {
                let d = matrix[i * n + i] - sum;
                if d <= 0.0 {
                    return None;
                }
                l[i * n + i] = d.sqrt();
            } else {
                l[i * n + j] = (matrix[i * n + j] - sum) / l[j * n + j];
            }
        }
    }
    Some(l)
}

/// Solves `L·Lᵀ·x = b` for the factor of [`cholesky`] (the first `n` entries of the result).
fn cholesky_solve(l: &[f64], n: usize, b: &[f64]) -> [f64; MAX_PATH] {
    let mut y = [0.0f64; MAX_PATH];
    for i in 0..n {
        let sum: f64 = (0..i).map(|k| l[i * n + k] * y[k]).sum();
        y[i] = (b[i] - sum) / l[i * n + i];
    }
    let mut x = [0.0f64; MAX_PATH];
    for i in (0..n).rev() {
        let sum: f64 = (i + 1..n).map(|k| l[k * n + i] * x[k]).sum();
        x[i] = (y[i] - sum) / l[i * n + i];
    }
    x
}

/// The running sums of a least-squares quadratic's normal equations through points `(t, x, y)`,
/// both axes at once: `M · c = r` with `M[i][j] = Σ t^(i+j)` and `r[i] = Σ t^i · y`.
#[derive(Default)]
struct QuadraticFit {
    points: usize,
    powers: [f64; 5],
    r: [[f64; 3]; 2],
}

impl QuadraticFit {
    fn add(&mut self, t: f64, xy: &[f32]) {
        self.points += 1;
        let mut tp = 1.0;
        for (k, p) in self.powers.iter_mut().enumerate() {
            *p += tp;
            if k < 3 {
                for (r, &y) in self.r.iter_mut().zip(xy) {
                    r[k] += tp * f64::from(y);
                }
            }
            tp *= t;
        }
    }

    /// The fitted (x, y) at t = 0: c0 by Cramer's rule (None when `M` is singular).
    fn at_zero(&self) -> Option<[f64; 2]> {
        let det3 = |c: [[f64; 3]; 3]| {
            c[0][0] * (c[1][1] * c[2][2] - c[1][2] * c[2][1])
                - c[0][1] * (c[1][0] * c[2][2] - c[1][2] * c[2][0])
                + c[0][2] * (c[1][0] * c[2][1] - c[1][1] * c[2][0])
        };
        let p = &self.powers;
        let matrix = [[p[0], p[1], p[2]], [p[1], p[2], p[3]], [p[2], p[3], p[4]]];
        let det = det3(matrix);
        if det.abs() < 1e-9 {
            return None;
        }
        Some(self.r.map(|r| {
            // The first column replaced by r.
            let mut first = matrix;
            for (row, &value) in first.iter_mut().zip(&r) {
                row[0] = value;
            }
            det3(first) / det
        }))
    }
}

#[cfg(test)]
mod tests {
    use std::f32::consts::FRAC_1_SQRT_2;

    use super::*;

    #[test]
    fn turns_stay_within_the_turning_circle() {
        // Heading scale 2 units per radian, positions in metres, radius 5 m.
        let history = vec![vec![[0.0, 0.0, 0.0]]; 3];
        let valid = vec![vec![true]; 3];
        let mut emitted = vec![
            // Standing, turned 1 rad: held at 0.
            0.0, 0.0, 2.0, //
            // 1 m step, turned −0.5 rad: at most 0.2 rad (−0.4 units).
            1.0, 0.0, -1.0, //
            // 1 m step, turned 0.1 rad: within the circle, unchanged.
            1.0, 0.0, 0.2,
        ];
        limit_turn_to_radius(&history, &valid, &mut emitted, 2.0, 5.0);
        assert_eq!(emitted[2], 0.0);
        assert!((emitted[5] + 0.4).abs() < 1e-6, "{}", emitted[5]);
        assert_eq!(emitted[8], 0.2);
    }

    #[test]
    fn headings_turn_towards_the_course_of_fast_steps_only() {
        let scale = 0.25f64; // heading units per radian (the default model's)
        let deg = |d: f64| d.to_radians();
        // Five agents, each from (0, 0) with its newest history state.
        let history = vec![vec![[0.0f32, 0.0, 0.0]]; 5];
        let mut history_valid = vec![vec![true]; 5];
        history_valid[4] = vec![false];
        let state = |x: f32, y: f32, heading_rad: f64| [x, y, (heading_rad * scale) as f32];
        let mut emitted: Vec<f32> = [
            state(1.0, 0.0, deg(30.0)),  // fast, 30° off: turned to 5°
            state(1.0, 0.0, deg(-3.0)),  // within the bound: kept
            state(0.01, 0.0, deg(30.0)), // slow: kept
            state(0.0, 1.0, deg(90.0 + 40.0) + std::f64::consts::TAU), // wound once: stays so
            state(1.0, 0.0, deg(30.0)),  // no valid history: kept
        ]
        .concat();
        let before = emitted.clone();
        align_heading_to_course(
            &history,
            &history_valid,
            &mut emitted,
            scale,
            0.05,
            deg(5.0),
        );
        let heading_deg = |a: usize| (f64::from(emitted[3 * a + 2]) / scale).to_degrees();
        assert!((heading_deg(0) - 5.0).abs() < 1e-3, "{}", heading_deg(0));
        assert!(
            (heading_deg(3) - (95.0 + 360.0)).abs() < 1e-3,
            "{}",
            heading_deg(3)
        );
        for a in [1, 2, 4] {
            assert_eq!(emitted[3 * a + 2], before[3 * a + 2], "agent {a}");
        }
        // Positions never move.
        for a in 0..5 {
            assert_eq!(emitted[3 * a..3 * a + 2], before[3 * a..3 * a + 2]);
        }
    }

    /// (history, its flags, the window's denoised estimate, the window's flags) of one agent.
    type PlanCase = (Vec<Vec<[f32; 3]>>, Vec<Vec<bool>>, Vec<f32>, Vec<f32>);

    /// One agent: history at steps −len…−1 and window estimates at steps 1…, of `path(t)`.
    fn plan_case(path: impl Fn(f64) -> [f32; 2], past: usize, planned: usize) -> PlanCase {
        let history = vec![
            (0..past)
                .map(|k| {
                    let p = path(k as f64 - past as f64);
                    [p[0], p[1], 0.0]
                })
                .collect(),
        ];
        let valid = vec![vec![true; past]];
        // A window of 12 slots; the planned ones start at slot 2.
        let mut denoised = vec![0.0; 12 * 3];
        let mut window_valid = vec![0.0; 12];
        for k in 0..planned {
            let p = path(k as f64 + 1.0);
            denoised[3 * (2 + k)..][..2].copy_from_slice(&p);
            window_valid[2 + k] = 1.0;
        }
        (history, valid, denoised, window_valid)
    }

    /// [`smooth_with_plan`] of a [`plan_case`] (12 slots, planned from slot 2), h = 3.
    fn smooth_case(
        history: &[Vec<[f32; 3]>],
        valid: &[Vec<bool>],
        denoised: &[f32],
        window_valid: &[f32],
        emitted: &mut [f32],
    ) {
        smooth_with_plan(
            history,
            valid,
            denoised,
            window_valid,
            12,
            2,
            (3, 3),
            emitted,
        );
    }

    /// A path of constant acceleration that turns: (1, −0.5) at t = 0.
    fn accelerating_turn(t: f64) -> [f32; 2] {
        let (x, y) = (1.0 + 0.3 * t + 0.02 * t * t, -0.5 + 0.1 * t - 0.01 * t * t);
        [x as f32, y as f32]
    }

    #[test]
    fn plan_smoothing_keeps_constant_acceleration_and_turns_exactly() {
        let path = accelerating_turn;
        let (history, valid, denoised, window_valid) = plan_case(path, 6, 8);
        let mut emitted = [path(0.0)[0], path(0.0)[1], 0.4];
        smooth_case(&history, &valid, &denoised, &window_valid, &mut emitted);
        assert!(
            (emitted[0] - 1.0).abs() < 1e-5 && (emitted[1] + 0.5).abs() < 1e-5,
            "{emitted:?}"
        );
        assert_eq!(emitted[2], 0.4);
    }

    #[test]
    fn plan_smoothing_pulls_a_scattered_emission_back_to_the_path() {
        let path = |t: f64| [(2.0 * t) as f32, 0.0];
        let (history, valid, denoised, window_valid) = plan_case(path, 6, 8);
        // 7 points, quadratic: the emitted one weighs 7/21 at the centre.
        let mut emitted = [0.0, 0.21, 0.0];
        smooth_case(&history, &valid, &denoised, &window_valid, &mut emitted);
        assert!(emitted[0].abs() < 1e-5, "{emitted:?}");
        assert!((emitted[1] - 0.07).abs() < 1e-5, "{emitted:?}");
    }

    #[test]
    fn plan_smoothing_uses_only_valid_points_and_needs_four() {
        let path = |t: f64| [t as f32, 0.0];
        // Two past states and one planned slot: 4 points, still a fit.
        let (history, valid, denoised, window_valid) = plan_case(path, 2, 1);
        let mut emitted = [0.0, 0.3, 0.0];
        smooth_case(&history, &valid, &denoised, &window_valid, &mut emitted);
        assert!(emitted[1] < 0.3 && emitted[1] > 0.0, "{emitted:?}");
        // One past state and one planned slot: left alone.
        let (history, valid, denoised, window_valid) = plan_case(path, 1, 1);
        let mut emitted = [0.0, 0.3, 0.0];
        smooth_case(&history, &valid, &denoised, &window_valid, &mut emitted);
        assert_eq!(emitted, [0.0, 0.3, 0.0]);
        // An invalid past state cuts the history there.
        let (history, mut valid, denoised, window_valid) = plan_case(path, 4, 1);
        valid[0][2] = false;
        let mut emitted = [0.0, 0.3, 0.0];
        smooth_case(&history, &valid, &denoised, &window_valid, &mut emitted);
        assert_eq!(emitted, [0.0, 0.3, 0.0]);
    }

    #[test]
    fn plan_smoothing_takes_only_the_planned_slots_it_is_told() {
        let path = |t: f64| [t as f32, 0.0];
        let (history, valid, mut denoised, window_valid) = plan_case(path, 6, 4);
        // The 2nd to 4th planned slots (window slots 3..6) far off the path.
        for slot in 3..6 {
            denoised[3 * slot + 1] = 5.0;
        }
        let fit = |planned, emitted: &mut [f32]| {
            smooth_with_plan(
                &history,
                &valid,
                &denoised,
                &window_valid,
                12,
                2,
                (3, planned),
                emitted,
            )
        };
        // One planned slot: 3 past + emitted + 1 planned, all on the line.
        let mut emitted = [0.0, 0.0, 0.0];
        fit(1, &mut emitted);
        assert!(emitted[1].abs() < 1e-5, "{emitted:?}");
        // None: the past and the emission alone (4 points).
        let mut emitted = [0.0, 0.0, 0.0];
        fit(0, &mut emitted);
        assert!(emitted[1].abs() < 1e-5, "{emitted:?}");
        // All four: the off-path slots pull the emission off the line.
        let mut emitted = [0.0, 0.0, 0.0];
        fit(4, &mut emitted);
        assert!(emitted[1] > 0.5, "{emitted:?}");
    }

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

    /// [`track_least_jerk`] of a [`plan_case`] (12 slots, planned from slot 2).
    fn track_case(case: &PlanCase, ahead: usize, jerk_weight: f64, emitted: &mut [f32]) {
        let (history, valid, denoised, window_valid) = case;
        track_least_jerk(
            history,
            valid,
            denoised,
            window_valid,
            12,
            2,
            ahead,
            jerk_weight,
            None,
            None,
            None,
            emitted,
        );
    }

    /// [`track_least_jerk`] of agents without a plan (the emission is the only target), with
    /// the options that need no window.
    fn track_unplanned(
        history: &[Vec<[f32; 3]>],
        valid: &[Vec<bool>],
        jerk_weight: f64,
        max_acceleration: Option<f64>,
        heading_scale: Option<f64>,
        max_slip_tan: Option<f64>,
        emitted: &mut [f32],
    ) {
        track_least_jerk(
            history,
            valid,
            &[],
            &[],
            0,
            0,
            0,
            jerk_weight,
            max_acceleration,
            heading_scale,
            max_slip_tan,
            emitted,
        );
    }

    #[test]
    fn least_jerk_tracking_keeps_a_path_of_constant_acceleration() {
        let path = accelerating_turn;
        let case = plan_case(path, 6, 8);
        for ahead in [0, 3, 8] {
            let mut emitted = [path(0.0)[0], path(0.0)[1], 0.4];
            track_case(&case, ahead, 100.0, &mut emitted);
            assert!(
                (emitted[0] - 1.0).abs() < 1e-5 && (emitted[1] + 0.5).abs() < 1e-5,
                "ahead {ahead}: {emitted:?}"
            );
            assert_eq!(emitted[2], 0.4, "the heading stays the model's");
        }
    }

    #[test]
    fn without_a_plan_the_emission_moves_towards_the_jerk_free_continuation() {
        // Constant velocity 0.1 per step: the jerk-free continuation is 0.5; the model says 0.6.
        // One jerk, one target: p₀ = b₀ + (r₀ − b₀)/(1 + λ).
        let case: PlanCase = (vec![line(0.1, 5)], vec![vec![true; 5]], vec![], vec![]);
        for (weight, expected) in [(0.0, 0.6), (1.0, 0.55), (3.0, 0.525), (1e9, 0.5)] {
            let (history, valid, _, _) = &case;
            let mut emitted = [0.6, 1.0, 0.7];
            track_unplanned(history, valid, weight, None, None, None, &mut emitted);
            assert!(
                (emitted[0] - expected).abs() < 1e-6,
                "λ {weight}: {emitted:?}"
            );
            assert!((emitted[1] - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn least_jerk_tracking_anticipates_the_plan() {
        // Constant speed so far and in the emission; the plan brakes from the next step on.
        let history = (0..5)
            .map(|k| [0.1 * k as f32, 0.0, 0.0])
            .collect::<Vec<_>>();
        let braking = |t: f64| [(0.5 + 0.1 * t - 0.01 * t * t) as f32, 0.0];
        let case = plan_case(braking, 0, 4);
        let (_, _, denoised, window_valid) = case;
        let case = (vec![history], vec![vec![true; 5]], denoised, window_valid);
        let mut without_plan = [0.5, 0.0, 0.0];
        track_case(&case, 0, 100.0, &mut without_plan);
        assert!((without_plan[0] - 0.5).abs() < 1e-6);
        let mut with_plan = [0.5, 0.0, 0.0];
        track_case(&case, 4, 100.0, &mut with_plan);
        assert!(
            with_plan[0] < 0.5 - 1e-4,
            "starts braking early: {with_plan:?}"
        );
        assert!(with_plan[0] > 0.49, "and only gently: {with_plan:?}");
    }

    #[test]
    fn least_jerk_tracking_leaves_agents_without_three_valid_states() {
        let history = vec![line(0.1, 2), line(0.1, 5)];
        let valid = vec![vec![true; 2], vec![true, true, false, true, true]];
        let mut emitted = [0.9, 0.0, 0.0, 0.9, 0.0, 0.0];
        track_unplanned(&history, &valid, 10.0, None, None, None, &mut emitted);
        assert_eq!(emitted, [0.9, 0.0, 0.0, 0.9, 0.0, 0.0]);
    }

    #[test]
    fn the_jerk_weight_is_the_squared_cost_over_the_step_cubed() {
        let tracking = road_sched::JerkTracking {
            jerk_cost_m: 0.01,
            ahead: 3,
            max_acceleration_mps2: None,
            max_slip_deg: None,
            max_course_offset_deg: None,
            min_turn_radius_m: None,
        };
        assert!((tracking.jerk_weight(0.1) - 100.0).abs() < 1e-9);
    }

    #[test]
    fn a_committed_acceleration_over_the_bound_is_scaled_down_first() {
        // A kink in the committed path (a guard's correction): 0.3 per step² sideways.
        let history = vec![vec![[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.3, 0.0]]];
        let valid = vec![vec![true; 3]];
        let track = |bound: Option<f64>| {
            // The model emits the kink carried on; with no cost the path is the emission.
            let mut emitted = [0.3, 0.9, 0.0];
            track_unplanned(&history, &valid, 1e9, bound, None, None, &mut emitted);
            emitted
        };
        // Unbounded, a prohibitive jerk cost carries the kink on: x + v + a = (0.3, 0.9).
        let carried = track(None);
        assert!((carried[0] - 0.3).abs() < 1e-5 && (carried[1] - 0.9).abs() < 1e-5);
        // Bounded at 0.01 per step²: (0.3, 0.3 + 0.3 + 0.01).
        let bounded = track(Some(0.01));
        assert!((bounded[0] - 0.3).abs() < 1e-5, "{bounded:?}");
        assert!((bounded[1] - 0.61).abs() < 1e-5, "{bounded:?}");
        // A bound above the committed acceleration changes nothing.
        assert_eq!(track(Some(1.0)), carried);
    }

    #[test]
    fn a_braking_carried_on_past_standstill_does_not_reverse() {
        // Heading north-east (state units 0.25 per radian), 0.1 per step along it, stopped dead
        // last tick (a guard's brake): the committed acceleration, carried on, would step back.
        let heading = 0.25 * std::f32::consts::FRAC_PI_4;
        let at = |t: f32| [t * 0.1 * FRAC_1_SQRT_2, t * 0.1 * FRAC_1_SQRT_2, heading];
        let history = vec![vec![at(0.0), at(1.0), at(1.0)]];
        let valid = vec![vec![true; 3]];
        let track = |heading_scale: Option<f64>, model: [f32; 2]| {
            let mut emitted = [model[0], model[1], heading];
            track_unplanned(
                &history,
                &valid,
                1e9,
                None,
                heading_scale,
                None,
                &mut emitted,
            );
            emitted
        };
        let stopped = at(1.0);
        let reversed = track(None, [stopped[0], stopped[1]]);
        assert!(
            (reversed[0] - at(0.0)[0]).abs() < 1e-6,
            "unchecked, it reverses: {reversed:?}"
        );
        let held = track(Some(0.25), [stopped[0], stopped[1]]);
        assert!(
            (held[0] - stopped[0]).abs() < 1e-6 && (held[1] - stopped[1]).abs() < 1e-6,
            "stops where it is: {held:?}"
        );
        // A sideways component stays: only the backward one goes. Here the model's own step is
        // all the path takes (no jerk cost), back and to the left.
        let mut emitted = [stopped[0] - 0.05, stopped[1], heading];
        track_unplanned(&history, &valid, 0.0, None, Some(0.25), None, &mut emitted);
        let step = [emitted[0] - stopped[0], emitted[1] - stopped[1]];
        assert!(
            (step[0] + step[1]).abs() < 1e-6 && step[1] > 0.02,
            "the step left: {step:?}"
        );
    }

    #[test]
    fn a_carried_sideways_kink_slides_no_further_than_the_bound() {
        // Heading east; last tick a correction moved the car 0.005 to the left: carried on (a
        // prohibitive jerk cost) the step goes 0.01 forward and 0.01 left. The model steps
        // straight ahead.
        let history = vec![vec![[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.005, 0.0]]];
        let valid = vec![vec![true; 3]];
        let track = |max_slip_tan: Option<f64>| {
            let mut emitted = [0.03, 0.005, 0.0];
            track_unplanned(
                &history,
                &valid,
                1e9,
                None,
                Some(0.25),
                max_slip_tan,
                &mut emitted,
            );
            emitted
        };
        let carried = track(None);
        assert!((carried[0] - 0.03).abs() < 1e-6 && (carried[1] - 0.015).abs() < 1e-6);
        let tan = 5f64.to_radians().tan();
        let bounded = track(Some(tan));
        assert!((bounded[0] - 0.03).abs() < 1e-6, "{bounded:?}");
        assert!(
            (f64::from(bounded[1]) - (0.005 + tan * 0.01)).abs() < 1e-6,
            "{bounded:?}"
        );
    }
}
