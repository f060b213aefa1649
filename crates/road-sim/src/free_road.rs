//! Whether a vehicle stands with free road ahead: what the stall release
//! (`road_sched::StallRelease`) and the long sessions' counts (`crate::session`) both ask. The
//! release asks [`BlockedPaths`] for the centre rule (`centres_ahead`; an oncoming vehicle
//! clear of the path aside), relaxed where only vehicles waiting for it hold it, and for
//! gridlocks; the counts ask it what stands in the vehicle's own path, gridlocks included.

use glam::DVec2;

use crate::Pose;
use crate::geometry::OrientedBox;

/// Slower than this, a vehicle is stopped (m/s).
pub const STOPPED_MAX_SPEED_MPS: f64 = 0.3;
/// The road ahead of a stopped vehicle is free when no other vehicle's centre lies within this
/// distance ahead of it (metres), within [`FREE_ROAD_HALF_WIDTH_M`] of its axis.
pub const FREE_ROAD_AHEAD_M: f64 = 15.0;
pub const FREE_ROAD_HALF_WIDTH_M: f64 = 3.0;
/// A vehicle's path: its own width and this much on each side (metres), from its centre to
/// [`FREE_ROAD_AHEAD_M`] ahead of it.
pub const PATH_MARGIN_M: f64 = 0.3;
/// A vehicle pointing more than this off another's heading (radians, 135°) comes towards it:
/// one on its own side of the road, its box clear of the other's path, holds nobody
/// ([`BlockedPaths::new`]).
pub const ONCOMING_MIN_RAD: f64 = 3.0 * std::f64::consts::FRAC_PI_4;

/// The other present vehicles whose centre lies ahead of `agent` by the centre rule: within
/// [`FREE_ROAD_AHEAD_M`] ahead of it and [`FREE_ROAD_HALF_WIDTH_M`] of its axis.
fn centres_ahead<'a>(
    agent: usize,
    poses: &'a [Pose],
    present: &'a [usize],
) -> impl Iterator<Item = usize> + 'a {
    let me = poses[agent];
    let forward = DVec2::from_angle(me.heading_rad);
    present.iter().copied().filter(move |&b| {
        let d = poses[b].position_m() - me.position_m();
        let along = d.dot(forward);
        let across = d.perp_dot(forward).abs();
        b != agent && along > 0.0 && along <= FREE_ROAD_AHEAD_M && across <= FREE_ROAD_HALF_WIDTH_M
    })
}

/// For one tick, what stands in each present vehicle's way, by footprint: a vehicle turned
/// across another's path has its centre beside that path and its tail in it, and the centre
/// rule alone (`centres_ahead`) called the one behind it free (8 of issue 39's 9 long
/// stops "with free road ahead" in the 2026-11-27 sessions stood behind such a tail).
#[derive(Debug, Clone)]
pub struct BlockedPaths {
    /// Per agent (indexed like the poses; empty for absent ones): the present vehicles whose
    /// box lies in its path ([`PATH_MARGIN_M`]).
    in_path: Vec<Vec<usize>>,
    /// Per agent: the present vehicles whose centre lies ahead of it by the centre rule, those
    /// coming towards it with their box clear of its path left out.
    centre_ahead: Vec<Vec<usize>>,
}

impl BlockedPaths {
    /// `size_m[a]` is agent `a`'s `[length, width]` (metres); `present` the agents in the scene.
    pub fn new(poses: &[Pose], size_m: &[[f64; 2]], present: &[usize]) -> Self {
        let box_of = |a: usize, pose: Pose, grow_width_m: f64, length_m: f64| OrientedBox {
            pose,
            length_m,
            width_m: size_m[a][1] + 2.0 * grow_width_m,
        };
        let mut in_path = vec![Vec::new(); poses.len()];
        let mut centre_ahead = vec![Vec::new(); poses.len()];
        for &a in present {
            let me = poses[a];
            let forward = DVec2::from_angle(me.heading_rad);
            // From the centre to FREE_ROAD_AHEAD_M ahead: a box centred half way.
            let path = box_of(
                a,
                Pose::at(
                    me.position_m() + forward * (FREE_ROAD_AHEAD_M / 2.0),
                    me.heading_rad,
                ),
                PATH_MARGIN_M,
                FREE_ROAD_AHEAD_M,
            );
            let reach_m = FREE_ROAD_AHEAD_M + size_m[a][1] + PATH_MARGIN_M;
            in_path[a] = present
                .iter()
                .copied()
                .filter(|&b| {
                    b != a
                        && poses[b].position_m().distance(me.position_m())
                            <= reach_m + 0.5 * size_m[b][0].hypot(size_m[b][1])
                        && path.overlaps(&box_of(b, poses[b], 0.0, size_m[b][0]))
                })
                .collect();
            // An oncoming vehicle on its own side of the road passes: two on their own lanes,
            // centres 2.5 m apart across the centre line, each had the other "ahead", neither
            // stood with free road by the count nor was released, and the model crawled them
            // towards each other for 97 s (issue 39).
            let in_path_a = &in_path[a];
            centre_ahead[a] = centres_ahead(a, poses, present)
                .filter(|&b| {
                    let oncoming = DVec2::from_angle(poses[b].heading_rad).dot(forward)
                        < ONCOMING_MIN_RAD.cos();
                    !oncoming || in_path_a.contains(&b)
                })
                .collect();
        }
        Self {
            in_path,
            centre_ahead,
        }
    }

