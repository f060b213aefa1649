//! What a long session did, counted tick by tick ([`SessionStats`]): the figures of
//! `road eval --suite long` (issue 39), per vehicle-minute so that sessions with more traffic
//! compare with sessions with less.

use std::collections::BTreeSet;

use serde::Serialize;

use crate::Pose;
use crate::closed_loop::SceneTick;
use crate::free_road::{BlockedPaths, STOPPED_MAX_SPEED_MPS};
use road_data::LaneletMap;
use road_data::tracks::STEP_SECS;
use road_planner::collision_guard::GuardAction;
use road_planner::lane_guard::onto_an_opposing_lane;

/// A stop with free road ahead counts once it lasts this long (seconds).
pub const LONG_STOP_SECS: f64 = 10.0;
/// The lengths by which stops with free road ahead are counted too
/// ([`SessionStats::free_stops_at_least`]), in ticks: 3, 5, 7 and 10 s.
pub const STOP_LENGTH_EDGES_TICKS: [u32; 4] = [30, 50, 70, 100];
/// A vehicle whose heading turns more than this in all (net, radians: 1¼ turns) has lapped a
/// ring: no route through a roundabout or a crossing turns that much.
pub const LAP_TURN_RAD: f64 = 2.5 * std::f64::consts::PI;
/// From this speed a vehicle's course over a tick says which way it drives (m/s).
pub const MOVING_MIN_SPEED_MPS: f64 = 1.0;
/// A vehicle stands when it is slower than `STOPPED_MAX_SPEED_MPS` over its last tick, or on
/// average over this many ticks (2 s): one the releases rock back and forth in place moves
/// every tick and stood for 101 s uncounted (issue 39).
pub const STANDING_WINDOW_TICKS: usize = 20;

/// One long stop with free road ahead ([`SessionStats::long_free_stop_ends`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LongStopEnd {
    /// The vehicle's agent slot (slots are reused: a trace's `entered` says by whom).
    pub agent: usize,
    /// The tick in which the stop ended, or the session's last (0-based).
    pub tick: usize,
    /// How long it stood, seconds.
    pub secs: f64,
    /// Whether it stood in a gridlock at some time in the stop.
    pub in_gridlock: bool,
    /// Where it stood at the end, metres.
    pub at_m: [f64; 2],
}

