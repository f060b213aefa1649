//! The lane guard (a planner option, `lane_guard`): a lane-keeping layer between the model's
//! emitted states and the world, in the spirit of a lane-keeping assist. A deviation from the
//! paper, measured in `docs/results.md`; off unless a planner sets it.
//!
//! The model's vehicles leave the road where the map is unlike its training maps (issue 13: on
//! `road demo`'s procedural roundabout about a third of them). Each tick, for every model-driven
//! agent whose centre was on a lanelet before the tick and whose proposed centre is off the road,
//! or on a lane merging into its own entered against that lane's direction (a roundabout exit
//! taken through the entry beside it, which leads off the road a few steps later):
//! 1. **Steer.** Its lane is the lanelet under it whose centre line runs most nearly along its
//!    step (or its heading when it barely moves); the target is the point `lookahead_m` ahead
//!    along that centre line, continued into the successor the model's proposal is nearest to.
//!    The agent keeps the model's step length (its speed) and takes its step towards the target
//!    (pure pursuit), its heading along the new step.
//! 2. **Stop at the edge.** If the steered step still ends off road (or against a merging lane),
//!    the agent moves only the largest fraction of it that does not (bisection).
//!
//! With `anticipation` it also acts before that: a step that stays on the road but whose
//! constant-velocity continuation would leave it within a few steps turns a little towards the
//! same target ([`nudge_towards_lane`]), so that a vehicle drifting towards the edge bends back
//! over several ticks instead of being steered 20–70° in one.
//!
//! The guard keeps lane followers in their lane: it does not steer an agent that moves
//! backwards, and leaves alone one that drives off the end of a lanelet without successor (out
//! of the mapped area, as vehicles in the log do; stopping it there would park it in the way of
//! the traffic behind). An agent moving backwards, across or against every lanelet under it,
//! or creeping, has no lane to be steered into: it stops at the road's edge rather than leave
//! the road (issues 39 and 41: one crept onto a median, another crossed a roundabout's median
//! and drove on over the fields, a third slid sideways off the merge). The guarded state is
//! what joins the history and the window, so the model plans on from where the vehicle really
//! is: back in its lane. With `turn_plan` the closed loop turns the steered vehicle's plan too
//! (the window's future slots rotated about its position before the tick by the angle its step
//! turned, headings with them: `road_rollout::turn_plan`); without it the model, its plan still
//! pointing where it had meant to go, turns its heading back there while its positions follow
//! the lane, and the vehicle slides sideways
//! (`docs/experiments/2026-11-26-lane-guard-turns-plan.md`).

use glam::DVec2;
use road_data::geometry::Point;
use road_data::map::{Lanelet, LaneletMap};

use crate::Pose;
use road_sched::LaneAnticipation;

/// Bisection rounds of the on-road fraction: 2⁻¹² of a step.
const BISECTION_ROUNDS: usize = 12;
/// Lanelets the look-ahead may walk through (the agent's own and its successors).
const MAX_LANELETS_AHEAD: usize = 4;
/// Steps shorter than this (metres) are a standing vehicle's jitter: not steered, only kept
/// on the road.
const STANDSTILL_STEP_M: f64 = 0.05;
/// A proposal projecting within this of a lanelet's end (metres) drives off that end.
const END_TOLERANCE_M: f64 = 0.5;
/// Steps at least this long (metres per 0.1 s step: 2 m/s, as the kinematic metrics' yaw) are
/// checked against merging lanes.
const DIRECTED_STEP_M: f64 = 0.2;

/// What the lane guard did to one agent this tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LaneAction {
    /// Its step turned towards its lane (and it stayed on road).
    Steered,
    /// It stopped at the road's edge (the steered step, or the model's, would have left it).
    StoppedAtEdge,
}