    /// No vehicle's box in its path and no vehicle's centre ahead by the centre rule.
    pub fn road_ahead_free(&self, agent: usize) -> bool {
        self.in_path[agent].is_empty() && self.centre_ahead[agent].is_empty()
    }

    /// No vehicle's centre ahead by the centre rule (`centres_ahead`), oncoming vehicles
    /// clear of its path aside.
    pub fn centre_rule_free(&self, agent: usize) -> bool {
        self.centre_ahead[agent].is_empty()
    }

    /// Free by the centre rule, or held only by vehicles that wait for it: no vehicle's box in
    /// its path, and every vehicle whose centre lies ahead of it by the centre rule stands
    /// with it in that vehicle's own path (`standing[b]` for every agent). Neither moves
    /// first otherwise: a vehicle against its lane at MA's kerb stood 33 s beside one it
    /// blocked, whose centre lay 0.4 m ahead of it and 2.7 m to the side (issue 39).
    pub fn free_but_for_those_waiting(&self, agent: usize, standing: &[bool]) -> bool {
        self.centre_rule_free(agent)
            || (self.in_path[agent].is_empty()
                && self.centre_ahead[agent]
                    .iter()
                    .all(|&b| standing[b] && self.in_path[b].contains(&agent)))
    }

    /// The vehicles whose box lies in its path.
    pub fn in_path(&self, agent: usize) -> &[usize] {
        &self.in_path[agent]
    }

    /// Whether `agent` stands in a gridlock: it is on a cycle of standing vehicles, each with
    /// the next in its path (`standing[b]` for every agent). No brake undoes one, and its
    /// vehicles' roads are never free: counted with the stops with free road ahead, a
    /// deadlock cannot hide. A vehicle queued behind a gridlock is not on the cycle.
    pub fn in_gridlock(&self, agent: usize, standing: &[bool]) -> bool {
        standing[agent] && self.reached_from(agent, standing)[agent]
    }

    /// The vehicles of `agent`'s gridlock ([`Self::in_gridlock`]), itself included, in index
    /// order: every standing vehicle on a cycle through it. Empty when it is in none.
    pub fn gridlock(&self, agent: usize, standing: &[bool]) -> Vec<usize> {
        if !standing[agent] {
            return Vec::new();
        }
        let from_agent = self.reached_from(agent, standing);
        if !from_agent[agent] {
            return Vec::new();
        }
        (0..self.in_path.len())
            .filter(|&b| {
                standing[b]
                    && from_agent[b]
                    && (b == agent || self.reached_from(b, standing)[agent])
            })
            .collect()
    }

    /// Per agent: whether a chain of paths from `agent` reaches it, every vehicle on the way
    /// (the last one aside) standing.
    fn reached_from(&self, agent: usize, standing: &[bool]) -> Vec<bool> {
        let mut reached = vec![false; self.in_path.len()];
        let mut stack: Vec<usize> = self.in_path[agent].clone();
        while let Some(b) = stack.pop() {
            if reached[b] {
                continue;
            }
            reached[b] = true;
            if standing[b] && b != agent {
                stack.extend(self.in_path[b].iter().copied());
            }
        }
        reached
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x_m: f64, y_m: f64, heading_deg: f64) -> Pose {
        Pose {
            x_m,
            y_m,
            heading_rad: heading_deg.to_radians(),
        }
    }

    const CAR: [f64; 2] = [4.5, 1.8];

    #[test]
    fn a_tail_turned_across_the_path_blocks_it_and_a_car_beside_the_lane_does_not() {
        // Car 0 east at the origin; car 1 turned away to the south, its centre 3.3 m right of
        // car 0's axis and 3 m ahead, its tail in car 0's path; car 2 in the next lane, 3.5 m
        // to the left.
        let poses = [
            pose(0.0, 0.0, 0.0),
            pose(3.0, -3.3, -90.0),
            pose(2.0, 3.5, 0.0),
        ];
        let present = [0, 1, 2];
        assert!(
            centres_ahead(0, &poses, &present).next().is_none(),
            "the centre rule misses it"
        );
        let paths = BlockedPaths::new(&poses, &[CAR; 3], &present);
        assert_eq!(paths.in_path(0), &[1]);
        assert!(!paths.road_ahead_free(0));
        assert!(paths.road_ahead_free(2));
        // Alone, car 0's road is free again.
        let alone = BlockedPaths::new(&poses, &[CAR; 3], &[0, 2]);
        assert!(alone.road_ahead_free(0));
    }