/// The counts of one session; feed it every tick ([`Self::tick`]) and every vehicle that
/// joins ([`Self::entered`]).
#[derive(Debug, Clone, Default, Serialize)]
pub struct SessionStats {
    pub ticks: usize,
    /// Present model-driven vehicles summed over ticks: vehicle-minutes are this / 600.
    pub vehicle_ticks: u64,
    /// A present vehicle going from on the road to off it (leaving the map's end is not one).
    pub off_road_events: u64,
    /// A pair of present vehicles starting to overlap.
    pub collision_events: u64,
    /// Stops with free road ahead that lasted [`LONG_STOP_SECS`] or more, and the longest.
    /// Free road: no vehicle's box in the vehicle's path and no centre ahead by the centre
    /// rule ([`crate::free_road::BlockedPaths`]); a vehicle in a gridlock (on a cycle of
    /// standing vehicles, each in the path of the one before) counts as stopped with free
    /// road too: nothing ahead of it will ever move.
    pub long_free_stops: u64,
    pub longest_free_stop_secs: f64,
    /// Vehicles whose heading turned more than [`LAP_TURN_RAD`] in all (net).
    pub ring_laps: u64,
    /// Ticks vehicles moved ([`MOVING_MIN_SPEED_MPS`] or faster), and of them those driven
    /// forwards against the lanes under them (a lanelet running more than 135° off the course
    /// and none within 90° of it: `road_planner::lane_guard::onto_an_opposing_lane`): the
    /// wrong way. Backing up a lane is not counted.
    pub moving_ticks: u64,
    pub wrong_way_ticks: u64,
    /// Of the long stops, those in a gridlock for one tick or more.
    pub long_gridlock_stops: u64,
    /// Ticks vehicles stood with free road ahead, by what held them that tick: the collision
    /// guard (braked or stopped short: a vehicle beside or crossing, not ahead), the lane
    /// guard at the road's edge, or neither (the model's own stop).
    pub free_stop_ticks_collision_guard: u64,
    pub free_stop_ticks_lane_guard: u64,
    pub free_stop_ticks_model: u64,
    pub entered: u64,
    pub left: u64,
    /// Of those that left, vehicles the stuck removal took out (`road_sched::StuckRemoval`).
    pub removed_stuck: u64,
    /// Present vehicles at every 10 s of the session (the first at tick 0).
    pub vehicles_every_10s: Vec<usize>,
    /// The first 100 long stops with free road ahead: which vehicle, where, and when each
    /// ended, to find it in a trace (`road eval --suite long --trace`).
    pub long_free_stop_ends: Vec<LongStopEnd>,
    /// Stands of [`LONG_STOP_SECS`] or more whatever was ahead (queued behind another vehicle
    /// too: the free-road count cannot see a queue behind a jam), the longest, and the
    /// vehicle-ticks spent in them.
    pub long_stands: u64,
    pub longest_stand_secs: f64,
    pub long_stand_ticks: u64,
    /// Stops with free road ahead or in a gridlock that lasted at least each of
    /// [`STOP_LENGTH_EDGES_TICKS`], and of them those in a gridlock. A stop of 10 s is rare
    /// (one in some 150 vehicle-minutes) and a rule that changes one vehicle's move reshapes the
    /// rest of its session, so a lever's effect on that count drowns in chance; the stops the
    /// releases (at 1 s in a gridlock, 3 s on free road) did not end within a few seconds are
    /// many times as many.
    pub free_stops_at_least: [u64; 4],
    pub gridlock_stops_at_least: [u64; 4],
    #[serde(skip)]
    present: Vec<bool>,
    #[serde(skip)]
    off: Vec<bool>,
    #[serde(skip)]
    last: Vec<Option<Pose>>,
    /// Each agent's positions over the last [`STANDING_WINDOW_TICKS`] ticks, oldest first.
    #[serde(skip)]
    recent: Vec<std::collections::VecDeque<glam::DVec2>>,
    #[serde(skip)]
    free_stop_ticks: Vec<u32>,
    /// Consecutive ticks each agent has stood, whatever was ahead.
    #[serde(skip)]
    stand_ticks: Vec<u32>,
    #[serde(skip)]
    gridlocked: Vec<bool>,
    /// Each agent's `[length, width]` (metres).
    #[serde(skip)]
    size_m: Vec<[f64; 2]>,
    #[serde(skip)]
    turned_rad: Vec<f64>,
    #[serde(skip)]
    lapped: Vec<bool>,
    #[serde(skip)]
    overlapping: BTreeSet<(usize, usize)>,
    /// Agents not counted (the ego, when there is one).
    #[serde(skip)]
    excluded: Vec<usize>,
}

impl SessionStats {
    /// A session whose agents of sizes `size_m` (`[length, width]`, metres) are present,
    /// `excluded` (an ego) not counted.
    pub fn new(size_m: &[[f64; 2]], excluded: &[usize]) -> Self {
        let mut s = Self {
            excluded: excluded.to_vec(),
            ..Self::default()
        };
        for (a, &size) in size_m.iter().enumerate() {
            s.entered_quietly(a, size);
        }
        s
    }

    fn grow(&mut self, agent: usize) {
        if agent >= self.present.len() {
            let n = agent + 1;
            self.present.resize(n, false);
            self.off.resize(n, false);
            self.last.resize(n, None);
            self.recent.resize(n, Default::default());
            self.free_stop_ticks.resize(n, 0);
            self.stand_ticks.resize(n, 0);
            self.gridlocked.resize(n, false);
            self.size_m.resize(n, [0.0; 2]);
            self.turned_rad.resize(n, 0.0);
            self.lapped.resize(n, false);
        }
    }

    fn entered_quietly(&mut self, agent: usize, size_m: [f64; 2]) {
        self.grow(agent);
        self.size_m[agent] = size_m;
        self.gridlocked[agent] = false;
        self.present[agent] = !self.excluded.contains(&agent);
        self.off[agent] = false;
        self.last[agent] = None;
        self.recent[agent].clear();
        self.free_stop_ticks[agent] = 0;
        self.stand_ticks[agent] = 0;
        self.turned_rad[agent] = 0.0;
        self.lapped[agent] = false;
        self.overlapping.retain(|&(i, j)| i != agent && j != agent);
    }

