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
//!    heading stays the model's). With `yield_to_unreactive`, an agent the guard does not move
//!    (an ego stack, a scripted or replayed agent: none of them reacts) that closes in on a
//!    model agent makes it brake too, when braking on at `brake_mps2` keeps it clear over the
//!    horizon (it stops short of a crossing ego's path instead of creeping into it); when
//!    braking cannot help (a car driving into its back) it keeps going.
//! 2. **No new overlap.** A model agent whose box would overlap another's after the tick moves
//!    only the largest fraction of its step that keeps it a centimetre clear (bisection), over
//!    as many passes as it takes to settle (an agent stopped short can push its follower back).
//! 3. **Cut steps tried again** (`regrow_cut_steps`): each step the passes cut is tried whole
//!    against everyone as settled and kept where rule 2 lets it through.
//!
//! Pairs that already overlapped before the tick are left alone (braking cannot separate them,
//! and the log has such pairs at standstill). The guarded state is what joins the history and
//! the window, so the model plans on from where the vehicle really is.

use glam::DVec2;
use road_data::tracks::STEP_SECS;
use road_sched::CollisionGuard;

use crate::Pose;
use crate::geometry::OrientedBox;

/// Bisection rounds of the no-overlap fraction: 2⁻¹² of a step.
const BISECTION_ROUNDS: usize = 12;
/// The gap (metres) the no-overlap rule leaves between an agent it stops short and the other
/// box: the guarded pose then survives the round trip through the engines' f32 model units
/// (some micrometres at the scene scale) without touching. The bisection alone could stop an
/// agent a micrometre from the other.
const STOP_SHORT_CLEARANCE_M: f64 = 0.01;

/// One agent as the guard sees it: its pose before the tick, the proposed pose after it, its
/// footprint, and whether the guard may change it (model-driven).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardAgent {
    pub before: Pose,
    pub proposed: Pose,
    pub length_m: f64,
    pub width_m: f64,
    pub movable: bool,
    /// Whether it brakes ahead of predicted collisions with other model-driven agents (the
    /// anticipation); false for an agent that breaks a deadlock
    /// (`CollisionGuard::release_deadlock_after_secs`) or that the stall release manoeuvres
    /// (backing and filling, turning in place): only the no-overlap rule holds it then.
    pub anticipates_model_agents: bool,
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
    /// Lane guard: its step turned a little towards its lane ahead of the road's edge.
    NudgedTowardsLane,
    /// Lane guard: stopped at the road's edge.
    StoppedAtRoadEdge,
    /// Stall release: pulled away after standing still with free road ahead.
    PulledAway,
    /// Deadlock release: backed off from a vehicle it was locked with, which has the way; or
    /// moved off (backwards, or forwards from one behind) to make room for a wedged vehicle.
    BackedOff,
    /// Give-way rule: held short of its stop line, its way not clear.
    GaveWay,
}

