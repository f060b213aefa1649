//! The give-way rule ([`GiveWay`]): model-driven vehicles heed the map's priority rules
//! (`road_data::rules`). A vehicle on a lanelet that gives way stops before the lanelet's end
//! (its stop line) until its way is clear: at a right of way, no priority vehicle due within
//! the gap and room beyond the line; at an all-way stop, its turn in the order of arrival and
//! nobody in the junction in its way. Issue 39's long sessions jammed where vehicles pushed
//! into a roundabout's ring or an all-way stop's box that the recordings' drivers gave way at.

use glam::DVec2;
use road_data::LaneletMap;
use road_data::geometry::Point;
use road_data::rules::{PriorityRule, RuleKind};
use road_planner::collision_guard::GuardAction;
use road_sched::GiveWay;

use super::{Controller, STEP_SECS, SceneRuntime, set_emitted};

/// A vehicle stops this far short of its stop line, metres.
const STOP_MARGIN_M: f64 = 0.5;
/// A vehicle whose front is within this of its stop line, standing, has arrived at an
/// all-way stop, metres.
const ARRIVED_WITHIN_M: f64 = 4.0;
/// A vehicle that could not stop by its line braking at this many times the rule's
/// deceleration goes on, as a driver does at an amber light.
const HARD_BRAKE_FACTOR: f64 = 2.0;
/// A vehicle slower than this can stop at once (m/s).
const CAN_ALWAYS_STOP_BELOW_MPS: f64 = 1.0;
/// A vehicle slower than this, standing beyond a right of way's line, leaves no room there
/// (m/s).
const ROOM_SPEED_MPS: f64 = 1.0;
/// Room beyond the line: the waiting vehicle's length and this much, metres.
const ROOM_GAP_M: f64 = 2.0;

/// A vehicle on its way to a stop line: the rule, the lanelet that gives way, and how far its
/// centre has left to the line along the lane (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Approach {
    rule: usize,
    lane: u32,
    to_line_m: f64,
}

/// Where `p` lies along a centre line: the length after its nearest point (metres), the line's
/// direction there, and `p`'s distance from it (metres).
struct Along {
    rest_m: f64,
    direction: DVec2,
    off_m: f64,
}

fn along(centre: &[Point], p: DVec2) -> Along {
    let mut best = (f64::INFINITY, 0, 0.0);
    for (i, w) in centre.windows(2).enumerate() {
        let (a, b) = (DVec2::from(w[0]), DVec2::from(w[1]));
        let ab = b - a;
        let t = ((p - a).dot(ab) / ab.length_squared().max(1e-12)).clamp(0.0, 1.0);
        let d = (a + ab * t).distance(p);
        if d < best.0 {
            best = (d, i, t);
        }
    }
    let (off_m, i, t) = best;
    let segment = |k: usize| DVec2::from(centre[k + 1]) - DVec2::from(centre[k]);
    let rest: f64 = (i + 1..centre.len() - 1).map(|k| segment(k).length()).sum();
    let here = segment(i);
    Along {
        rest_m: rest + here.length() * (1.0 - t),
        direction: here.normalize_or_zero(),
        off_m,
    }
}

fn length_of(centre: &[Point]) -> f64 {
    road_data::geometry::polyline_length(centre)
}

/// The rules' view of a map for one tick: each lanelet's predecessors.
struct Rules<'a> {
    map: &'a LaneletMap,
    rules: &'a [PriorityRule],
    predecessors: Vec<Vec<u32>>,
}

impl<'a> Rules<'a> {
    fn new(map: &'a LaneletMap) -> Self {
        let mut predecessors = vec![Vec::new(); map.lanelets.len()];
        for (i, l) in map.lanelets.iter().enumerate() {
            for &s in &l.successors {
                predecessors[s as usize].push(i as u32);
            }
        }
        Self {
            map,
            rules: &map.priority_rules,
            predecessors,
        }
    }