    /// A vehicle of `size_m` (`[length, width]`, metres) joined as agent `agent` (a new index
    /// or a retired one's).
    pub fn entered(&mut self, agent: usize, size_m: [f64; 2]) {
        self.entered += 1;
        self.entered_quietly(agent, size_m);
    }

    /// Present vehicles now.
    pub fn vehicles(&self) -> usize {
        self.present.iter().filter(|&&p| p).count()
    }

    /// One tick of the session on `map` (none: no wrong-way count).
    pub fn tick(&mut self, tick: &SceneTick, map: Option<&LaneletMap>) {
        if self.ticks.is_multiple_of(100) {
            let present = self.vehicles();
            self.vehicles_every_10s.push(present);
        }
        self.ticks += 1;
        for &a in &tick.stuck {
            self.grow(a);
            if self.present[a] {
                self.removed_stuck += 1;
            }
        }
        for &a in &tick.left {
            self.grow(a);
            if self.present[a] {
                self.left += 1;
                self.flush_stop(a);
                self.flush_stand(a);
            }
            self.present[a] = false;
        }
        self.grow(tick.poses.len().saturating_sub(1));
        let present: Vec<usize> = (0..tick.poses.len()).filter(|&a| self.present[a]).collect();
        self.vehicle_ticks += present.len() as u64;
        let off_now: BTreeSet<usize> = tick.off_road.iter().copied().collect();
        for &a in &present {
            let now = off_now.contains(&a);
            if now && !self.off[a] {
                self.off_road_events += 1;
            }
            self.off[a] = now;
        }
        let pairs: BTreeSet<(usize, usize)> = tick
            .collisions
            .iter()
            .copied()
            .filter(|&(i, j)| self.present[i] && self.present[j])
            .collect();
        self.collision_events += pairs.difference(&self.overlapping).count() as u64;
        self.overlapping = pairs;
        for &a in &present {
            let recent = &mut self.recent[a];
            if recent.len() == STANDING_WINDOW_TICKS + 1 {
                recent.pop_front();
            }
            recent.push_back(tick.poses[a].position_m());
        }
        let standing: Vec<bool> = (0..tick.poses.len())
            .map(|a| {
                let slow = |ticks: usize, from: glam::DVec2| {
                    (tick.poses[a].position_m() - from).length() / (ticks as f64 * STEP_SECS)
                        < STOPPED_MAX_SPEED_MPS
                };
                let recent = &self.recent[a];
                self.present[a]
                    && (self.last[a].is_some_and(|last| slow(1, last.position_m()))
                        || (recent.len() == STANDING_WINDOW_TICKS + 1
                            && slow(STANDING_WINDOW_TICKS, recent[0])))
            })
            .collect();
        let paths = BlockedPaths::new(&tick.poses, &self.size_m, &present);
        for &a in &present {
            let pose = tick.poses[a];
            if standing[a] {
                self.stand_ticks[a] += 1;
            } else {
                self.flush_stand(a);
            }
            if let Some(last) = self.last[a] {
                let step_m = pose.position_m() - last.position_m();
                if step_m.length() / STEP_SECS >= MOVING_MIN_SPEED_MPS {
                    self.moving_ticks += 1;
                    // Forwards only: backing off to make room (the releases) is no wrong way.
                    let forwards = step_m.dot(glam::DVec2::from_angle(pose.heading_rad)) > 0.0;
                    if forwards
                        && map.is_some_and(|m| {
                            onto_an_opposing_lane(m, pose.position_m(), step_m.normalize())
                        })
                    {
                        self.wrong_way_ticks += 1;
                    }
                }
                let turn = f64::from(road_data::wrap_angle(
                    (pose.heading_rad - last.heading_rad) as f32,
                ));
                // Net turning: weaving left and right cancels out, circling adds up.
                self.turned_rad[a] += turn;
                if self.turned_rad[a].abs() > LAP_TURN_RAD && !self.lapped[a] {
                    self.lapped[a] = true;
                    self.ring_laps += 1;
                }
                let gridlocked = paths.in_gridlock(a, &standing);
                if standing[a] && (paths.road_ahead_free(a) || gridlocked) {
                    self.free_stop_ticks[a] += 1;
                    self.gridlocked[a] |= gridlocked;
                    let held = |what: &[GuardAction]| {
                        tick.guarded
                            .iter()
                            .any(|(g, action)| *g == a && what.contains(action))
                    };
                    if held(&[GuardAction::StoppedAtRoadEdge]) {
                        self.free_stop_ticks_lane_guard += 1;
                    } else if held(&[GuardAction::Braked, GuardAction::StoppedShort]) {
                        self.free_stop_ticks_collision_guard += 1;
                    } else {
                        self.free_stop_ticks_model += 1;
                    }
                } else {
                    self.flush_stop(a);
                }
            }
            self.last[a] = Some(pose);
        }
    }

