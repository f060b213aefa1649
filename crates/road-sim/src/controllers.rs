//! Agents that the model does not drive: constant velocity (a sanity baseline) and the paper's
//! adversarial agent.

use crate::Pose;

/// Constant velocity from the last two observed poses (10 Hz), for `steps` steps.
pub fn constant_velocity(previous: Pose, last: Pose, steps: usize) -> Vec<Pose> {
    let step_m = last.position_m() - previous.position_m();
    (1..=steps)
        .map(|k| Pose::at(last.position_m() + step_m * k as f64, last.heading_rad))
        .collect()
}

/// The adversarial agent of the reactivity test: it follows its logged path `logged` (poses
/// from the last observation on, `logged[0]` = now) but slowed so that after `steps` steps it
/// has covered only half of the path's arc length; positions are interpolated by arc length,
/// headings taken from the segment it is on.
pub fn slowed_replay(logged: &[Pose], steps: usize) -> Vec<Pose> {
    assert!(!logged.is_empty(), "a logged path needs at least its start");
    let mut arc = vec![0.0f64; logged.len()];
    for i in 1..logged.len() {
        arc[i] = arc[i - 1] + logged[i - 1].distance_m(logged[i]);
    }
    let total = *arc.last().unwrap_or(&0.0);
    if logged.len() == 1 || total == 0.0 {
        return vec![logged[0]; steps];
    }
    (1..=steps)
        .map(|k| {
            let target = 0.5 * total * k as f64 / steps as f64;
            // The segment [seg − 1, seg] holding the target arc length.
            let seg = arc
                .partition_point(|&s| s < target)
                .clamp(1, logged.len() - 1);
            let (a, b) = (logged[seg - 1], logged[seg]);
            let len = arc[seg] - arc[seg - 1];
            let t = if len > 0.0 {
                ((target - arc[seg - 1]) / len).clamp(0.0, 1.0)
            } else {
                0.0
            };
            // a + (b − a)·t, the form used before glam (`lerp` rounds differently).
            Pose::at(
                a.position_m().lerp_monotonic(b.position_m(), t),
                b.heading_rad,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f64, y: f64) -> Pose {
        Pose {
            x_m: x,
            y_m: y,
            heading_rad: 0.0,
        }
    }

    #[test]
    fn constant_velocity_extrapolates() {
        let out = constant_velocity(pose(0.0, 0.0), pose(1.0, 0.5), 3);
        assert_eq!(out[2], pose(4.0, 2.0));
    }

    #[test]
    fn slowed_replay_covers_half_the_path() {
        // An L-shaped path of 10 m + 10 m; half of it ends at the corner.
        let logged: Vec<Pose> = (0..=10)
            .map(|i| pose(f64::from(i), 0.0))
            .chain((1..=10).map(|i| pose(10.0, f64::from(i))))
            .collect();
        let out = slowed_replay(&logged, 40);
        let end = out[39];
        assert!(
            (end.x_m - 10.0).abs() < 1e-9 && end.y_m.abs() < 1e-9,
            "{end:?}"
        );
        // Uniform speed along the path: 0.25 m per step.
        assert!((out[0].x_m - 0.25).abs() < 1e-9);
        assert!((out[19].x_m - 5.0).abs() < 1e-9);
        // A standing agent stays.
        assert_eq!(slowed_replay(&[pose(3.0, 3.0)], 5), vec![pose(3.0, 3.0); 5]);
    }
}