/// Keeps one agent's proposed pose on the road, in place; returns what the guard did, `None`
/// when the proposal stays on a lanelet or the agent was off every lanelet before the tick.
/// Headings in radians, unwrapped as the caller keeps them (the result stays near `before`'s).
pub fn keep_on_road(
    map: &LaneletMap,
    before: Pose,
    proposed: &mut Pose,
    lookahead_m: f64,
    keep_off_opposing_lanes: bool,
) -> Option<LaneAction> {
    let from = DVec2::new(before.x_m, before.y_m);
    let to = DVec2::new(proposed.x_m, proposed.y_m);
    if !on_road(map, from) {
        return None;
    }
    let step = to - from;
    let step_m = step.length();
    if step_m < STANDSTILL_STEP_M {
        // A standing vehicle's jitter says nothing of its way, but it may not carry it off the
        // road a few centimetres a tick either (issue 39: a vehicle held up beside the ego
        // crept onto the median): it stays where it is.
        if on_road(map, to) || leaves_through_an_open_end(map, from, to) {
            return None;
        }
        proposed.x_m = before.x_m;
        proposed.y_m = before.y_m;
        return Some(LaneAction::StoppedAtEdge);
    }
    let direction = step / step_m;
    // Out of the map through an open lane end, whichever way it faces: it leaves (and is
    // retired). Held at the edge, a vehicle facing into the map that was asked to back off
    // out of its end stood there for 334 s, those it was to make room for behind it (issue 39).
    if !on_road(map, to) && leaves_through_an_open_end(map, from, to) {
        return None;
    }
    // A step backwards or square to the heading is not lane following: no lane to steer it
    // into, and no right to leave the road either (issue 41: a vehicle standing beside a
    // stopped ego slid sideways off the merge, its steps a hair behind square).
    let reversing = step.dot(DVec2::from_angle(before.heading_rad)) <= 0.0;
    let lane = if reversing {
        None
    } else {
        lane_under(map, from, direction)
    };
    let Some((lanelet, along_m)) = lane else {
        // Also on the road but on no lane that runs its way (across or against its lane):
        // issue 41 saw one cross a roundabout's median and drive on over the fields. It stops
        // at the edge.
        return stop_on_the_road(map, from, proposed, direction);
    };
    // A slow vehicle's step is mostly position noise: its direction says nothing of its way.
    let directed = step_m >= DIRECTED_STEP_M;
    // On its own lanelet it is on its way (and no other lanelet need be looked at).
    let stays_on_its_way = |p: DVec2, direction: DVec2| {
        map.lanelets[lanelet].contains([p.x, p.y])
            || on_road(map, p)
                && !(directed
                    && (against_a_merging_lane(map, lanelet, p, direction)
                        || (keep_off_opposing_lanes && onto_an_opposing_lane(map, p, direction))))
    };
    if stays_on_its_way(to, direction) {
        return None;
    }
    if drives_off_the_map(map, lanelet, to) {
        return None;
    }
    let target = lane_target(map, lanelet, along_m, to, lookahead_m);
    let towards = target - from;
    if towards.length() > 1e-9 {
        let steered_direction = towards.normalize();
        let steered = from + steered_direction * step_m;
        *proposed = Pose {
            x_m: steered.x,
            y_m: steered.y,
            heading_rad: unwrap_near(steered_direction.to_angle(), before.heading_rad),
        };
        if stays_on_its_way(steered, steered_direction) {
            return Some(LaneAction::Steered);
        }
    }
    // The steered step still leaves the road (a sharp bend, a narrow lanelet): stop at the edge.
    let end = DVec2::new(proposed.x_m, proposed.y_m);
    let stopped = stop_at_edge(from, end, direction, stays_on_its_way);
    proposed.x_m = stopped.x;
    proposed.y_m = stopped.y;
    Some(LaneAction::StoppedAtEdge)
}

/// For an agent with no lane to steer into: `None` when its proposed step stays on the road or
/// leaves the map through an open lane end, else the step cut short at the road's edge.
fn stop_on_the_road(
    map: &LaneletMap,
    from: DVec2,
    proposed: &mut Pose,
    direction: DVec2,
) -> Option<LaneAction> {
    let to = DVec2::new(proposed.x_m, proposed.y_m);
    if on_road(map, to) || leaves_through_an_open_end(map, from, to) {
        return None;
    }
    let stopped = stop_at_edge(from, to, direction, |p, _| on_road(map, p));
    proposed.x_m = stopped.x;
    proposed.y_m = stopped.y;
    Some(LaneAction::StoppedAtEdge)
}

/// The farthest point of the step from `from` to `end` that `stays` accepts (bisection; `from`
/// itself when none does), the step's direction passed along (`direction` for a null step).
fn stop_at_edge(
    from: DVec2,
    end: DVec2,
    direction: DVec2,
    stays: impl Fn(DVec2, DVec2) -> bool,
) -> DVec2 {
    let end_direction = (end - from).normalize_or(direction);
    let (mut inside, mut outside) = (0.0f64, 1.0f64);
    for _ in 0..BISECTION_ROUNDS {
        let mid = 0.5 * (inside + outside);
        if stays(from + (end - from) * mid, end_direction) {
            inside = mid;
        } else {
            outside = mid;
        }
    }
    from + (end - from) * inside
}

/// The lane guard's nudge ahead of the road's edge (`anticipation`), for an agent
/// [`keep_on_road`] left alone: when its step stays on the road but the step's
/// constant-velocity continuation leaves it (or runs against a merging lane) within
/// `anticipation.steps`, the step turns towards the lane's pure-pursuit target by at most
/// `anticipation.max_turn_rad_per_m` per metre of step, the heading along the new step as
/// after a steer (turned by as much as the step instead, it lagged behind the positions:
/// `docs/experiments/2026-11-26-lane-guard-nudges.md`). Returns whether it nudged. Vehicles driving
/// off the end of a lanelet without successor are left alone, as by [`keep_on_road`].
pub fn nudge_towards_lane(
    map: &LaneletMap,
    before: Pose,
    proposed: &mut Pose,
    lookahead_m: f64,
    anticipation: LaneAnticipation,
    keep_off_opposing_lanes: bool,
) -> bool {
    let from = DVec2::new(before.x_m, before.y_m);
    let to = DVec2::new(proposed.x_m, proposed.y_m);
    let step = to - from;
    let step_m = step.length();
    // Slow steps are mostly position noise, and reversing ones are not lane following.
    if step_m < DIRECTED_STEP_M
        || step.dot(DVec2::from_angle(before.heading_rad)) <= 0.0
        || !on_road(map, from)
    {
        return false;
    }
    let direction = step / step_m;
    let Some((lanelet, along_m)) = lane_under(map, from, direction) else {
        return false;
    };
    let stays_on_its_way = |p: DVec2| {
        map.lanelets[lanelet].contains([p.x, p.y])
            || on_road(map, p)
                && !against_a_merging_lane(map, lanelet, p, direction)
                && !(keep_off_opposing_lanes && onto_an_opposing_lane(map, p, direction))
    };
    if !stays_on_its_way(to) {
        return false;
    }
    let Some(leaving) = (1..=anticipation.steps)
        .map(|k| to + step * k as f64)
        .find(|&p| !stays_on_its_way(p))
    else {
        return false;
    };
    if drives_off_the_map(map, lanelet, leaving) {
        return false;
    }
    let target = lane_target(map, lanelet, along_m, to, lookahead_m);
    let max_turn_rad = anticipation.max_turn_rad_per_m * step_m;
    let turn_rad = step
        .angle_to(target - from)
        .clamp(-max_turn_rad, max_turn_rad);
    if turn_rad.abs() < 1e-6 {
        return false;
    }
    let nudged = from + DVec2::from_angle(turn_rad).rotate(step);
    if !stays_on_its_way(nudged) {
        return false;
    }
    *proposed = Pose {
        x_m: nudged.x,
        y_m: nudged.y,
        heading_rad: unwrap_near((nudged - from).to_angle(), before.heading_rad),
    };
    true
}