    #[test]
    fn a_car_held_only_by_one_waiting_for_it_is_free_but_for_those_waiting() {
        // Car 1 against its lane at the kerb, pointing back (−118°); car 0 turning across it
        // (120°, 122° off car 1: not oncoming), 3 m away: car 1's box lies in car 0's path,
        // while car 0's centre lies ahead of car 1 by the centre rule with its box clear of
        // car 1's path.
        let poses = [pose(1021.0, 1031.0, 120.0), pose(1018.4, 1032.4, -118.0)];
        let present = [0, 1];
        let paths = BlockedPaths::new(&poses, &[CAR; 2], &present);
        assert_eq!(paths.in_path(0), &[1]);
        assert!(paths.in_path(1).is_empty());
        assert!(
            !paths.centre_rule_free(1),
            "car 0's centre is ahead of car 1"
        );
        let standing = [true; 2];
        assert!(!paths.in_gridlock(0, &standing), "no cycle of paths");
        assert!(paths.free_but_for_those_waiting(1, &standing));
        assert!(
            !paths.free_but_for_those_waiting(0, &standing),
            "car 1's centre ahead, its box in the path"
        );
        // Car 0 driving on: car 1 waits for it.
        assert!(!paths.free_but_for_those_waiting(1, &[false, true]));
        // A car whose centre is ahead of car 1 (6 m on, 2.6 m to the side, the same way), its
        // box beside car 1's path and car 1 not in its own, holds it.
        let beside = [poses[0], poses[1], pose(1017.89, 1025.88, -118.0)];
        let paths = BlockedPaths::new(&beside, &[CAR; 3], &[0, 1, 2]);
        assert!(paths.in_path(1).is_empty() && paths.in_path(2).is_empty());
        assert!(!paths.free_but_for_those_waiting(1, &[true; 3]));
        // MA's own case: car 0 north (89°, 153° off car 1) comes towards car 1, clear of its
        // path, and holds it no more, standing or not.
        let ma = [pose(1020.6, 1030.8, 89.0), poses[1]];
        let paths = BlockedPaths::new(&ma, &[CAR; 2], &present);
        assert!(
            centres_ahead(1, &ma, &present).next().is_some(),
            "by the centre rule alone"
        );
        assert!(paths.centre_rule_free(1));
        assert!(paths.free_but_for_those_waiting(1, &[false, true]));
    }

    #[test]
    fn an_oncoming_car_on_its_own_side_holds_nobody_and_one_in_the_path_or_the_same_way_does() {
        // Car 0 east; car 1 west, 8 m ahead and 2.5 m to its left (the other lane of a
        // two-lane road): each centre lies ahead of the other by the centre rule.
        let poses = [pose(0.0, 0.0, 0.0), pose(8.0, 2.5, 180.0)];
        let present = [0, 1];
        assert!(
            centres_ahead(0, &poses, &present).next().is_some(),
            "the centre rule alone"
        );
        let paths = BlockedPaths::new(&poses, &[CAR; 2], &present);
        assert!(paths.road_ahead_free(0) && paths.road_ahead_free(1));
        assert!(paths.centre_rule_free(0) && paths.centre_rule_free(1));
        // 165° off, 2.8 m across, still comes towards it.
        let skewed = [poses[0], pose(10.0, 2.8, 165.0)];
        assert!(BlockedPaths::new(&skewed, &[CAR; 2], &present).road_ahead_free(0));
        // The same way (a queue offset in its lane) holds it, as before.
        let same_way = [poses[0], pose(8.0, 2.5, 0.0)];
        let paths = BlockedPaths::new(&same_way, &[CAR; 2], &present);
        assert!(paths.in_path(0).is_empty() && !paths.centre_rule_free(0));
        // Oncoming in its lane (1.2 m across: the boxes overlap the paths) holds both.
        let head_on = [poses[0], pose(8.0, 1.2, 180.0)];
        let paths = BlockedPaths::new(&head_on, &[CAR; 2], &present);
        assert!(!paths.road_ahead_free(0) && !paths.road_ahead_free(1));
        assert!(!paths.centre_rule_free(0) && !paths.centre_rule_free(1));
    }

    #[test]
    fn standing_cars_each_in_the_next_one_s_path_are_a_gridlock_and_a_queue_behind_is_not() {
        // Cars 0–3 round a 6 m square, each pointing at the next one's flank (the four arms
        // of a crossing blocked box); car 4 queued 8 m behind car 0.
        let poses = [
            pose(0.0, 0.0, 0.0),
            pose(6.0, 0.0, 90.0),
            pose(6.0, 6.0, 180.0),
            pose(0.0, 6.0, 270.0),
            pose(-8.0, 0.0, 0.0),
        ];
        let present = [0, 1, 2, 3, 4];
        let paths = BlockedPaths::new(&poses, &[CAR; 5], &present);
        let standing = [true; 5];
        for a in 0..4 {
            assert!(paths.in_gridlock(a, &standing), "car {a}");
        }
        assert!(!paths.in_gridlock(4, &standing), "queued behind it");
        assert_eq!(paths.gridlock(2, &standing), vec![0, 1, 2, 3]);
        assert!(paths.gridlock(4, &standing).is_empty());
        // One of them moving: no gridlock.
        let mut one_moving = standing;
        one_moving[2] = false;
        assert!((0..4).all(|a| !paths.in_gridlock(a, &one_moving)));
    }
}