    /// How far a vehicle at `p` heading along `heading` is from the end of `lane` along the
    /// lanes, when it is on `lane` or on a lanelet leading into it (and every lanelet leading
    /// on from that one satisfies `also_on`), driving their way; and how far off that lanelet's
    /// centre line it is (metres).
    fn due_at_end_of(
        &self,
        lane: u32,
        p: DVec2,
        heading: DVec2,
        also_on: impl Fn(u32) -> bool,
    ) -> Option<(f64, f64)> {
        let lanelet = &self.map.lanelets[lane as usize];
        if lanelet.contains(p.into()) {
            let at = along(&lanelet.centre_m, p);
            return (at.direction.dot(heading) > 0.0).then_some((at.rest_m, at.off_m));
        }
        self.predecessors[lane as usize]
            .iter()
            .map(|&q| &self.map.lanelets[q as usize])
            .filter(|q| q.successors.iter().all(|&s| also_on(s)) && q.contains(p.into()))
            .find_map(|q| {
                let at = along(&q.centre_m, p);
                (at.direction.dot(heading) > 0.0)
                    .then(|| (at.rest_m + length_of(&lanelet.centre_m), at.off_m))
            })
    }

    /// The stop line a vehicle at `p` heading along `heading` is on its way to, if any: not
    /// where it lies nearer the centre of a lanelet that has the way (the end of a ramp
    /// overlaps the main road).
    fn approach(&self, p: DVec2, heading: DVec2) -> Option<Approach> {
        self.rules.iter().enumerate().find_map(|(r, rule)| {
            let (lane, (to_line_m, off_m)) = rule.yield_lanelets.iter().find_map(|&lane| {
                self.due_at_end_of(lane, p, heading, |s| rule.yields_on(s))
                    .map(|due| (lane, due))
            })?;
            let on_priority = rule.priority_lanelets.iter().any(|&priority| {
                self.due_at_end_of(priority, p, heading, |_| false)
                    .is_some_and(|(_, priority_off_m)| priority_off_m < off_m)
            });
            (!on_priority).then_some(Approach {
                rule: r,
                lane,
                to_line_m,
            })
        })
    }

    /// The junction's lanelets a vehicle leaving `lane` may drive through (successors within
    /// the junction, on and on).
    fn paths_from(&self, rule: &PriorityRule, lane: u32) -> Vec<u32> {
        let in_junction = |l: u32| rule.junction.iter().any(|(m, _)| *m == l);
        let mut paths: Vec<u32> = Vec::new();
        let mut next: Vec<u32> = self.map.lanelets[lane as usize].successors.clone();
        while let Some(l) = next.pop() {
            if in_junction(l) && !paths.contains(&l) {
                paths.push(l);
                next.extend(&self.map.lanelets[l as usize].successors);
            }
        }
        paths
    }

    /// Whether any lanelet of `a` is, or conflicts with, any of `b` in `rule`'s junction.
    fn cross(&self, rule: &PriorityRule, a: &[u32], b: &[u32]) -> bool {
        a.iter().any(|&x| {
            b.iter()
                .any(|&y| x == y || rule.conflicts_of(x).contains(&y))
        })
    }
}