/// Whether `p`, off the road ahead of an agent on `lanelet`, lies past the end of that
/// lanelet and it has no successor: the agent drives out of the mapped area, as vehicles in
/// the log do, and the guard leaves it alone.
fn drives_off_the_map(map: &LaneletMap, lanelet: usize, p: DVec2) -> bool {
    let centre = &map.lanelets[lanelet].centre_m;
    map.lanelets[lanelet].successors.is_empty()
        && project_on_polyline(centre, p).0 >= polyline_length_m(centre) - END_TOLERANCE_M
}

/// Whether `to`, off the road, lies past an open end of a lanelet under `from`: the end of one
/// without successors or the start of one without predecessors (the map's edge, whichever
/// way the lanelet runs). A vehicle there leaves the mapped area, whatever its lane: held at
/// the edge it would stand there for good (issue 39: a vehicle that drifted onto the opposite
/// lane near the map's end stood at its edge for the rest of a long session).
pub fn leaves_through_an_open_end(map: &LaneletMap, from: DVec2, to: DVec2) -> bool {
    map.lanelets.iter().enumerate().any(|(i, l)| {
        if l.centre_m.len() < 2 || !l.contains([from.x, from.y]) {
            return false;
        }
        let along_m = project_on_polyline(&l.centre_m, to).0;
        let open_end =
            l.successors.is_empty() && along_m >= polyline_length_m(&l.centre_m) - END_TOLERANCE_M;
        let open_start = along_m <= END_TOLERANCE_M
            && !map
                .lanelets
                .iter()
                .any(|other| other.successors.contains(&(i as u32)));
        open_end || open_start
    })
}

fn on_road(map: &LaneletMap, p: DVec2) -> bool {
    map.lanelet_at([p.x, p.y]).is_some()
}

/// Whether `p` lies, against its direction, on a lane that merges into the agent's `lane` (a
/// lanelet whose successors are `lane` or one of its successors), and on no lanelet running
/// along `direction` (within 90°): a roundabout's exit taken through the entry beside it, which
/// leads off the road a few steps later. Other lanelets crossing the agent's way do not count:
/// vehicles in the recordings cross them where the map has no lanelet for their own path.
fn against_a_merging_lane(map: &LaneletMap, lane: usize, p: DVec2, direction: DVec2) -> bool {
    // A merge: `l` ends where its successor starts, running its way (maps also link lanes of
    // opposite ways end to end, as U-turns).
    let merges_into = |l: &Lanelet, s: u32| {
        map.lanelets.get(s as usize).is_some_and(|next| {
            next.centre_m.len() >= 2
                && end_tangent(&l.centre_m).dot(start_tangent(&next.centre_m)) > 0.0
        })
    };
    let leads_on = |l: &Lanelet| {
        l.successors.iter().any(|&s| {
            (s as usize == lane || map.lanelets[lane].successors.contains(&s)) && merges_into(l, s)
        })
    };
    let on_against = map.lanelets.iter().any(|l| {
        l.centre_m.len() >= 2
            && leads_on(l)
            && l.contains([p.x, p.y])
            && project_on_polyline(&l.centre_m, p).1.dot(direction) < 0.0
    });
    on_against && lane_under(map, p, direction).is_none()
}

/// Whether `p` lies on a lanelet running against `direction` (more than
/// [`OPPOSING_MIN_ANGLE_DEG`] off it) and on none running its way (within 90°): a step onto
/// the opposite carriageway, as when a vehicle leaves a roundabout through the entry beside
/// its exit on a map whose merging-lane rule ([`against_a_merging_lane`]) does not see it
/// (issue 39). Crossing lanes, at right angles, do not count. The long sessions' wrong-way
/// count asks it of every moving vehicle's course (`road_sim::session`).
pub fn onto_an_opposing_lane(map: &LaneletMap, p: DVec2, direction: DVec2) -> bool {
    let opposing_cos = OPPOSING_MIN_ANGLE_DEG.to_radians().cos();
    let on_opposing = map.lanelets.iter().any(|l| {
        l.centre_m.len() >= 2
            && l.contains([p.x, p.y])
            && project_on_polyline(&l.centre_m, p).1.dot(direction) < opposing_cos
    });
    on_opposing && lane_under(map, p, direction).is_none()
}

