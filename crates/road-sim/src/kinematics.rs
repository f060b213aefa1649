//! Kinematic realism in the style of the Waymo Sim Agents metrics: the distributions of speed,
//! longitudinal acceleration, jerk, yaw rate and yaw acceleration of the simulated agents
//! against the logged ones, each compared by the Jensen–Shannon divergence over fixed histogram
//! bins. Jitter (a stopped vehicle trembling in place) shows up as mass in the high |jerk|
//! bins; weaving (a path that snakes from side to side of its lane) in the high |yaw rate| and
//! |yaw acceleration| bins. Three counts see what the histograms cannot: steps going backwards,
//! steps sliding sideways of the heading, and sharp turns of the course.

use glam::DVec2;
use road_data::geometry::hypot_length;
use serde::Serialize;

/// The recordings' and the simulation's step: INTERACTION's (`road_data::tracks`), re-exported.
pub use road_data::tracks::STEP_SECS;

/// Yaw is read from the direction of motion between consecutive positions (the path's
/// course, not the heading channel), and only where the agent covers at least this much per
/// second: below it a few centimetres of position noise swing the course by whole radians.
pub const YAW_MIN_SPEED_MPS: f64 = 2.0;

/// A step counts as reversing where the agent moves backwards along its heading faster than
/// this (position noise of a stopped vehicle is millimetres per step: 0.02 m/s).
pub const REVERSING_MIN_SPEED_MPS: f64 = 0.2;

/// Of the steps between consecutive poses of one agent (`STEP_SECS` apart), how many go
/// backwards along the heading it has after the step faster than
/// [`REVERSING_MIN_SPEED_MPS`]: (reversing, steps). Speeds and yaw above are blind to it (a
/// car reversing at 1 m/s has the speed of one creeping forward).
pub fn reversing_steps(poses: &[crate::Pose]) -> (usize, usize) {
    let reversing = poses
        .windows(2)
        .filter(|p| {
            let step = DVec2::new(p[1].x_m - p[0].x_m, p[1].y_m - p[0].y_m);
            let forward = DVec2::from_angle(p[1].heading_rad);
            step.dot(forward) < -REVERSING_MIN_SPEED_MPS * STEP_SECS
        })
        .count();
    (reversing, poses.len().saturating_sub(1))
}

/// A step slides where it moves more than this off the agent's heading after it (degrees).
pub const SLIDING_MIN_ANGLE_DEG: f64 = 10.0;

/// Of one agent's steps at [`YAW_MIN_SPEED_MPS`] or faster, how many move more than
/// [`SLIDING_MIN_ANGLE_DEG`] off the heading it has after the step (a car sliding sideways):
/// (sliding, moving). Yaw rates read from the course cannot see it.
pub fn sliding_steps(poses: &[crate::Pose]) -> (usize, usize) {
    let (mut sliding, mut moving) = (0, 0);
    for p in poses.windows(2) {
        let step = DVec2::new(p[1].x_m - p[0].x_m, p[1].y_m - p[0].y_m);
        if step.length() < YAW_MIN_SPEED_MPS * STEP_SECS {
            continue;
        }
        moving += 1;
        let off = DVec2::from_angle(p[1].heading_rad).angle_to(step).abs();
        sliding += usize::from(off > SLIDING_MIN_ANGLE_DEG.to_radians());
    }
    (sliding, moving)
}

/// Two consecutive moving steps turn sharply where the course turns by more than this between
/// them (degrees in one 0.1 s step: a car at 10 m/s doing so pulls over 3 g sideways).
pub const SHARP_TURN_MIN_DEG: f64 = 20.0;

/// Of one agent's consecutive pairs of steps both at [`YAW_MIN_SPEED_MPS`] or faster, how many
/// turn the course by more than [`SHARP_TURN_MIN_DEG`] (a kink no car drives, such as a lane
/// guard's steer back onto the lane): (sharp, pairs). The yaw-rate histogram blurs a few of
/// them into its tail.
pub fn sharp_turns(poses: &[crate::Pose]) -> (usize, usize) {
    let min_step_m = YAW_MIN_SPEED_MPS * STEP_SECS;
    let (mut sharp, mut pairs) = (0, 0);
    for p in poses.windows(3) {
        let first = DVec2::new(p[1].x_m - p[0].x_m, p[1].y_m - p[0].y_m);
        let second = DVec2::new(p[2].x_m - p[1].x_m, p[2].y_m - p[1].y_m);
        if first.length() < min_step_m || second.length() < min_step_m {
            continue;
        }
        pairs += 1;
        sharp += usize::from(first.angle_to(second).abs() > SHARP_TURN_MIN_DEG.to_radians());
    }
    (sharp, pairs)
}