impl SceneRuntime<'_> {
    /// The give-way rule ([`GiveWay`]) on this tick's states (model units, overrides in):
    /// model-driven vehicles whose way is not clear stop short of their stop line.
    pub(super) fn give_way(
        &mut self,
        emitted: &mut [f32],
        heading_scale: f64,
        settings: GiveWay,
        map: &LaneletMap,
    ) {
        if map.priority_rules.is_empty() {
            return;
        }
        let rules = Rules::new(map);
        let frame = self.window.frame;
        let present: Vec<usize> = (0..self.controllers.len())
            .filter(|&a| !self.retired[a])
            .collect();
        let mut approach = vec![None; self.poses.len()];
        for &a in &present {
            approach[a] = rules.approach(
                self.poses[a].position_m(),
                DVec2::from_angle(self.heading_unwrapped[a]),
            );
        }
        let stop_ticks = (settings.stop_secs / STEP_SECS).round() as u32;
        for &a in &present {
            // One pulled out of a gridlock goes (the stall release's way out of it).
            if self.controllers[a] != Controller::Model
                || self.overrides[a].is_some()
                || self.held[a].pulling_out_of_gridlock
            {
                self.held[a].giving_way = false;
                continue;
            }
            let length_m = f64::from(self.window.length_m[a]);
            let memory = &mut self.held[a];
            memory.giving_way = false;
            let braking_for_line = std::mem::take(&mut memory.braking_for_line);
            let Some(at) = approach[a] else {
                // Gone on: it keeps its place in the junction until it has left it.
                if let Some((rule, _)) = memory.gone_from {
                    let p = self.poses[a].position_m();
                    let in_junction = map.priority_rules[rule as usize]
                        .junction
                        .iter()
                        .any(|(l, _)| map.lanelets[*l as usize].contains(p.into()));
                    if !in_junction {
                        memory.gone_from = None;
                    }
                }
                memory.waiting_ticks = 0;
                continue;
            };
            if memory.gone_from == Some((at.rule as u32, at.lane)) {
                continue;
            }
            memory.gone_from = None;
            let front_to_line_m = at.to_line_m - length_m / 2.0;
            if front_to_line_m > settings.approach_m {
                memory.waiting_ticks = 0;
                continue;
            }
            let speed = self.speed_mps[a];
            let room_m = (front_to_line_m - STOP_MARGIN_M).max(0.0);
            // Braking for the line since the last tick, or creeping up to it, it can stop.
            let cannot_stop = !braking_for_line
                && speed > CAN_ALWAYS_STOP_BELOW_MPS
                && speed * speed > 2.0 * HARD_BRAKE_FACTOR * settings.brake_mps2 * room_m;
            let rule = &map.priority_rules[at.rule];
            if rule.kind == RuleKind::AllWayStop
                && speed < crate::free_road::STOPPED_MAX_SPEED_MPS
                && front_to_line_m <= ARRIVED_WITHIN_M
            {
                self.held[a].waiting_ticks += 1;
            }
            let clear = cannot_stop
                || match rule.kind {
                    RuleKind::Yield => self.yield_clear(a, at, &rules, settings),
                    RuleKind::AllWayStop => {
                        self.held[a].waiting_ticks >= stop_ticks.max(1)
                            && self.all_way_clear(a, at, &rules, &approach)
                    }
                };
            if clear {
                // It goes once at its line (or unable to stop by it); further back the way is
                // looked at again each tick.
                if front_to_line_m <= ARRIVED_WITHIN_M || cannot_stop {
                    self.held[a].gone_from = Some((at.rule as u32, at.lane));
                    self.held[a].waiting_ticks = 0;
                }
                continue;
            }
            // Waiting at its line for its way; further back, the stall release may still pull
            // it up to the line (a vehicle the model stopped 10 m short stood there for 75 s).
            self.held[a].giving_way = front_to_line_m <= ARRIVED_WITHIN_M;
            self.held[a].braking_for_line = true;
            // Short of the line, no faster than it can still stop there.
            let before = self.poses[a].position_m();
            let proposed = DVec2::from(frame.to_metres([emitted[3 * a], emitted[3 * a + 1]]));
            let step = proposed - before;
            let limit_m = room_m.min((2.0 * settings.brake_mps2 * room_m).sqrt() * STEP_SECS);
            if step.length() > limit_m + 1e-6 {
                let to = before + step.normalize_or_zero() * limit_m;
                let heading = if limit_m > 0.05 {
                    f64::from(emitted[3 * a + 2]) / heading_scale
                } else {
                    self.heading_unwrapped[a]
                };
                set_emitted(emitted, a, &frame, to, heading, heading_scale);
                self.guarded.push((a, GuardAction::GaveWay));
            }
        }
    }

    /// A right of way: no vehicle on the rule's priority lanelets (or leading into one) due
    /// at its end within the gap, and no vehicle standing just beyond `a`'s line.
    fn yield_clear(&self, a: usize, at: Approach, rules: &Rules<'_>, settings: GiveWay) -> bool {
        let rule = &rules.rules[at.rule];
        let line = &rules.map.lanelets[at.lane as usize].centre_m;
        let end = DVec2::from(line[line.len() - 1]);
        let along = (end - DVec2::from(line[line.len() - 2])).normalize_or_zero();
        let length_a = f64::from(self.window.length_m[a]);
        (0..self.poses.len())
            .filter(|&b| b != a && !self.retired[b])
            .all(|b| {
                let p = self.poses[b].position_m();
                let heading = DVec2::from_angle(self.heading_unwrapped[b]);
                let speed = self.speed_mps[b];
                let due = rule.priority_lanelets.iter().any(|&lane| {
                    rules
                        .due_at_end_of(lane, p, heading, |s| s == lane)
                        .is_some_and(|(d, _)| {
                            speed >= crate::free_road::STOPPED_MAX_SPEED_MPS
                                && d / speed <= settings.gap_secs
                        })
                });
                // Beyond the line and near it: standing there, or its tail not yet clear of it.
                let beyond = p - end;
                let half_b = f64::from(self.window.length_m[b]) / 2.0;
                let no_room = beyond.dot(along) > -STOP_MARGIN_M
                    && beyond.length() < length_a + ROOM_GAP_M + half_b
                    && (speed < ROOM_SPEED_MPS || beyond.dot(along) < half_b + ROOM_GAP_M);
                !due && !no_room
            })
    }

    /// An all-way stop: everyone who stood at the rule's lines before `a` and would cross its
    /// way has gone, and nobody in the junction is in its way (those gone on from `a`'s own
    /// lane aside).
    fn all_way_clear(
        &self,
        a: usize,
        at: Approach,
        rules: &Rules<'_>,
        approach: &[Option<Approach>],
    ) -> bool {
        let rule = &rules.rules[at.rule];
        let leaving = |lane: u32| rules.paths_from(rule, lane);
        let mine = leaving(at.lane);
        let waited = self.held[a].waiting_ticks;
        (0..self.poses.len())
            .filter(|&b| b != a && !self.retired[b])
            .all(|b| {
                let memory = &self.held[b];
                if let Some(other) = approach[b].filter(|o| o.rule == at.rule) {
                    let earlier = memory.waiting_ticks > waited
                        || (memory.waiting_ticks == waited && waited > 0 && b < a);
                    let gone = memory.gone_from == Some((at.rule as u32, other.lane));
                    if gone {
                        return other.lane == at.lane
                            || !rules.cross(rule, &mine, &leaving(other.lane));
                    }
                    // One from another lane that stood there first and crosses its way
                    // goes first.
                    return !(earlier
                        && other.lane != at.lane
                        && rules.cross(rule, &mine, &leaving(other.lane)));
                }
                if memory
                    .gone_from
                    .is_some_and(|(r, lane)| r as usize == at.rule && lane == at.lane)
                {
                    return true;
                }
                // Its centre or its tail in the junction.
                let p = self.poses[b].position_m();
                let tail = p - DVec2::from_angle(self.heading_unwrapped[b])
                    * (f64::from(self.window.length_m[b]) / 2.0);
                let occupied: Vec<u32> = rule
                    .junction
                    .iter()
                    .map(|(l, _)| *l)
                    .filter(|&l| {
                        let lanelet = &rules.map.lanelets[l as usize];
                        lanelet.contains(p.into()) || lanelet.contains(tail.into())
                    })
                    .collect();
                !rules.cross(rule, &mine, &occupied)
            })
    }
}