/// Whether a vehicle at `p` facing `direction` (a unit vector) points more than
/// `min_angle_rad` off the way of every lanelet under it; true on none (off the road).
pub fn across_every_lane(map: &LaneletMap, p: DVec2, direction: DVec2, min_angle_rad: f64) -> bool {
    let along_cos = min_angle_rad.cos();
    !map.lanelets.iter().any(|l| {
        l.centre_m.len() >= 2
            && l.contains([p.x, p.y])
            && project_on_polyline(&l.centre_m, p).1.dot(direction) >= along_cos
    })
}

/// The least angle between a step and a lanelet's way for [`onto_an_opposing_lane`], degrees.
const OPPOSING_MIN_ANGLE_DEG: f64 = 135.0;

/// The agent's lane: of the lanelets under `from`, the one whose centre line runs most nearly
/// along `direction` (none when every one runs against it), with `from`'s arc length along it.
fn lane_under(map: &LaneletMap, from: DVec2, direction: DVec2) -> Option<(usize, f64)> {
    map.lanelets
        .iter()
        .enumerate()
        .filter(|(_, l)| l.centre_m.len() >= 2 && l.contains([from.x, from.y]))
        .filter_map(|(i, l)| {
            let (along_m, tangent) = project_on_polyline(&l.centre_m, from);
            let alignment = tangent.dot(direction);
            (alignment > 0.0).then_some((i, along_m, alignment))
        })
        .max_by(|a, b| a.2.total_cmp(&b.2))
        .map(|(i, along_m, _)| (i, along_m))
}

/// The pure-pursuit target: `lookahead_m` ahead of `along_m` on `lanelet`'s centre line,
/// continued into the successor nearest `proposed` (clamped at the end of a lanelet without
/// successor).
fn lane_target(
    map: &LaneletMap,
    mut lanelet: usize,
    mut along_m: f64,
    proposed: DVec2,
    lookahead_m: f64,
) -> DVec2 {
    let mut remaining_m = lookahead_m;
    for _ in 0..MAX_LANELETS_AHEAD {
        let centre = &map.lanelets[lanelet].centre_m;
        let length_m = polyline_length_m(centre);
        if along_m + remaining_m <= length_m {
            return point_along(centre, along_m + remaining_m);
        }
        remaining_m -= (length_m - along_m).max(0.0);
        let next = map.lanelets[lanelet]
            .successors
            .iter()
            .map(|&s| s as usize)
            .filter(|&s| map.lanelets.get(s).is_some_and(|l| l.centre_m.len() >= 2))
            .min_by(|&a, &b| {
                distance_to_polyline(&map.lanelets[a], proposed)
                    .total_cmp(&distance_to_polyline(&map.lanelets[b], proposed))
            });
        match next {
            Some(s) => {
                lanelet = s;
                along_m = 0.0;
            }
            None => return point_along(centre, length_m),
        }
    }
    let centre = &map.lanelets[lanelet].centre_m;
    point_along(centre, along_m.min(polyline_length_m(centre)))
}

/// Arc length of `p`'s nearest point on `line` (≥ 2 points), and the unit tangent there.
fn project_on_polyline(line: &[Point], p: DVec2) -> (f64, DVec2) {
    let mut best = (f64::INFINITY, 0.0, DVec2::X);
    let mut start_m = 0.0;
    for pair in line.windows(2) {
        let (a, b) = (DVec2::from(pair[0]), DVec2::from(pair[1]));
        let segment = b - a;
        let length_m = segment.length();
        if length_m < 1e-9 {
            continue;
        }
        let t = ((p - a).dot(segment) / (length_m * length_m)).clamp(0.0, 1.0);
        let distance_m = (a + segment * t - p).length();
        if distance_m < best.0 {
            best = (distance_m, start_m + t * length_m, segment / length_m);
        }
        start_m += length_m;
    }
    (best.1, best.2)
}

fn distance_to_polyline(lanelet: &Lanelet, p: DVec2) -> f64 {
    lanelet
        .centre_m
        .windows(2)
        .map(|pair| {
            let (a, b) = (DVec2::from(pair[0]), DVec2::from(pair[1]));
            let segment = b - a;
            let t = if segment.length_squared() < 1e-18 {
                0.0
            } else {
                ((p - a).dot(segment) / segment.length_squared()).clamp(0.0, 1.0)
            };
            (a + segment * t - p).length()
        })
        .fold(f64::INFINITY, f64::min)
}

/// The unit direction of a polyline's (≥ 2 points) first segment.
fn start_tangent(line: &[Point]) -> DVec2 {
    (DVec2::from(line[1]) - DVec2::from(line[0])).normalize_or_zero()
}

/// The unit direction of a polyline's (≥ 2 points) last segment.
fn end_tangent(line: &[Point]) -> DVec2 {
    let n = line.len();
    (DVec2::from(line[n - 1]) - DVec2::from(line[n - 2])).normalize_or_zero()
}

fn polyline_length_m(line: &[Point]) -> f64 {
    line.windows(2)
        .map(|pair| (DVec2::from(pair[1]) - DVec2::from(pair[0])).length())
        .sum()
}