    fn flush_stop(&mut self, agent: usize) {
        let ticks = self.free_stop_ticks[agent];
        for (k, &edge) in STOP_LENGTH_EDGES_TICKS.iter().enumerate() {
            if ticks >= edge {
                self.free_stops_at_least[k] += 1;
                self.gridlock_stops_at_least[k] += u64::from(self.gridlocked[agent]);
            }
        }
        let secs = f64::from(ticks) * STEP_SECS;
        if secs >= LONG_STOP_SECS {
            self.long_free_stops += 1;
            self.long_gridlock_stops += u64::from(self.gridlocked[agent]);
            if let (Some(p), true) = (self.last[agent], self.long_free_stop_ends.len() < 100) {
                self.long_free_stop_ends.push(LongStopEnd {
                    agent,
                    // The tick under way (0-based, as a trace numbers them): the stop ended in it.
                    tick: self.ticks.saturating_sub(1),
                    secs,
                    in_gridlock: self.gridlocked[agent],
                    at_m: [p.x_m, p.y_m],
                });
            }
        }
        self.longest_free_stop_secs = self.longest_free_stop_secs.max(secs);
        self.free_stop_ticks[agent] = 0;
        self.gridlocked[agent] = false;
    }

    fn flush_stand(&mut self, agent: usize) {
        let ticks = self.stand_ticks[agent];
        let secs = f64::from(ticks) * STEP_SECS;
        if secs >= LONG_STOP_SECS {
            self.long_stands += 1;
            self.long_stand_ticks += u64::from(ticks);
        }
        self.longest_stand_secs = self.longest_stand_secs.max(secs);
        self.stand_ticks[agent] = 0;
    }

    /// Ends the session: stops still going count.
    pub fn finish(&mut self) {
        for a in 0..self.present.len() {
            if self.present[a] {
                self.flush_stop(a);
                self.flush_stand(a);
            }
        }
    }

    /// The share of vehicle time spent in stands of [`LONG_STOP_SECS`] or more (0 with no
    /// vehicle time).
    pub fn long_stand_share(&self) -> f64 {
        if self.vehicle_ticks == 0 {
            0.0
        } else {
            self.long_stand_ticks as f64 / self.vehicle_ticks as f64
        }
    }

    /// The share of moving ticks driven against the lanes (0 when none moved).
    pub fn wrong_way_share(&self) -> f64 {
        if self.moving_ticks == 0 {
            0.0
        } else {
            self.wrong_way_ticks as f64 / self.moving_ticks as f64
        }
    }