/// Applies the guard to `agents` in place (their `proposed` poses); returns what it did, per
/// agent index. The settings as in [`road_sched::CollisionGuard`].
pub fn guard_step(
    agents: &mut [GuardAgent],
    settings: &CollisionGuard,
) -> Vec<(usize, GuardAction)> {
    let CollisionGuard {
        horizon_steps,
        brake_mps2,
        yield_to_unreactive,
        ..
    } = *settings;
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
                if b.movable && !a.anticipates_model_agents {
                    return false;
                }
                let towards = position(b.proposed) - position(a.proposed);
                // Too far apart to meet within the horizon: no box test needed.
                let travel = horizon_steps as f64 * (step_a.length() + step_b.length());
                if towards.length() > reach(a) + reach(b) + travel {
                    return false;
                }
                // Who closes in: the velocity component towards the other, both measured
                // along the line between them.
                let closing_in = step_a.dot(towards) > (-step_b).dot(towards);
                let yields = yield_to_unreactive && !b.movable;
                if !closing_in && !yields {
                    return false;
                }
                let b_at = |k: f64| box_at(b, shifted(b.proposed, k * step_b));
                let meet = (1..=horizon_steps).any(|k| {
                    box_at(a, shifted(a.proposed, k as f64 * step_a)).overlaps(&b_at(k as f64))
                });
                if !meet || closing_in {
                    return meet;
                }
                // The other closes in and will not react: brake if braking keeps this agent
                // clear, from this tick's step on (it is the step braking cuts).
                let direction = step_a.normalize_or_zero();
                let mut travelled = 0.0;
                (0..=horizon_steps).all(|k| {
                    travelled += braked_step_length(step_a.length(), k + 1, brake_mps2);
                    let pose = shifted(a.before, travelled * direction);
                    !box_at(a, pose).overlaps(&b_at(k as f64))
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
            let braked = braked_step_length(length, 1, brake_mps2);
            agent.proposed = along(agent.before, agent.proposed, braked / length);
            actions.push((i, GuardAction::Braked));
        }
    }

    // 2. No new overlap after the tick. Agents only ever move back along their steps, towards
    // poses clear of one another before the tick, so passes until nothing changes settle: a
    // queue of followers behind an agent stopped short takes one pass per link.
    let movable: Vec<usize> = (0..n).filter(|&i| agents[i].movable).collect();
    // The steps as proposed, for rule 3 only (no copy each tick where it is off).
    let wanted: Option<Vec<Pose>> = settings
        .regrow_cut_steps
        .then(|| agents.iter().map(|a| a.proposed).collect());
    for _ in 0..=movable.len() {
        let mut changed = false;
        for &i in &movable {
            let clear = |agents: &[GuardAgent], pose: Pose, margin_m: f64| {
                clear_of_others(agents, i, pose, margin_m, &overlapped_before)
            };
            if passes_no_overlap(agents, i, &overlapped_before) {
                continue;
            }
            let (before, proposed) = (agents[i].before, agents[i].proposed);
            // The largest clear fraction of the step; 0 when even the start is not clear (the
            // other agent drove into this one: it cannot do better than to stay).
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..BISECTION_ROUNDS {
                let mid = 0.5 * (lo + hi);
                if clear(agents, along(before, proposed, mid), STOP_SHORT_CLEARANCE_M) {
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

    // 3. Steps cut for another's step that was itself cut after (`regrow_cut_steps`): the
    // passes above only ever shorten steps, in agent order, each against the others' steps as
    // they stand then, so an agent pulling away from one about to drive into it is cut for
    // that drive, the other is then cut for it, and both stand (a long session's exit on the
    // roundabout held so for 15 s). Each cut step is tried again whole against everyone as
    // settled, in agent order, and kept where the rule above lets it through; every pair is
    // then still checked with its later-moved member in its final pose.
    if let Some(wanted) = wanted {
        for &i in &movable {
            let settled = agents[i].proposed;
            if settled == wanted[i] {
                continue;
            }
            agents[i].proposed = wanted[i];
            if passes_no_overlap(agents, i, &overlapped_before) {
                actions.retain(|&action| action != (i, GuardAction::StoppedShort));
            } else {
                agents[i].proposed = settled;
            }
        }
    }
    actions
}

/// Whether agent `i`'s proposed pose is clear of every other agent's box by `margin_m` (its own
/// box grown by it), pairs that overlapped before the tick aside.
fn clear_of_others(
    agents: &[GuardAgent],
    i: usize,
    pose: Pose,
    margin_m: f64,
    overlapped_before: &[bool],
) -> bool {
    let n = agents.len();
    let a = &agents[i];
    let grown = OrientedBox {
        pose,
        length_m: a.length_m + 2.0 * margin_m,
        width_m: a.width_m + 2.0 * margin_m,
    };
    (0..n).all(|j| {
        let b = &agents[j];
        j == i
            || overlapped_before[i * n + j]
            || (position(pose) - position(b.proposed)).length() > reach(a) + reach(b) + margin_m
            || !grown.overlaps(&OrientedBox {
                pose: b.proposed,
                length_m: b.length_m,
                width_m: b.width_m,
            })
    })
}

/// The no-overlap rule for agent `i`'s proposed step against the others as proposed: clear of
/// everyone by [`STOP_SHORT_CLEARANCE_M`], or standing, or closer than that but overlapping
/// nobody and nearer to nobody that close (a standing vehicle may pull away from a
/// neighbour). Steps allowed merely because they overlap nobody let a standing vehicle's
/// millimetre jitter close the gap to nothing, and rounding then made it an overlap (issue
/// 39's long sessions counted those as collisions).
fn passes_no_overlap(agents: &[GuardAgent], i: usize, overlapped_before: &[bool]) -> bool {
    let pose = agents[i].proposed;
    clear_of_others(agents, i, pose, STOP_SHORT_CLEARANCE_M, overlapped_before)
        || pose == agents[i].before
        || clear_of_others(agents, i, pose, 0.0, overlapped_before)
            && !nearer_to_a_close_agent(agents, i)
}

/// Whether agent `i`'s proposed pose brings its box nearer, outline to outline, to another
/// agent's box that lies within [`STOP_SHORT_CLEARANCE_M`] of it (the other as proposed).
fn nearer_to_a_close_agent(agents: &[GuardAgent], i: usize) -> bool {
    let a = &agents[i];
    let box_of = |g: &GuardAgent, pose: Pose| OrientedBox {
        pose,
        length_m: g.length_m,
        width_m: g.width_m,
    };
    let (after, before) = (box_of(a, a.proposed), box_of(a, a.before));
    agents.iter().enumerate().any(|(j, b)| {
        j != i
            && (position(a.proposed) - position(b.proposed)).length()
                <= reach(a) + reach(b) + STOP_SHORT_CLEARANCE_M
            && nearer_within_clearance(&before, &after, &box_of(b, b.proposed))
    })
}

/// Whether a box moved from `before` to `after` ends within [`STOP_SHORT_CLEARANCE_M`] of
/// `other` and nearer to it, outline to outline, than it was. A move that takes the centre
/// away may still swing a corner closer: issue 39's long sessions saw micrometre steps of that
/// kind close a gap to nothing over minutes, and rounding then made it an overlap. A move
/// alongside, keeping the gap, is not nearer.
fn nearer_within_clearance(before: &OrientedBox, after: &OrientedBox, other: &OrientedBox) -> bool {
    let gap_after_m = after.gap_m(other);
    gap_after_m < STOP_SHORT_CLEARANCE_M && gap_after_m + GAP_TOLERANCE_M < before.gap_m(other)
}

/// Whether a box moved from `before` to `after` passes the guard's no-overlap rule against
/// `other` standing still: no overlap, and within [`STOP_SHORT_CLEARANCE_M`] no nearer than
/// before. For planning a move the guard will then let through (the stall release's
/// manoeuvres).
pub fn keeps_clear(before: &OrientedBox, after: &OrientedBox, other: &OrientedBox) -> bool {
    !after.overlaps(other) && !nearer_within_clearance(before, after, other)
}

/// Gaps this close are equal: a step alongside another box keeps its gap up to rounding.
const GAP_TOLERANCE_M: f64 = 1e-9;

/// The length of a step of `step_m` after braking at `brake_mps2` for `steps` steps (this
/// tick's is the first), never below standstill.
fn braked_step_length(step_m: f64, steps: usize, brake_mps2: f64) -> f64 {
    (step_m - steps as f64 * brake_mps2 * STEP_SECS * STEP_SECS).max(0.0)
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
    use std::f64::consts::FRAC_PI_2;

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
            anticipates_model_agents: true,
        }
    }

    fn settings(horizon_steps: usize, yield_to_unreactive: bool) -> CollisionGuard {
        CollisionGuard {
            horizon_steps,
            brake_mps2: 6.0,
            yield_to_unreactive,
            release_deadlock_after_secs: None,
            regrow_cut_steps: false,
        }
    }

    /// A model car at x = −7.7 m driving east at 3 m/s, and an external car (a turning ego
    /// that does not yield) 4.7 m ahead of it and 6.8 m to its left, driving south at 7 m/s:
    /// across the model car's lane, where the model car will be in a second.
    fn crossing() -> [GuardAgent; 2] {
        let model = agent(-8.0, -7.7, -1.8, true);
        let pose = |y: f64| Pose {
            x_m: -3.0,
            y_m: y,
            heading_rad: -FRAC_PI_2,
        };
        let ego = GuardAgent {
            before: pose(5.7),
            proposed: pose(5.0),
            length_m: 4.6,
            width_m: 1.9,
            movable: false,
            anticipates_model_agents: true,
        };
        [model, ego]
    }

    #[test]
    fn a_car_that_does_not_anticipate_model_cars_backs_up_to_the_clearance_unbraked() {
        // A backs at 1 m/s (0.1 m a tick) towards B, a model car standing 0.5 m behind it:
        // its 1 s horizon meets B, so a car that anticipates brakes; one manoeuvred by a
        // release (or breaking a deadlock) does not, and backs its full step, still clear.
        let backing = |anticipates| {
            let mut a = agent(0.0, -0.1, 0.0, true);
            a.anticipates_model_agents = anticipates;
            [a, agent(-4.5, -4.5, 0.0, true)]
        };
        let mut anticipating = backing(true);
        let actions = guard_step(&mut anticipating, &settings(10, true));
        assert_eq!(actions, vec![(0, GuardAction::Braked)]);
        assert!(anticipating[0].proposed.x_m > -0.1);
        let mut manoeuvring = backing(false);
        assert!(guard_step(&mut manoeuvring, &settings(10, true)).is_empty());
        assert_eq!(manoeuvring[0].proposed.x_m, -0.1);
        // Its next steps go on up to the clearance, and no farther.
        let mut at_the_gap = [agent(-0.45, -0.55, 0.0, true), agent(-4.5, -4.5, 0.0, true)];
        at_the_gap[0].anticipates_model_agents = false;
        let actions = guard_step(&mut at_the_gap, &settings(10, true));
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        let gap_m = at_the_gap[0].proposed.x_m - 2.0 - (-4.5 + 2.0);
        // (The cut is a bisection of the 0.1 m step: within a millimetre of the clearance.)
        assert!(
            (STOP_SHORT_CLEARANCE_M..=STOP_SHORT_CLEARANCE_M + 1e-3).contains(&gap_m),
            "gap {gap_m}"
        );
    }

    #[test]
    fn within_the_clearance_a_car_may_move_away_but_not_creep_closer() {
        // A stands 5 mm behind B (4 m boxes): a 4 mm creep forward overlaps nobody, but would
        // close the gap to nothing, where rounding makes it an overlap: it is cut. A step back
        // is left alone.
        let creeping = [agent(0.0, 0.004, 0.0, true), agent(4.005, 4.005, 0.0, true)];
        let mut agents = creeping;
        let actions = guard_step(&mut agents, &settings(0, false));
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        assert_eq!(agents[0].proposed.x_m, 0.0, "held where it stood");
        let mut agents = [agent(0.0, -0.05, 0.0, true), agent(4.005, 4.005, 0.0, true)];
        assert!(guard_step(&mut agents, &settings(0, false)).is_empty());
        assert_eq!(agents[0].proposed.x_m, -0.05);
        // So is a step that takes the centre away but swings a corner closer (1 mm back, turned
        // 3 mrad: the front corner 2 mm nearer), while one alongside, keeping the gap, goes on.
        let mut swinging = creeping;
        swinging[0].proposed = Pose {
            x_m: -0.001,
            y_m: 0.0,
            heading_rad: 0.003,
        };
        let actions = guard_step(&mut swinging, &settings(0, false));
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        let mut alongside = [agent(0.0, 0.0, 2.005, true), agent(0.0, 0.0, 0.0, true)];
        alongside[0].proposed.x_m = 0.3;
        assert!(guard_step(&mut alongside, &settings(0, false)).is_empty());
        assert_eq!(alongside[0].proposed.x_m, 0.3);
        // Turning on the spot beside it is cut too: a corner may swing into it.
        let mut turning = creeping;
        turning[0].proposed = Pose {
            x_m: 0.0,
            y_m: 0.0,
            heading_rad: 0.001,
        };
        let actions = guard_step(&mut turning, &settings(0, false));
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        assert_eq!(turning[0].proposed.heading_rad, 0.0);
    }

    #[test]
    fn a_model_car_yields_to_a_crossing_ego_only_when_asked_to() {
        let mut agents = crossing();
        // The ego closes in; the model car, not closing in, is left alone by default and
        // drives into the ego's path.
        assert!(guard_step(&mut agents, &settings(10, false)).is_empty());
        let mut agents = crossing();
        let actions = guard_step(&mut agents, &settings(10, true));
        assert_eq!(actions, vec![(0, GuardAction::Braked)]);
        assert!(
            (agents[0].proposed.x_m - (-7.7 - 0.06)).abs() < 1e-9,
            "{:?}",
            agents[0]
        );
        assert_eq!(
            agents[1].proposed,
            crossing()[1].proposed,
            "the ego is never moved"
        );
    }

    #[test]
    fn a_model_car_does_not_brake_for_a_car_driving_into_its_back() {
        // An external car 7 m behind (bumper to bumper: 3 m) at 8 m/s, the model car at 2 m/s:
        // braking cannot keep it clear, so it keeps its step.
        let mut agents = [agent(0.0, 0.2, 0.0, true), agent(-7.8, -7.0, 0.0, false)];
        assert!(guard_step(&mut agents, &settings(10, true)).is_empty());
        assert_eq!(agents[0].proposed.x_m, 0.2);
    }

    #[test]
    fn free_agents_pass_unchanged() {
        let mut agents = [agent(0.0, 1.0, 0.0, true), agent(0.0, 1.0, 10.0, true)];
        let before = agents;
        assert!(guard_step(&mut agents, &settings(10, false)).is_empty());
        assert_eq!(agents, before);
    }

    #[test]
    fn a_follower_brakes_behind_a_stopped_car_and_the_leader_does_not() {
        // Follower at 10 m/s, 6 m of gap (bumper to bumper) to a stopped car: it would meet it
        // within 1 s at constant velocity.
        let mut agents = [agent(0.0, 1.0, 0.0, true), agent(11.0, 11.0, 0.0, true)];
        let actions = guard_step(&mut agents, &settings(10, false));
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
        let actions = guard_step(&mut agents, &settings(0, false));
        assert_eq!(actions, vec![(0, GuardAction::StoppedShort)]);
        let x = agents[0].proposed.x_m;
        assert!(
            x <= 2.0 - STOP_SHORT_CLEARANCE_M && x > 1.98,
            "stops a centimetre short of the other's rear bumper: {x}"
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

    /// Agent 0 pulls away (0.1 m) from agent 1, whose nose stands 5 mm behind its tail and
    /// which drives 0.3 m on: checked first, 0 is cut for 1's drive into its tail, then 1 for
    /// 0's tail, and both stand. Tried again against 1 as settled, 0's step passes and 1 alone
    /// is held.
    #[test]
    fn a_step_cut_for_another_s_cut_step_is_regrown_when_asked() {
        let pair = || [agent(0.0, 0.1, 0.0, true), agent(-4.005, -3.705, 0.0, true)];
        let mut both_stand = pair();
        let actions = guard_step(&mut both_stand, &settings(0, false));
        assert_eq!(both_stand[0].proposed, both_stand[0].before);
        assert_eq!(both_stand[1].proposed, both_stand[1].before);
        assert_eq!(
            actions,
            vec![
                (0, GuardAction::StoppedShort),
                (1, GuardAction::StoppedShort)
            ]
        );

        let regrow = CollisionGuard {
            regrow_cut_steps: true,
            ..settings(0, false)
        };
        let mut regrown = pair();
        let actions = guard_step(&mut regrown, &regrow);
        assert_eq!(regrown[0].proposed, pair()[0].proposed, "0 pulls away");
        assert_eq!(regrown[1].proposed, regrown[1].before, "1 waits");
        assert_eq!(actions, vec![(1, GuardAction::StoppedShort)]);
        let boxes = regrown.map(|a| OrientedBox {
            pose: a.proposed,
            length_m: a.length_m,
            width_m: a.width_m,
        });
        assert!(!boxes[0].overlaps(&boxes[1]));
    }

    #[test]
    fn a_queue_behind_a_car_stopped_short_settles_without_overlap() {
        // Five model cars 1 m apart behind an external car standing at x = 20, each stepping
        // 3 m. The leader (listed last) stops short of the standing car, which pushes each
        // follower back in turn: one pass per link, more than a fixed three.
        let mut agents: Vec<GuardAgent> = (0..5)
            .map(|k| {
                let x = 14.5 - 5.0 * (4 - k) as f64;
                agent(x, x + 3.0, 0.0, true)
            })
            .chain([agent(20.0, 20.0, 0.0, false)])
            .collect();
        let actions = guard_step(&mut agents, &settings(0, false));
        assert_eq!(actions.len(), 5, "{actions:?}");
        let footprint = |a: &GuardAgent| OrientedBox {
            pose: a.proposed,
            length_m: a.length_m,
            width_m: a.width_m,
        };
        for i in 0..agents.len() {
            for j in i + 1..agents.len() {
                assert!(
                    !footprint(&agents[i]).overlaps(&footprint(&agents[j])),
                    "{i} and {j}: {agents:?}"
                );
            }
        }
    }

    #[test]
    fn pairs_that_overlapped_before_the_tick_are_left_alone() {
        let mut agents = [agent(0.0, 0.5, 0.0, true), agent(3.0, 3.0, 0.0, true)];
        let before = agents;
        assert!(guard_step(&mut agents, &settings(10, false)).is_empty());
        assert_eq!(agents, before);
    }

    #[test]
    fn an_agent_driven_into_keeps_its_place() {
        // The movable agent stands still; an external car drives into it: nothing it can do
        // by braking, and it does not jump away.
        let mut agents = [agent(0.0, 0.0, 0.0, true), agent(-5.0, -3.0, 0.0, false)];
        guard_step(&mut agents, &settings(10, false));
        assert_eq!(agents[0].proposed.x_m, 0.0);
    }
    #[test]
    fn a_car_pinned_at_the_clearance_on_both_sides_slides_out_along_them() {
        // Issue 39's intersection gridlock (long suite, intersection, seed 1, tick 705): a car
        // crossing the box with one car beside it and another's nose at its flank, both 1 cm
        // off (the clearance the guard leaves). Driving on slides it along both outlines; the
        // gaps stay 1 cm up to rounding, and it stood 20 s while each step was cut to nothing.
        let car = |x_m, y_m, heading_rad, length_m, width_m| GuardAgent {
            before: Pose {
                x_m,
                y_m,
                heading_rad,
            },
            proposed: Pose {
                x_m,
                y_m,
                heading_rad,
            },
            length_m,
            width_m,
            movable: true,
            anticipates_model_agents: true,
        };
        let pinned = car(
            2.2632816667943962,
            -0.5434322348499299,
            0.04600119590759277,
            4.453240312284435,
            1.855033189760026,
        );
        let nose_at_its_flank = car(
            0.06290706352291187,
            -4.009605645265579,
            1.8930561542510986,
            4.5,
            1.899999976158142,
        );
        let beside = car(
            2.0822565491586693,
            2.044001222524643,
            -2.776254892349243,
            4.800000190734863,
            1.899999976158142,
        );
        let mut agents = [nose_at_its_flank, beside, pinned];
        let step = DVec2::from_angle(pinned.before.heading_rad) * 0.02;
        agents[2].proposed = shifted(pinned.before, step);
        let actions = guard_step(&mut agents, &settings(0, false));
        assert!(actions.is_empty(), "{actions:?}");
        assert_eq!(agents[2].proposed, shifted(pinned.before, step));
    }
}