/// The point `along_m` metres along `line` (clamped to its ends).
fn point_along(line: &[Point], along_m: f64) -> DVec2 {
    let mut left_m = along_m.max(0.0);
    for pair in line.windows(2) {
        let (a, b) = (DVec2::from(pair[0]), DVec2::from(pair[1]));
        let length_m = (b - a).length();
        if left_m <= length_m && length_m > 1e-9 {
            return a + (b - a) * (left_m / length_m);
        }
        left_m -= length_m;
    }
    DVec2::from(*line.last().expect("a centre line has points"))
}

/// `angle` plus the multiple of 2π that puts it nearest `reference`.
fn unwrap_near(angle: f64, reference: f64) -> f64 {
    let turns = ((reference - angle) / std::f64::consts::TAU).round();
    angle + turns * std::f64::consts::TAU
}

#[cfg(test)]
mod tests {
    use super::*;
    use road_data::geometry::Aabb;
    use std::f64::consts::{FRAC_PI_2, PI};

    /// A straight lanelet along +x from `x0` to `x1`, 4 m wide (y in [−2, 2]).
    fn straight(id: i64, x0: f64, x1: f64) -> Lanelet {
        let xs: Vec<f64> = (0..=((x1 - x0) as usize)).map(|i| x0 + i as f64).collect();
        Lanelet {
            id,
            subtype: None,
            left_way: 2 * id,
            right_way: 2 * id + 1,
            left_m: xs.iter().map(|&x| [x, 2.0]).collect(),
            right_m: xs.iter().map(|&x| [x, -2.0]).collect(),
            centre_m: xs.iter().map(|&x| [x, 0.0]).collect(),
            successors: Vec::new(),
            neighbours: Vec::new(),
            bounds: Aabb {
                min: [x0, -2.0],
                max: [x1, 2.0],
            },
        }
    }

    fn road() -> LaneletMap {
        let mut first = straight(1, 0.0, 20.0);
        first.successors = vec![1];
        LaneletMap {
            location: "test".into(),
            lanelets: vec![first, straight(2, 20.0, 40.0)],
            skipped: Default::default(),
            priority_rules: Vec::new(),
        }
    }

    /// `road()` with the opposite lane beside it: a lanelet along −x from 40 to 0, y in [2, 6].
    fn two_way_road() -> LaneletMap {
        let mut map = road();
        let mut opposite = straight(3, 0.0, 40.0);
        for p in opposite
            .left_m
            .iter_mut()
            .chain(opposite.right_m.iter_mut())
        {
            p[1] += 4.0;
        }
        for p in &mut opposite.centre_m {
            p[1] = 4.0;
        }
        // Driving −x, the left bound is the one at y = 2 and the centre line runs backwards.
        std::mem::swap(&mut opposite.left_m, &mut opposite.right_m);
        opposite.left_m.reverse();
        opposite.right_m.reverse();
        opposite.centre_m.reverse();
        opposite.bounds = Aabb {
            min: [0.0, 2.0],
            max: [40.0, 6.0],
        };
        map.lanelets.push(opposite);
        map
    }

    fn pose(x_m: f64, y_m: f64, heading_rad: f64) -> Pose {
        Pose {
            x_m,
            y_m,
            heading_rad,
        }
    }

    #[test]
    fn a_vehicle_across_or_against_every_lane_under_it_is_told_from_one_along_one() {
        let map = two_way_road();
        let across = |x_m: f64, y_m: f64, heading_deg: f64| {
            let facing = DVec2::from_angle(heading_deg.to_radians());
            across_every_lane(&map, DVec2::new(x_m, y_m), facing, 60f64.to_radians())
        };
        // On the +x lane: along it, or 50° off, it is not across; 70° off, it is.
        assert!(!across(10.0, 0.0, 0.0));
        assert!(!across(10.0, 0.0, -50.0));
        assert!(across(10.0, 0.0, 70.0));
        // Against the +x lane, where no lane runs −x: across every lane.
        assert!(across(10.0, 0.0, 180.0));
        // Facing −x on the opposite lane, it drives along that one.
        assert!(!across(10.0, 4.0, 180.0));
        // Off the road it is across every lane (there is none).
        assert!(across(10.0, 20.0, 0.0));
    }

    /// A standing vehicle's jitter is not steered, but it may not creep off the road.
    #[test]
    fn a_creeping_vehicle_stays_on_the_road() {
        let before = pose(10.0, 1.98, 0.0);
        let mut creeping = pose(10.01, 2.02, 0.0);
        let action = keep_on_road(&road(), before, &mut creeping, 6.0, false);
        assert_eq!(action, Some(LaneAction::StoppedAtEdge));
        assert_eq!((creeping.x_m, creeping.y_m), (10.0, 1.98));
        let mut jitter = pose(10.01, 1.97, 0.0);
        assert_eq!(keep_on_road(&road(), before, &mut jitter, 6.0, false), None);
        assert_eq!(jitter, pose(10.01, 1.97, 0.0));
    }

    #[test]
    fn a_step_that_stays_on_road_is_left_alone() {
        let mut proposed = pose(11.0, 1.0, 0.1);
        let action = keep_on_road(&road(), pose(10.0, 0.5, 0.0), &mut proposed, 6.0, false);
        assert_eq!(action, None);
        assert_eq!(proposed, pose(11.0, 1.0, 0.1));
    }