/// Reversing and sliding steps and sharp turns of some agents over a closed loop's ticks,
/// summed.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct StepCounts {
    /// Steps between consecutive ticks, and those going backwards ([`reversing_steps`]).
    pub steps: usize,
    pub reversing: usize,
    /// Steps at [`YAW_MIN_SPEED_MPS`] or faster, and those sliding ([`sliding_steps`]).
    pub moving: usize,
    pub sliding: usize,
    /// Consecutive pairs of moving steps, and those turning sharply ([`sharp_turns`]).
    pub moving_pairs: usize,
    pub sharp_turns: usize,
}

impl std::ops::AddAssign for StepCounts {
    fn add_assign(&mut self, other: Self) {
        self.steps += other.steps;
        self.reversing += other.reversing;
        self.moving += other.moving;
        self.sliding += other.sliding;
        self.moving_pairs += other.moving_pairs;
        self.sharp_turns += other.sharp_turns;
    }
}

impl StepCounts {
    /// The counts of `agents` over `ticks`.
    pub fn of(
        ticks: &[crate::closed_loop::SceneTick],
        agents: impl Iterator<Item = usize>,
    ) -> Self {
        let mut counts = Self::default();
        for a in agents {
            let poses: Vec<crate::Pose> = ticks.iter().map(|t| t.poses[a]).collect();
            let (reversing, steps) = reversing_steps(&poses);
            let (sliding, moving) = sliding_steps(&poses);
            let (sharp_turns, moving_pairs) = sharp_turns(&poses);
            counts += Self {
                steps,
                reversing,
                moving,
                sliding,
                moving_pairs,
                sharp_turns,
            };
        }
        counts
    }
}

/// A histogram over fixed bins on `[lo, hi)`; values outside fall into the edge bins.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Histogram {
    pub lo: f64,
    pub hi: f64,
    pub counts: Vec<f64>,
}

impl Histogram {
    pub fn new(lo: f64, hi: f64, bins: usize) -> Self {
        assert!(hi > lo && bins > 0, "histogram [{lo}, {hi}) of {bins} bins");
        Self {
            lo,
            hi,
            counts: vec![0.0; bins],
        }
    }

    pub fn add(&mut self, value: f64) {
        if !value.is_finite() {
            return;
        }
        let bins = self.counts.len();
        let at = ((value - self.lo) / (self.hi - self.lo) * bins as f64).floor();
        let bin = at.clamp(0.0, (bins - 1) as f64) as usize;
        self.counts[bin] += 1.0;
    }

    pub fn total(&self) -> f64 {
        self.counts.iter().sum()
    }

    /// Jensen–Shannon divergence in bits (0 = the same distribution, 1 = disjoint support);
    /// NaN when either histogram is empty.
    pub fn js_divergence(&self, other: &Histogram) -> f64 {
        assert_eq!(
            self.counts.len(),
            other.counts.len(),
            "histograms of other bins"
        );
        let (tp, tq) = (self.total(), other.total());
        if tp == 0.0 || tq == 0.0 {
            return f64::NAN;
        }
        let kl_to_mid = |p: f64, m: f64| if p > 0.0 { p * (p / m).log2() } else { 0.0 };
        self.counts
            .iter()
            .zip(&other.counts)
            .map(|(&a, &b)| {
                let (p, q) = (a / tp, b / tq);
                let m = 0.5 * (p + q);
                0.5 * kl_to_mid(p, m) + 0.5 * kl_to_mid(q, m)
            })
            .sum()
    }
}

/// Speed (m/s), longitudinal acceleration (m/s², the rate of change of speed), jerk (m/s³),
/// yaw rate (rad/s, the rate of change of the course) and yaw acceleration (rad/s²) of many
/// paths.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Kinematics {
    pub speed_mps: Histogram,
    pub acceleration_mps2: Histogram,
    pub jerk_mps3: Histogram,
    pub yaw_rate_radps: Histogram,
    pub yaw_acceleration_radps2: Histogram,
}

impl Default for Kinematics {
    fn default() -> Self {
        Self {
            speed_mps: Histogram::new(0.0, 30.0, 30),
            // Odd bin counts: zero sits mid-bin, so steady motion's float noise stays in one.
            acceleration_mps2: Histogram::new(-8.25, 8.25, 33),
            jerk_mps3: Histogram::new(-41.25, 41.25, 33),
            // 0.1 rad/s bins: a car on a 20 m ring at 7 m/s turns at 0.35 rad/s.
            yaw_rate_radps: Histogram::new(-1.65, 1.65, 33),
            yaw_acceleration_radps2: Histogram::new(-4.95, 4.95, 33),
        }
    }
}

/// The Jensen–Shannon divergence of each quantity (bits).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct KinematicDivergence {
    pub speed: f64,
    pub acceleration: f64,
    pub jerk: f64,
    pub yaw_rate: f64,
    pub yaw_acceleration: f64,
}