    pub fn vehicle_minutes(&self) -> f64 {
        self.vehicle_ticks as f64 * STEP_SECS / 60.0
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::{FRAC_PI_2, PI};

    use super::*;

    fn pose(x: f64, y: f64, heading: f64) -> Pose {
        Pose {
            x_m: x,
            y_m: y,
            heading_rad: heading,
        }
    }

    const CAR: [f64; 2] = [4.5, 1.8];

    fn tick(poses: Vec<Pose>) -> SceneTick {
        SceneTick {
            poses,
            ..SceneTick::default()
        }
    }

    #[test]
    fn a_vehicle_stopped_with_free_road_counts_and_one_queued_does_not() {
        // Vehicle 0 stands alone; vehicle 1 stands 8 m behind vehicle 2, which stands too.
        let mut stats = SessionStats::new(&[CAR; 3], &[]);
        for _ in 0..150 {
            stats.tick(
                &tick(vec![
                    pose(0.0, 50.0, 0.0),
                    pose(0.0, 0.0, 0.0),
                    pose(8.0, 0.0, 0.0),
                ]),
                None,
            );
        }
        stats.finish();
        // Vehicles 0 and 2 have free road (15 s each); 1 is queued.
        assert_eq!(stats.long_free_stops, 2);
        let ends: Vec<(usize, usize, [f64; 2])> = stats
            .long_free_stop_ends
            .iter()
            .map(|e| (e.agent, e.tick, e.at_m))
            .collect();
        assert_eq!(
            ends,
            vec![(0, 149, [0.0, 50.0]), (2, 149, [8.0, 0.0])],
            "ended with the session's last tick"
        );
        assert!(stats.long_free_stop_ends.iter().all(|e| !e.in_gridlock));
        assert_eq!(stats.free_stops_at_least, [2, 2, 2, 2]);
        assert_eq!(stats.gridlock_stops_at_least, [0; 4]);
        assert!((stats.longest_free_stop_secs - 14.9).abs() < 1e-9);
        // Every one of the three stood, the queued one too.
        assert_eq!(stats.long_stands, 3);
        assert!((stats.longest_stand_secs - 14.9).abs() < 1e-9);
        assert_eq!(stats.long_stand_ticks, 3 * 149);
        assert!((stats.long_stand_share() - 447.0 / 450.0).abs() < 1e-12);
        assert_eq!(stats.vehicle_ticks, 450);
        assert_eq!(stats.vehicles_every_10s, vec![3, 3]);
    }

    #[test]
    fn a_vehicle_rocking_in_place_stands_and_one_creeping_on_does_not() {
        // Vehicle 0 moves 0.1 m forwards and back in turn (1 m/s every tick) for 15 s, alone:
        // on average it stands. Vehicle 1, far off, creeps on at 0.5 m/s: it drives.
        let mut stats = SessionStats::new(&[CAR; 2], &[]);
        for k in 0..150 {
            stats.tick(
                &tick(vec![
                    pose(0.1 * f64::from(k % 2), 0.0, 0.0),
                    pose(0.05 * f64::from(k), 100.0, 0.0),
                ]),
                None,
            );
        }
        stats.finish();
        assert_eq!(stats.long_free_stops, 1);
        // From the window's first full 2 s on.
        assert!(
            (stats.longest_free_stop_secs - 13.0).abs() < 1e-9,
            "{}",
            stats.longest_free_stop_secs
        );
    }

    #[test]
    fn a_vehicle_behind_a_tail_across_its_path_is_queued_and_a_gridlock_counts() {
        // Vehicle 0 stands behind vehicle 1's tail (1 turned away across 0's path, its
        // centre 3.3 m off 0's axis): queued. Vehicle 1 has free road: it counts.
        let behind_a_tail = vec![pose(0.0, 0.0, 0.0), pose(3.0, -3.3, -FRAC_PI_2)];
        let mut stats = SessionStats::new(&[CAR; 2], &[]);
        for _ in 0..150 {
            stats.tick(&tick(behind_a_tail.clone()), None);
        }
        stats.finish();
        assert_eq!((stats.long_free_stops, stats.long_gridlock_stops), (1, 0));
        // Four vehicles round a 6 m square, each nose at the next one's flank, stand 15 s:
        // none has free road, all four are in a gridlock and count.
        let square = vec![
            pose(0.0, 0.0, 0.0),
            pose(6.0, 0.0, FRAC_PI_2),
            pose(6.0, 6.0, PI),
            pose(0.0, 6.0, -FRAC_PI_2),
        ];
        let mut stats = SessionStats::new(&[CAR; 4], &[]);
        for _ in 0..150 {
            stats.tick(&tick(square.clone()), None);
        }
        stats.finish();
        assert_eq!((stats.long_free_stops, stats.long_gridlock_stops), (4, 4));
        assert!(stats.long_free_stop_ends.iter().all(|e| e.in_gridlock));
        assert_eq!(stats.gridlock_stops_at_least, [4; 4]);
    }

    #[test]
    fn shorter_stops_count_by_length() {
        // Vehicle 0 stands alone for 60 ticks, then drives off at 5 m/s; vehicle 1 stands 40
        // ticks, drives 20, then stands to the end (80 ticks).
        let mut stats = SessionStats::new(&[CAR; 2], &[]);
        for k in 0..140 {
            let x0 = 0.5 * f64::from(k.max(60) - 60);
            let x1 = 0.5 * f64::from(k.clamp(40, 60) - 40);
            stats.tick(&tick(vec![pose(x0, 0.0, 0.0), pose(x1, 100.0, 0.0)]), None);
        }
        stats.finish();
        // The first tick has nothing to stand against: 0 stood 60 ticks, 1 stood 40, then 79.
        assert_eq!(stats.free_stops_at_least, [3, 2, 1, 0]);
        assert_eq!(stats.gridlock_stops_at_least, [0; 4]);
        assert_eq!(stats.long_free_stops, 0);
    }

    #[test]
    fn events_count_once_and_left_vehicles_stop_counting() {
        let mut stats = SessionStats::new(&[CAR; 2], &[]);
        let mut t = tick(vec![pose(0.0, 0.0, 0.0), pose(2.0, 0.0, 0.0)]);
        t.collisions = vec![(0, 1)];
        t.off_road = vec![1];
        stats.tick(&t, None);
        stats.tick(&t, None);
        assert_eq!((stats.collision_events, stats.off_road_events), (1, 1));
        let mut gone = tick(vec![pose(0.0, 0.0, 0.0), pose(2.0, 0.0, 0.0)]);
        gone.left = vec![1];
        stats.tick(&gone, None);
        assert_eq!((stats.left, stats.removed_stuck), (1, 0));
        assert_eq!(stats.vehicles(), 1);
        stats.entered(1, CAR);
        assert_eq!((stats.entered, stats.vehicles()), (1, 2));
        // Taken out stuck: it leaves, and counts as removed once.
        let mut removed = tick(vec![pose(0.0, 0.0, 0.0), pose(2.0, 0.0, 0.0)]);
        removed.left = vec![1];
        removed.stuck = vec![1];
        stats.tick(&removed, None);
        stats.tick(&removed, None);
        assert_eq!((stats.left, stats.removed_stuck), (2, 1));
        assert_eq!(stats.vehicles(), 1);
    }

    #[test]
    fn a_vehicle_that_keeps_circling_has_lapped() {
        let mut stats = SessionStats::new(&[CAR], &[]);
        for k in 0..200 {
            let angle = f64::from(k) * 0.05;
            stats.tick(
                &tick(vec![pose(
                    20.0 * angle.cos(),
                    20.0 * angle.sin(),
                    angle + std::f64::consts::FRAC_PI_2,
                )]),
                None,
            );
        }
        // 10 rad turned: more than 1¼ turns, once.
        assert_eq!(stats.ring_laps, 1);
    }

    #[test]
    fn a_vehicle_moving_against_its_lane_counts_as_wrong_way() {
        // One eastbound lanelet, 100 m × 4 m; vehicle 0 drives east, vehicle 1 west on it,
        // vehicle 2 backs west facing east.
        let left: Vec<road_data::geometry::Point> = vec![[0.0, 2.0], [100.0, 2.0]];
        let right: Vec<road_data::geometry::Point> = vec![[0.0, -2.0], [100.0, -2.0]];
        let map = LaneletMap {
            location: "straight".into(),
            lanelets: vec![road_data::map::Lanelet {
                id: 1,
                subtype: Some("road".into()),
                left_way: 2,
                right_way: 3,
                bounds: road_data::geometry::Aabb::of(&[left.clone(), right.clone()].concat()),
                centre_m: vec![[0.0, 0.0], [50.0, 0.0], [100.0, 0.0]],
                left_m: left,
                right_m: right,
                successors: Vec::new(),
                neighbours: Vec::new(),
            }],
            skipped: Default::default(),
            priority_rules: Vec::new(),
        };
        let mut stats = SessionStats::new(&[CAR; 3], &[]);
        for k in 0..10 {
            let x = 1.0 * f64::from(k); // 10 m/s
            stats.tick(
                &tick(vec![
                    pose(20.0 + x, 0.0, 0.0),
                    pose(80.0 - x, 0.0, PI),
                    pose(50.0 - x, 0.0, 0.0),
                ]),
                Some(&map),
            );
        }
        // 9 moving ticks each (the first has no course yet), vehicle 1's against the lane.
        assert_eq!(stats.moving_ticks, 27);
        assert_eq!(stats.wrong_way_ticks, 9);
        assert!((stats.wrong_way_share() - 1.0 / 3.0).abs() < 1e-12);
    }
}