    #[test]
    fn a_step_off_the_road_turns_back_to_the_lane_at_the_same_speed() {
        let before = pose(10.0, 1.6, 0.0);
        // 1 m at 45° to the left: ends at y = 2.3, off the 4 m wide road.
        let mut proposed = pose(10.0 + 0.5f64.sqrt(), 1.6 + 0.5f64.sqrt(), 0.785);
        let action = keep_on_road(&road(), before, &mut proposed, 6.0, false);
        assert_eq!(action, Some(LaneAction::Steered));
        let step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
        assert!((step.length() - 1.0).abs() < 1e-9, "speed kept: {step}");
        // Towards the centre line 6 m ahead: (16, 0).
        let expected = DVec2::new(6.0, -1.6).normalize();
        assert!((step.normalize() - expected).length() < 1e-9, "{step}");
        assert!((proposed.heading_rad - expected.to_angle()).abs() < 1e-9);
        assert!(road().lanelet_at([proposed.x_m, proposed.y_m]).is_some());
    }

    const ANTICIPATION: LaneAnticipation = LaneAnticipation {
        steps: 10,
        max_turn_rad_per_m: 0.1,
    };

    #[test]
    fn a_step_drifting_towards_the_edge_is_nudged_back_a_little() {
        let before = pose(10.0, 1.0, 0.1);
        // 1 m at 0.1 rad to the left: on the road (y = 1.1), its continuation leaves it
        // within 10 steps (y = 2 after 9).
        let drift = DVec2::from_angle(0.1);
        let mut proposed = pose(10.0 + drift.x, 1.0 + drift.y, 0.12);
        assert!(nudge_towards_lane(
            &road(),
            before,
            &mut proposed,
            6.0,
            ANTICIPATION,
            false
        ));
        let step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
        assert!((step.length() - 1.0).abs() < 1e-9, "speed kept: {step}");
        // The target (16, 0) lies 0.27 rad to the right: the turn stops at 0.1 rad per metre.
        assert!((step.to_angle() - 0.0).abs() < 1e-9, "{step}");
        assert!(proposed.heading_rad.abs() < 1e-9, "heading along the step");
    }

    #[test]
    fn a_step_along_the_lane_or_off_its_end_is_not_nudged() {
        let mut along = pose(11.0, 0.0, 0.0);
        assert!(!nudge_towards_lane(
            &road(),
            pose(10.0, 0.0, 0.0),
            &mut along,
            6.0,
            ANTICIPATION,
            false
        ));
        assert_eq!(along, pose(11.0, 0.0, 0.0));
        // Near the end of the last lanelet (x = 40), which has no successor: out of the map.
        let mut leaving_the_map = pose(38.0, 0.3, 0.05);
        let before = pose(37.0, 0.25, 0.05);
        assert!(!nudge_towards_lane(
            &road(),
            before,
            &mut leaving_the_map,
            6.0,
            ANTICIPATION,
            false
        ));
        // Slow (position noise) and backwards steps.
        let mut slow = pose(10.1, 1.9, 0.5);
        assert!(!nudge_towards_lane(
            &road(),
            pose(10.0, 1.85, 0.5),
            &mut slow,
            6.0,
            ANTICIPATION,
            false
        ));
        let mut backwards = pose(9.0, 1.9, 0.0);
        assert!(!nudge_towards_lane(
            &road(),
            pose(10.0, 1.8, 0.0),
            &mut backwards,
            6.0,
            ANTICIPATION,
            false
        ));
    }

    #[test]
    fn the_look_ahead_follows_the_successor() {
        let before = pose(18.0, 1.9, 0.0);
        let mut proposed = pose(19.0, 2.4, 0.46);
        let action = keep_on_road(&road(), before, &mut proposed, 6.0, false);
        assert_eq!(action, Some(LaneAction::Steered));
        // The target (24, 0) lies on the successor.
        let step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
        let expected = DVec2::new(6.0, -1.9).normalize();
        assert!((step.normalize() - expected).length() < 1e-9, "{step}");
    }

    /// `road()` with a side road joining it from the left (+y) at x = 20: a lanelet 4 m wide
    /// whose centre line is the quarter circle of radius 8 m about (20, 8) from (12, 8), heading
    /// −y, to (20, 0), heading +x, where it leads into the second lanelet (as a roundabout's
    /// entry leads into the ring just past the exit).
    fn road_with_merging_lane() -> LaneletMap {
        let centre = DVec2::new(20.0, 8.0);
        let ring = |radius_m: f64| -> Vec<Point> {
            (0..=16)
                .map(|i| {
                    let angle = std::f64::consts::PI * (1.0 + 0.5 * f64::from(i) / 16.0);
                    (centre + DVec2::from_angle(angle) * radius_m).into()
                })
                .collect()
        };
        let mut map = road();
        map.lanelets.push(Lanelet {
            id: 3,
            subtype: None,
            left_way: 6,
            right_way: 7,
            // Counter-clockwise about the centre: the left bound is the inner one.
            left_m: ring(6.0),
            right_m: ring(10.0),
            centre_m: ring(8.0),
            successors: vec![1],
            neighbours: Vec::new(),
            bounds: Aabb {
                min: [10.0, -2.0],
                max: [20.0, 8.0],
            },
        });
        map
    }