impl Kinematics {
    /// One path of positions at `STEP_SECS` apart (metres): speeds from the second position
    /// on, accelerations from the third, jerks from the fourth.
    pub fn add_path(&mut self, xy_m: &[[f64; 2]]) {
        let steps_m: Vec<DVec2> = xy_m
            .windows(2)
            .map(|p| DVec2::from(p[1]) - DVec2::from(p[0]))
            .collect();
        // `hypot`, as before glam: the histograms' bin edges must see the same speeds.
        let speeds: Vec<f64> = steps_m
            .iter()
            .map(|&step| hypot_length(step) / STEP_SECS)
            .collect();
        let accelerations: Vec<f64> = speeds
            .windows(2)
            .map(|v| (v[1] - v[0]) / STEP_SECS)
            .collect();
        for &v in &speeds {
            self.speed_mps.add(v);
        }
        for &a in &accelerations {
            self.acceleration_mps2.add(a);
        }
        for j in accelerations.windows(2) {
            self.jerk_mps3.add((j[1] - j[0]) / STEP_SECS);
        }
        // Course of each step, where the agent moves fast enough for it to mean something.
        let courses: Vec<Option<f64>> = steps_m
            .iter()
            .zip(&speeds)
            .map(|(step, &speed)| (speed >= YAW_MIN_SPEED_MPS).then(|| step.to_angle()))
            .collect();
        let yaw_rates: Vec<Option<f64>> = courses
            .windows(2)
            .map(|c| match (c[0], c[1]) {
                (Some(a), Some(b)) => Some(wrap_pi(b - a) / STEP_SECS),
                _ => None,
            })
            .collect();
        for &w in yaw_rates.iter().flatten() {
            self.yaw_rate_radps.add(w);
        }
        for w in yaw_rates.windows(2) {
            if let (Some(a), Some(b)) = (w[0], w[1]) {
                self.yaw_acceleration_radps2.add((b - a) / STEP_SECS);
            }
        }
    }

    pub fn divergence_from(&self, reference: &Kinematics) -> KinematicDivergence {
        KinematicDivergence {
            speed: self.speed_mps.js_divergence(&reference.speed_mps),
            acceleration: self
                .acceleration_mps2
                .js_divergence(&reference.acceleration_mps2),
            jerk: self.jerk_mps3.js_divergence(&reference.jerk_mps3),
            yaw_rate: self.yaw_rate_radps.js_divergence(&reference.yaw_rate_radps),
            yaw_acceleration: self
                .yaw_acceleration_radps2
                .js_divergence(&reference.yaw_acceleration_radps2),
        }
    }
}

