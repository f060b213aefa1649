//! The collision guard (a planner option, `collision_guard`): a safety layer between the model's
//! emitted states and the world, in the spirit of an automatic emergency brake. A deviation from
//! the paper, measured in `docs/results.md`; off unless a planner sets it.
//!
//! The model's vehicles do not avoid each other reliably (issue 13: any-collision 0.41 over
//! 4 s against 0.13 for log replay). Each tick, after the externally driven and scripted agents
//! have taken their states, the guard looks at every model-driven agent's step:
//! 1. **Anticipation.** Every agent's step of this tick is extrapolated at constant velocity for
//!    `horizon_steps`. If the extrapolated boxes of a model agent and another agent meet, and the
//!    model agent is the one closing in (its velocity towards the other exceeds the other's
//!    towards it), its speed this tick is cut by `brake_mps2 · Δt` along its own step (its
//!    heading stays the model's).
//! 2. **No new overlap.** A model agent whose box would overlap another's after the tick moves
//!    only the largest fraction of its step that keeps it clear (bisection).
//!
//! Pairs that already overlapped before the tick are left alone (braking cannot separate them,
//! and the log has such pairs at standstill). The guarded state is what joins the history and
//! the window, so the model plans on from where the vehicle really is.

use glam::DVec2;

use crate::Pose;
use crate::geometry::OrientedBox;

/// Seconds per simulated step (INTERACTION's 10 Hz).
const STEP_SECS: f64 = 0.1;
/// Bisection rounds of the no-overlap fraction: 2⁻¹² of a step.
const BISECTION_ROUNDS: usize = 12;
/// Passes of the no-overlap rule over the agents (an agent that backs off can clear another).
const OVERLAP_PASSES: usize = 3;

/// One agent as the guard sees it: its pose before the tick, the proposed pose after it, its
/// footprint, and whether the guard may change it (model-driven).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardAgent {
    pub before: Pose,
    pub proposed: Pose,
    pub length_m: f64,
    pub width_m: f64,
    pub movable: bool,
}

/// What a guard did to one agent this tick (the collision guard's actions, and the lane
/// guard's, [`crate::lane_guard`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum GuardAction {
    /// Braked ahead of a predicted collision.
    Braked,
    /// Stopped short of an overlap after the tick.
    StoppedShort,
    /// Lane guard: its step turned back towards its lane.
    SteeredToLane,
    /// Lane guard: stopped at the road's edge.
    StoppedAtRoadEdge,
}