    #[test]
    fn a_step_into_a_merging_lane_against_it_turns_back_to_its_own() {
        let map = road_with_merging_lane();
        let before = pose(13.0, 1.5, 1.0);
        // Up and to the left, leaving its lane (y ≤ 2) onto the side road, whose centre line
        // runs down and to the right there: about 120° against the step.
        let mut proposed = pose(13.3, 2.45, 1.26);
        assert!(map.lanelet_at([proposed.x_m, proposed.y_m]).is_some());
        let action = keep_on_road(&map, before, &mut proposed, 6.0, false);
        assert_eq!(action, Some(LaneAction::Steered));
        // Towards the centre line 6 m ahead, (19, 0), at the same speed.
        let step = DVec2::new(proposed.x_m - before.x_m, proposed.y_m - before.y_m);
        let expected = DVec2::new(6.0, -1.5).normalize();
        assert!((step.normalize() - expected).length() < 1e-9, "{step}");
        assert!(
            (step.length() - 0.3f64.hypot(0.95)).abs() < 1e-9,
            "speed kept: {step}"
        );
    }

    #[test]
    fn a_slow_step_into_a_merging_lane_is_left_alone() {
        // 0.1 m in 0.1 s, as the step above: a crawling vehicle's noise has no direction to
        // judge.
        let map = road_with_merging_lane();
        let before = pose(13.0, 1.95, 1.0);
        let mut proposed = pose(13.03, 2.045, 1.26);
        let unchanged = proposed;
        assert!(map.lanelets[0].contains([before.x_m, before.y_m]));
        assert!(!map.lanelets[0].contains([proposed.x_m, proposed.y_m]));
        assert!(map.lanelets[2].contains([proposed.x_m, proposed.y_m]));
        assert_eq!(keep_on_road(&map, before, &mut proposed, 6.0, false), None);
        assert_eq!(proposed, unchanged);
    }

    #[test]
    fn a_step_onto_a_lane_that_does_not_lead_into_its_own_is_left_alone() {
        // The same kind of step onto the opposite lane of a two-way road, linked end to end with
        // the agent's as a U-turn: lanelets of other ways are crossed in the recordings where the
        // map has none for a vehicle's own path.
        let mut map = two_way_road();
        map.lanelets[2].successors = vec![0];
        let mut proposed = pose(10.0 + 0.5f64.sqrt(), 1.6 + 0.5f64.sqrt(), 0.785);
        let unchanged = proposed;
        assert_eq!(
            keep_on_road(&map, pose(10.0, 1.6, 0.0), &mut proposed, 6.0, false),
            None
        );
        assert_eq!(proposed, unchanged);
    }

    #[test]
    fn a_step_onto_the_opposite_carriageway_is_steered_back_when_asked() {
        // From near the left edge of the +x lane, 0.46 rad to the left: the step ends on the
        // −x lane (154° against it) and on no lane running its way.
        let map = two_way_road();
        let before = pose(10.0, 1.8, 0.46);
        let stepping = pose(11.0, 2.3, 0.46);
        let mut proposed = stepping;
        assert_eq!(keep_on_road(&map, before, &mut proposed, 6.0, false), None);
        assert_eq!(proposed, stepping);
        let action = keep_on_road(&map, before, &mut proposed, 6.0, true);
        assert_eq!(action, Some(LaneAction::Steered));
        assert!(proposed.y_m < 2.0, "kept to its side: {proposed:?}");
        // A step that stays on its own lane is left alone either way.
        let mut along = pose(11.0, 1.9, 0.1);
        assert_eq!(
            keep_on_road(&map, pose(10.0, 1.8, 0.1), &mut along, 6.0, true),
            None
        );
    }

    #[test]
    fn a_vehicle_may_leave_through_the_start_of_a_lane_with_no_predecessor() {
        // Facing −x at the start of the first lanelet (x = 0, nothing leads into it): the map's
        // edge. Driving or creeping out is leaving the map, not leaving the road.
        let mut driving = pose(-0.5, 0.0, PI);
        assert_eq!(
            keep_on_road(&road(), pose(0.5, 0.0, PI), &mut driving, 6.0, false),
            None
        );
        assert_eq!(driving, pose(-0.5, 0.0, PI));
        let mut creeping = pose(-0.02, 0.0, PI);
        assert_eq!(
            keep_on_road(&road(), pose(0.02, 0.0, PI), &mut creeping, 6.0, false),
            None
        );
        // Over a side edge, the same step is stopped.
        let mut sideways = pose(5.0, 2.02, FRAC_PI_2);
        assert_eq!(
            keep_on_road(
                &road(),
                pose(5.0, 1.98, FRAC_PI_2),
                &mut sideways,
                6.0,
                false
            ),
            Some(LaneAction::StoppedAtEdge)
        );
    }

    #[test]
    fn a_vehicle_backing_out_through_the_map_s_end_leaves_and_backing_over_a_side_does_not() {
        // Facing into the map (−x) at the end of the last lanelet (x = 40, no successor),
        // backing off +x out of it: it leaves the map (and is retired), as one driving out does.
        let mut backing_out = pose(40.1, -1.0, PI);
        assert_eq!(
            keep_on_road(&road(), pose(39.95, -1.0, PI), &mut backing_out, 6.0, true),
            None
        );
        assert_eq!(backing_out, pose(40.1, -1.0, PI));
        // Backing over the road's side there is still stopped at the edge.
        let mut backing_sideways = pose(35.0, -2.1, FRAC_PI_2);
        assert_eq!(
            keep_on_road(
                &road(),
                pose(35.0, -1.9, FRAC_PI_2),
                &mut backing_sideways,
                6.0,
                true
            ),
            Some(LaneAction::StoppedAtEdge)
        );
    }