/// An angle difference wrapped to [−π, π).
fn wrap_pi(a: f64) -> f64 {
    use std::f64::consts::PI;
    (a + PI).rem_euclid(2.0 * PI) - PI
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight(speed_mps: f64, steps: usize) -> Vec<[f64; 2]> {
        (0..steps)
            .map(|t| [speed_mps * STEP_SECS * t as f64, 0.0])
            .collect()
    }

    #[test]
    fn the_same_paths_diverge_by_nothing_and_disjoint_ones_by_one_bit() {
        let (mut a, mut b, mut c) = (
            Kinematics::default(),
            Kinematics::default(),
            Kinematics::default(),
        );
        a.add_path(&straight(5.5, 20));
        b.add_path(&straight(5.5, 20));
        c.add_path(&straight(20.5, 20));
        let same = a.divergence_from(&b);
        assert_eq!((same.speed, same.acceleration, same.jerk), (0.0, 0.0, 0.0));
        let other = a.divergence_from(&c);
        assert!((other.speed - 1.0).abs() < 1e-12, "{other:?}");
        // Both drive at constant speed: acceleration and jerk agree.
        assert_eq!((other.acceleration, other.jerk), (0.0, 0.0));
    }

    #[test]
    fn jitter_shows_in_jerk() {
        let (mut smooth, mut jittery) = (Kinematics::default(), Kinematics::default());
        smooth.add_path(&straight(0.0, 30));
        // A stopped car trembling by up to 20 cm, irregularly.
        let trembling: Vec<[f64; 2]> = (0..30)
            .map(|t| [0.05 * ((t * 7) % 5) as f64, 0.0])
            .collect();
        jittery.add_path(&trembling);
        let d = jittery.divergence_from(&smooth);
        assert!(d.jerk > 0.9, "{d:?}");
        assert!(
            d.speed > 0.0,
            "1 m/s of trembling is not standing still: {d:?}"
        );
    }

    #[test]
    fn weaving_shows_in_yaw_rate_and_not_in_speed() {
        let (mut straight_path, mut weaving) = (Kinematics::default(), Kinematics::default());
        straight_path.add_path(&straight(8.0, 40));
        // The same 8 m/s forward, snaking ±0.5 m sideways with a 1 s period.
        let snake: Vec<[f64; 2]> = (0..40)
            .map(|t| {
                let s = t as f64 * STEP_SECS;
                [8.0 * s, 0.5 * (2.0 * std::f64::consts::PI * s).sin()]
            })
            .collect();
        weaving.add_path(&snake);
        let d = weaving.divergence_from(&straight_path);
        assert!(d.yaw_rate > 0.5 && d.yaw_acceleration > 0.5, "{d:?}");
        assert!(d.speed < 0.5, "{d:?}");
        // A stopped car's trembling never reaches the yaw histograms.
        let mut trembling = Kinematics::default();
        trembling.add_path(
            &(0..30)
                .map(|t| [0.05 * ((t * 7) % 5) as f64, 0.0])
                .collect::<Vec<_>>(),
        );
        assert_eq!(trembling.yaw_rate_radps.total(), 0.0);
    }

    #[test]
    fn a_steady_turn_has_a_steady_yaw_rate_across_the_angle_wrap() {
        // 0.3 rad/s on a 20 m circle (6 m/s), through ±π.
        let path: Vec<[f64; 2]> = (0..80)
            .map(|t| {
                let a = 2.5 + 0.3 * t as f64 * STEP_SECS;
                [20.0 * a.cos(), 20.0 * a.sin()]
            })
            .collect();
        let mut k = Kinematics::default();
        k.add_path(&path);
        let bin = ((0.3 + 1.65) / 3.3 * 33.0) as usize;
        assert_eq!(
            k.yaw_rate_radps.counts[bin],
            k.yaw_rate_radps.total(),
            "{:?}",
            k.yaw_rate_radps
        );
        assert_eq!(
            k.yaw_acceleration_radps2.counts[16],
            k.yaw_acceleration_radps2.total()
        );
    }

    #[test]
    fn out_of_range_values_fall_into_the_edge_bins() {
        let mut h = Histogram::new(0.0, 10.0, 5);
        for v in [-3.0, 0.0, 9.99, 42.0, f64::NAN] {
            h.add(v);
        }
        assert_eq!(h.counts, vec![2.0, 0.0, 0.0, 0.0, 2.0]);
    }

    #[test]
    fn reversing_counts_steps_backwards_along_the_heading() {
        let pose = |x_m: f64, heading_rad: f64| crate::Pose {
            x_m,
            y_m: 0.0,
            heading_rad,
        };
        // Forward, stopped, a millimetre back (noise), 0.5 m/s back, then the same step
        // forward for a car turned round (heading π).
        let poses = [
            pose(0.0, 0.0),
            pose(0.5, 0.0),
            pose(0.5, 0.0),
            pose(0.499, 0.0),
            pose(0.449, 0.0),
            pose(0.399, std::f64::consts::PI),
        ];
        assert_eq!(reversing_steps(&poses), (1, 5));
        assert_eq!(reversing_steps(&poses[..1]), (0, 0));
    }

    #[test]
    fn sliding_counts_moving_steps_off_the_heading() {
        let pose = |x_m: f64, y_m: f64, heading_deg: f64| crate::Pose {
            x_m,
            y_m,
            heading_rad: heading_deg.to_radians(),
        };
        // East at 5 m/s: on its heading, 5° off, 20° off (sliding), then a crawl 45° off
        // (too slow to count), then 5 m/s at heading 359° across the wrap.
        let poses = [
            pose(0.0, 0.0, 0.0),
            pose(0.5, 0.0, 0.0),
            pose(1.0, 0.0, 5.0),
            pose(1.5, 0.0, 20.0),
            pose(1.55, 0.0, 45.0),
            pose(2.05, 0.0, 359.0),
        ];
        assert_eq!(sliding_steps(&poses), (1, 4));
    }

    #[test]
    fn sharp_turns_count_kinks_between_moving_steps() {
        let pose = |x_m: f64, y_m: f64| crate::Pose {
            x_m,
            y_m,
            heading_rad: 0.0,
        };
        // At 5 m/s: east, 10° left (smooth), 40° left (sharp), a crawl (not counted on either
        // side), then back to 5 m/s.
        let step = |from: crate::Pose, deg: f64, m: f64| {
            let d = DVec2::from_angle(deg.to_radians()) * m;
            pose(from.x_m + d.x, from.y_m + d.y)
        };
        let mut poses = vec![pose(0.0, 0.0)];
        for (deg, m) in [
            (0.0, 0.5),
            (10.0, 0.5),
            (50.0, 0.5),
            (50.0, 0.05),
            (90.0, 0.5),
        ] {
            let next = step(*poses.last().unwrap(), deg, m);
            poses.push(next);
        }
        assert_eq!(sharp_turns(&poses), (1, 2));
        assert_eq!(sharp_turns(&poses[..2]), (0, 0));
    }
}