/// Applies the guard to `agents` in place (their `proposed` poses); returns what it did, per
/// agent index. `horizon_steps` and `brake_mps2` as in [`road_sched::CollisionGuard`].
pub fn guard_step(
    agents: &mut [GuardAgent],
    horizon_steps: usize,
    brake_mps2: f64,
) -> Vec<(usize, GuardAction)> {
    let n = agents.len();
    let box_at = |a: &GuardAgent, pose: Pose| OrientedBox {
        pose,
        length_m: a.length_m,
        width_m: a.width_m,
    };
    // Pairs already overlapping before the tick are out of the guard's reach.
    let mut overlapped_before = vec![false; n * n];
    for i in 0..n {
        for j in i + 1..n {
            let hit = box_at(&agents[i], agents[i].before)
                .overlaps(&box_at(&agents[j], agents[j].before));
            overlapped_before[i * n + j] = hit;
            overlapped_before[j * n + i] = hit;
        }
    }
    let mut actions = Vec::new();

    // 1. Anticipation, against every agent's step as proposed (one decision per agent).
    if horizon_steps > 0 {
        let step = |a: &GuardAgent| position(a.proposed) - position(a.before);
        let mut brake = vec![false; n];
        for i in (0..n).filter(|&i| agents[i].movable) {
            let (a, step_a) = (&agents[i], step(&agents[i]));
            brake[i] = (0..n).any(|j| {
                if j == i || overlapped_before[i * n + j] {
                    return false;
                }
                let (b, step_b) = (&agents[j], step(&agents[j]));
                let towards = position(b.proposed) - position(a.proposed);
                // Too far apart to meet within the horizon: no box test needed.
                let travel = horizon_steps as f64 * (step_a.length() + step_b.length());
                if towards.length() > reach(a) + reach(b) + travel {
                    return false;
                }
                // Who closes in: the velocity component towards the other, both measured
                // along the line between them.
                if step_a.dot(towards) <= (-step_b).dot(towards) {
                    return false;
                }
                (1..=horizon_steps).any(|k| {
                    let k = k as f64;
                    box_at(a, shifted(a.proposed, k * step_a))
                        .overlaps(&box_at(b, shifted(b.proposed, k * step_b)))
                })
            });
        }
        for (i, agent) in agents.iter_mut().enumerate() {
            if !brake[i] {
                continue;
            }
            let s = step(agent);
            let length = s.length();
            if length <= 0.0 {
                continue;
            }
            let braked = (length - brake_mps2 * STEP_SECS * STEP_SECS).max(0.0);
            agent.proposed = along(agent.before, agent.proposed, braked / length);
            actions.push((i, GuardAction::Braked));
        }
    }

    // 2. No new overlap after the tick.
    let movable: Vec<usize> = (0..n).filter(|&i| agents[i].movable).collect();
    for _ in 0..OVERLAP_PASSES {
        let mut changed = false;
        for &i in &movable {
            let clear = |agents: &[GuardAgent], pose: Pose| {
                (0..n).all(|j| {
                    let (a, b) = (&agents[i], &agents[j]);
                    j == i
                        || overlapped_before[i * n + j]
                        || (position(pose) - position(b.proposed)).length() > reach(a) + reach(b)
                        || !box_at(a, pose).overlaps(&box_at(b, b.proposed))
                })
            };
            if clear(agents, agents[i].proposed) {
                continue;
            }
            let (before, proposed) = (agents[i].before, agents[i].proposed);
            // The largest clear fraction of the step; 0 when even the start is not clear (the
            // other agent drove into this one: it cannot do better than to stay).
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..BISECTION_ROUNDS {
                let mid = 0.5 * (lo + hi);
                if clear(agents, along(before, proposed, mid)) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            agents[i].proposed = along(before, proposed, lo);
            changed = true;
            if !actions.contains(&(i, GuardAction::StoppedShort)) {
                actions.push((i, GuardAction::StoppedShort));
            }
        }
        if !changed {
            break;
        }
    }
    actions
}

/// Half the diagonal of an agent's box: no point of it is farther from its centre.
fn reach(a: &GuardAgent) -> f64 {
    0.5 * a.length_m.hypot(a.width_m)
}

fn position(p: Pose) -> DVec2 {
    DVec2::new(p.x_m, p.y_m)
}

fn shifted(p: Pose, by: DVec2) -> Pose {
    Pose {
        x_m: p.x_m + by.x,
        y_m: p.y_m + by.y,
        heading_rad: p.heading_rad,
    }
}

/// The pose a fraction `t` of the way from `from` to `to` (headings unwrapped by the caller).
fn along(from: Pose, to: Pose, t: f64) -> Pose {
    Pose {
        x_m: from.x_m + t * (to.x_m - from.x_m),
        y_m: from.y_m + t * (to.y_m - from.y_m),
        heading_rad: from.heading_rad + t * (to.heading_rad - from.heading_rad),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn agent(x0: f64, x1: f64, y: f64, movable: bool) -> GuardAgent {
        let pose = |x| Pose {
            x_m: x,
            y_m: y,
            heading_rad: 0.0,
        };
        GuardAgent {
            before: pose(x0),
            proposed: pose(x1),
            length_m: 4.0,
            width_m: 2.0,
            movable,
        }
    }

    #[test]
    fn free_agents_pass_unchanged() {
        let mut agents = [agent(0.0, 1.0, 0.0, true), agent(0.0, 1.0, 10.0, true)];
        let before = agents;
        assert!(guard_step(&mut agents, 10, 6.0).is_empty());
        assert_eq!(agents, before);
    }

    #[test]
    fn a_follower_brakes_behind_a_stopped_car_and_the_leader_does_not() {
        // Follower at 10 m/s, 6 m of gap (bumper to bumper) to a stopped car: it would meet it
        // within 1 s at constant velocity.
        let mut agents = [agent(0.0, 1.0, 0.0, true), agent(11.0, 11.0, 0.0, true)];
        let actions = guard_step(&mut agents, 10, 6.0);
        assert_eq!(actions, vec![(0, GuardAction::Braked)]);
        // 1 m this tick less 6 m/s² · 0.1 s · 0.1 s.
        assert!(
            (agents[0].proposed.x_m - 0.94).abs() < 1e-9,
            "{:?}",
            agents[0]
        );
        assert_eq!(agents[1].proposed.x_m, 11.0);
    }

    #[test]
    fn a_step_into_another_car_stops_short_of_it() {
        // A 3 m step that would end inside a car (external) 6 m ahead.
        let mut agents = [agent(0.0, 3.0, 0.0, true), agent(6.0, 6.0, 0.0, false)];
        let actions = guard_step(&mut agents, 0, 6.0);
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        let x = agents[0].proposed.x_m;
        assert!(
            x <= 2.0 && x > 1.99,
            "stops at the other's rear bumper: {x}"
        );
        assert!(
            !OrientedBox {
                pose: agents[0].proposed,
                length_m: 4.0,
                width_m: 2.0
            }
            .overlaps(&OrientedBox {
                pose: agents[1].proposed,
                length_m: 4.0,
                width_m: 2.0
            })
        );
        assert_eq!(
            agents[1].proposed.x_m, 6.0,
            "an external agent is never moved"
        );
    }

    #[test]
    fn pairs_that_overlapped_before_the_tick_are_left_alone() {
        let mut agents = [agent(0.0, 0.5, 0.0, true), agent(3.0, 3.0, 0.0, true)];
        let before = agents;
        assert!(guard_step(&mut agents, 10, 6.0).is_empty());
        assert_eq!(agents, before);
    }

    #[test]
    fn an_agent_driven_into_keeps_its_place() {
        // The movable agent stands still; an external car drives into it: nothing it can do
        // by braking, and it does not jump away.
        let mut agents = [agent(0.0, 0.0, 0.0, true), agent(-5.0, -3.0, 0.0, false)];
        guard_step(&mut agents, 10, 6.0);
        assert_eq!(agents[0].proposed.x_m, 0.0);
    }
}