    #[test]
    fn the_merging_lane_is_a_lane_for_those_driving_it() {
        let map = road_with_merging_lane();
        // Driving down the side road (heading −y at x = 12), drifting within it: left alone.
        let before = pose(12.0, 8.0, -std::f64::consts::FRAC_PI_2);
        let mut proposed = pose(12.3, 7.0, -1.3);
        assert_eq!(keep_on_road(&map, before, &mut proposed, 6.0, false), None);
        assert_eq!(proposed, pose(12.3, 7.0, -1.3));
    }

    #[test]
    fn an_agent_already_off_road_is_left_alone() {
        let mut proposed = pose(11.0, 4.0, 0.0);
        let action = keep_on_road(&road(), pose(10.0, 3.0, 0.0), &mut proposed, 6.0, false);
        assert_eq!(action, None);
        assert_eq!(proposed, pose(11.0, 4.0, 0.0));
    }

    #[test]
    fn an_agent_against_its_lane_stepping_off_the_side_stops_at_the_edge() {
        // Heading −x on a lanelet that runs +x, stepping off the road's side.
        let before = pose(10.0, 1.6, std::f64::consts::PI);
        let mut proposed = pose(9.3, 2.3, std::f64::consts::PI - 0.785);
        let action = keep_on_road(&road(), before, &mut proposed, 6.0, false);
        assert_eq!(action, Some(LaneAction::StoppedAtEdge));
        assert!(road().lanelet_at([proposed.x_m, proposed.y_m]).is_some());
        assert!(
            proposed.y_m > 1.9,
            "it went as far as the edge: {proposed:?}"
        );
        // On the road it is left alone.
        let mut staying = pose(9.0, 1.0, std::f64::consts::PI);
        assert_eq!(
            keep_on_road(&road(), before, &mut staying, 6.0, false),
            None
        );
        assert_eq!(staying, pose(9.0, 1.0, std::f64::consts::PI));
    }

    /// Issue 41: a vehicle standing beside a stopped ego slid off the merge's side, its steps
    /// (6 cm a tick) a hair behind square to its heading. Reversing is not steered, but it may
    /// not leave the road either.
    #[test]
    fn a_vehicle_sliding_or_backing_off_the_side_stops_at_the_edge() {
        let before = pose(10.0, 1.95, 0.0);
        let mut sliding = pose(9.999, 2.01, 0.0);
        let action = keep_on_road(&road(), before, &mut sliding, 6.0, false);
        assert_eq!(action, Some(LaneAction::StoppedAtEdge));
        assert!(road().lanelet_at([sliding.x_m, sliding.y_m]).is_some());
        assert!(
            sliding.y_m > 1.99,
            "it went as far as the edge: {sliding:?}"
        );
        let mut backing = pose(9.0, 2.5, 0.3);
        let action = keep_on_road(&road(), pose(10.0, 1.8, 0.3), &mut backing, 6.0, false);
        assert_eq!(action, Some(LaneAction::StoppedAtEdge));
        assert!(road().lanelet_at([backing.x_m, backing.y_m]).is_some());
        // Backing along the road is left alone, and so is backing out of the map's start.
        let mut along = pose(9.0, 1.0, 0.0);
        assert_eq!(
            keep_on_road(&road(), pose(10.0, 1.0, 0.0), &mut along, 6.0, false),
            None
        );
        assert_eq!(along, pose(9.0, 1.0, 0.0));
        let mut out_of_the_start = pose(-0.6, 0.2, 0.0);
        assert_eq!(
            keep_on_road(
                &road(),
                pose(0.3, 0.2, 0.0),
                &mut out_of_the_start,
                6.0,
                false
            ),
            None
        );
    }

    #[test]
    fn driving_off_the_end_of_the_map_is_left_alone() {
        // The second lanelet has no successor: its end is the end of the mapped area.
        let before = pose(39.5, 0.0, 0.0);
        let mut proposed = pose(40.5, 0.3, 0.3);
        assert_eq!(
            keep_on_road(&road(), before, &mut proposed, 6.0, false),
            None
        );
        assert_eq!(proposed, pose(40.5, 0.3, 0.3));
    }

    #[test]
    fn a_step_that_cannot_turn_back_in_time_stops_at_the_edge() {
        // A 6 m step out of the side at the road's edge, with a target 0.5 m ahead: steered
        // towards it, the step crosses the 4 m wide road and leaves it on the other side.
        let before = pose(10.0, 1.9, 1.2);
        let mut proposed = pose(10.0 + 6.0 * 1.2f64.cos(), 1.9 + 6.0 * 1.2f64.sin(), 1.2);
        let action = keep_on_road(&road(), before, &mut proposed, 0.5, false);
        assert_eq!(action, Some(LaneAction::StoppedAtEdge));
        assert!(road().lanelet_at([proposed.x_m, proposed.y_m]).is_some());
    }

    #[test]
    fn headings_stay_unwrapped_near_the_agent_s() {
        let before = pose(10.0, 1.6, 4.0 * std::f64::consts::PI);
        let mut proposed = pose(10.7, 2.3, 4.0 * std::f64::consts::PI + 0.785);
        keep_on_road(&road(), before, &mut proposed, 6.0, false);
        assert!((proposed.heading_rad - 4.0 * std::f64::consts::PI).abs() < 0.5);
    }
}
