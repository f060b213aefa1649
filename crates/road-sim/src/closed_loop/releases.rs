//! The closed loop's releases: the stall release ([`StallRelease`]) pulls away vehicles that
//! stand with free road ahead; the collision guard's plumbing with its deadlock release
//! (`CollisionGuard::release_deadlock_after_secs`) lets a vehicle held too long stop braking for
//! other model-driven vehicles, and one stuck against a lower-numbered held vehicle back off.

use glam::DVec2;
use road_data::{LaneletMap, wrap_angle};
use road_planner::collision_guard::{GuardAction, GuardAgent, guard_step, keeps_clear};
use road_planner::lane_guard::{across_every_lane, leaves_through_an_open_end};
use road_sched::{CollisionGuard, StallRelease, StuckRemoval};

use super::{Controller, STEP_SECS, SceneRuntime, set_emitted};
use crate::Pose;
use crate::free_road::BlockedPaths;
use crate::geometry::OrientedBox;
use crate::session::STANDING_WINDOW_TICKS;

/// What the stall release ([`StallRelease`]) and the collision guard's deadlock release
/// (`CollisionGuard::release_deadlock_after_secs`) remember of one agent.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct HeldMemory {
    /// Ticks stood still with free road ahead.
    pub(super) stalled_ticks: u32,
    /// Whether the stall release is pulling it away.
    pub(super) pulling_away: bool,
    /// Whether that pull-away has the way out of a gridlock (it goes on with vehicles ahead).
    pub(super) pulling_out_of_gridlock: bool,
    /// Consecutive ticks it stood while it had the way out of a gridlock.
    pub(super) stood_with_way_ticks: u32,
    /// Ticks left in which it has passed a gridlock's way on ([`HeldMemory::passes_way_on`]).
    pub(super) passes_way_ticks: u32,
    /// The way the stall release turns it (+1 counter-clockwise, −1 clockwise; 0 before it
    /// has turned), kept while it manoeuvres in place ([`held_turn`]).
    pub(super) turn_sign: i8,
    /// How far the stall release has backed it in its current run of backward moves, metres (0
    /// when its last move was not one): it backs on for [`BACK_AND_FILL_M`] before filling.
    pub(super) backed_m: f64,
    /// Whether the stall release moved it this tick at manoeuvring speed (backing and filling,
    /// turning in place, or starting off straight below [`RELEASE_STRAIGHT_BELOW_MPS`]): the
    /// collision guard then holds it by the no-overlap rule alone, as it does a vehicle
    /// breaking a deadlock ([`manoeuvres_unanticipated`]).
    pub(super) manoeuvred: bool,
    /// Whether the stall release found no move for it this tick (every one off the road or into
    /// a neighbour): asked, it makes room as a standing vehicle does ([`SceneRuntime::make_room`]).
    pub(super) wedged: bool,
    /// Consecutive ticks the collision guard braked it or stopped it short.
    pub(super) guard_held_ticks: u32,
    /// Ticks left in which it does not brake for other model-driven agents (it breaks a
    /// deadlock).
    pub(super) breaking_deadlock_ticks: u32,
    /// Consecutive ticks the collision guard held it (braked or stopped short), for backing off.
    pub(super) held_streak_ticks: u32,
    /// Ticks left in which it backs off (it gives way in a deadlock, or makes room).
    pub(super) backing_off_ticks: u32,
    /// The way it moves off: −1 backwards, +1 forwards (it makes room for a vehicle behind
    /// it); 0 reads as backwards.
    pub(super) backing_off_sign: i8,
    /// Ticks stood, since it last moved, in which a guard or release acted on it (the stuck
    /// removal's count).
    pub(super) stuck_ticks: u32,
    /// Ticks in a row it stood, a guard or release acting on it, pointing across or against
    /// every lanelet under it (`StuckRemoval::disoriented_after_secs`).
    pub(super) disoriented_ticks: u32,
    /// Where it has stayed within [`STILL_RADIUS_M`] of, and for how many ticks: a vehicle
    /// rocked back and forth in place moves every tick yet stands.
    pub(super) still_at_m: DVec2,
    pub(super) still_ticks: u32,
    /// While the stall release pulls it away: where it has stayed within
    /// [`MANOEUVRE_RADIUS_M`] of, and for how many ticks (backing and filling that gets
    /// nowhere).
    pub(super) manoeuvring_at_m: DVec2,
    pub(super) manoeuvring_ticks: u32,
    /// Where it was at each of its last [`STANDING_WINDOW_TICKS`] + 1 ticks (a ring, oldest
    /// at `recent_next` once full), for the long suite's notion of standing on average.
    pub(super) recent_m: [DVec2; STANDING_WINDOW_TICKS + 1],
    /// Its heading (radians, unwrapped) at the same ticks as `recent_m`.
    pub(super) recent_heading_rad: [f64; STANDING_WINDOW_TICKS + 1],
    /// How many of `recent_m` are filled, and where the next goes.
    pub(super) recent_len: usize,
    pub(super) recent_next: usize,
    /// Whether the give-way rule held it at its stop line in the last tick.
    pub(super) giving_way: bool,
    /// Whether the give-way rule held it short of its stop line, at any distance, in the last
    /// tick (braking for it: it can stop there).
    pub(super) braking_for_line: bool,
    /// Ticks stood at an all-way stop's line (its place in the order of arrival).
    pub(super) waiting_ticks: u32,
    /// The rule and yield lanelet the give-way rule let it go from, until it has left the
    /// junction.
    pub(super) gone_from: Option<(u32, u32)>,
}

impl HeldMemory {
    /// Records where it is after a tick, and its heading (unwrapped) in [`Self::recent_m`].
    fn record(&mut self, at: DVec2, heading_rad: f64) {
        let window = self.recent_m.len();
        self.recent_m[self.recent_next] = at;
        self.recent_heading_rad[self.recent_next] = heading_rad;
        self.recent_next = (self.recent_next + 1) % window;
        self.recent_len = (self.recent_len + 1).min(window);
    }

    /// How far it turned (radians) over its last `ticks` recorded (at most
    /// [`STANDING_WINDOW_TICKS`]; over fewer while fewer are known).
    fn turned_over_rad(&self, ticks: usize) -> f64 {
        let window = self.recent_heading_rad.len();
        let back = ticks.min(window - 1).min(self.recent_len.saturating_sub(1));
        let newest = (self.recent_next + window - 1) % window;
        let then = (newest + window - back) % window;
        self.recent_heading_rad[newest] - self.recent_heading_rad[then]
    }

    /// With a gridlock's way, after a tick in which it `stands` (or not): whether it passes the
    /// way on now, having stood [`WAY_PASSES_AFTER_SECS`] in a row with it. Its pull-away then
    /// ends, and for [`WAY_PASSED_FOR_SECS`] the way goes to another
    /// ([`way_out_of_gridlock`]). Out of the gridlock too: kept while wedged elsewhere, a
    /// vehicle's pull-away backed and filled it behind a queue for 29 s, towards the vehicle
    /// that was backing off for the gridlock's new holder, and was never asked to make room
    /// (issue 39).
    fn passes_way_on(&mut self, stands: bool) -> bool {
        self.stood_with_way_ticks = if stands {
            self.stood_with_way_ticks + 1
        } else {
            0
        };
        let after_ticks = (WAY_PASSES_AFTER_SECS / STEP_SECS).round() as u32;
        if self.stood_with_way_ticks < after_ticks {
            return false;
        }
        self.end_pull_away();
        self.passes_way_ticks = (WAY_PASSED_FOR_SECS / STEP_SECS).round() as u32;
        true
    }

    /// It is no longer pulled away: the stall release starts over.
    fn end_pull_away(&mut self) {
        self.stalled_ticks = 0;
        self.pulling_away = false;
        self.pulling_out_of_gridlock = false;
        self.stood_with_way_ticks = 0;
        self.turn_sign = 0;
        self.backed_m = 0.0;
        self.wedged = false;
    }
}

/// A vehicle that stays within this of one place (metres) for [`STILL_TICKS`] stands,
/// however it moves in between: `road_sim::session`'s count found vehicles the releases rocked
/// back and forth in place for up to 451 s, every tick faster than
/// `free_road::STOPPED_MAX_SPEED_MPS` and so never stuck, never in a gridlock (issue 39).
pub(super) const STILL_RADIUS_M: f64 = 0.6;
/// Ticks (2 s) within [`STILL_RADIUS_M`] of one place that make a vehicle stand.
pub(super) const STILL_TICKS: u32 = 20;
/// A vehicle the stall release pulls away that stays within this of one place (metres: a
/// back-and-fill leg, [`BACK_AND_FILL_M`], and a half metre) for [`MANOEUVRING_STILL_TICKS`]
/// stands too: wedged behind a tail that stuck into its lane, a gridlock's holder backed and
/// filled over 1.7 m for 16 s, never standing by [`STILL_RADIUS_M`], and so never passed the
/// way on to the vehicle that could go (issue 39).
const MANOEUVRE_RADIUS_M: f64 = BACK_AND_FILL_M + 0.5;
/// Ticks (4 s) within [`MANOEUVRE_RADIUS_M`] that make a vehicle pulled away stand.
const MANOEUVRING_STILL_TICKS: u32 = 40;

impl SceneRuntime<'_> {
    /// Whether agent `a` stands: slower than `STOPPED_MAX_SPEED_MPS` over the last tick, or on
    /// average over the last [`STANDING_WINDOW_TICKS`] (as the long suite counts a stand), or
    /// within [`STILL_RADIUS_M`] of one place for [`STILL_TICKS`], or pulled away within
    /// [`MANOEUVRE_RADIUS_M`] for [`MANOEUVRING_STILL_TICKS`]. Without the average, a
    /// vehicle the model crawled on at about 0.3 m/s, some ticks faster, never stood for the
    /// stall release's 3 s, and stood 10 s by the suite's count (issue 39).
    pub(super) fn stands(&self, a: usize) -> bool {
        let memory = &self.held[a];
        let slow_on_average = memory.recent_len == memory.recent_m.len() && {
            let oldest = memory.recent_m[memory.recent_next];
            let now = self.poses[a].position_m();
            now.distance(oldest) / (STANDING_WINDOW_TICKS as f64 * STEP_SECS)
                < crate::free_road::STOPPED_MAX_SPEED_MPS
        };
        self.speed_mps[a] < crate::free_road::STOPPED_MAX_SPEED_MPS
            || slow_on_average
            || memory.still_ticks >= STILL_TICKS
            || memory.manoeuvring_ticks >= MANOEUVRING_STILL_TICKS
    }

    /// Follows where each agent stays ([`HeldMemory::still_at_m`]) and where it was
    /// ([`HeldMemory::recent_m`]), after the tick's poses.
    pub(super) fn track_still(&mut self) {
        for ((memory, pose), &heading_rad) in self
            .held
            .iter_mut()
            .zip(&self.poses)
            .zip(&self.heading_unwrapped)
        {
            let at = pose.position_m();
            memory.record(at, heading_rad);
            if at.distance(memory.still_at_m) <= STILL_RADIUS_M {
                memory.still_ticks += 1;
            } else {
                memory.still_at_m = at;
                memory.still_ticks = 0;
            }
            if memory.pulling_away && at.distance(memory.manoeuvring_at_m) <= MANOEUVRE_RADIUS_M {
                memory.manoeuvring_ticks += 1;
            } else {
                memory.manoeuvring_at_m = at;
                memory.manoeuvring_ticks = 0;
            }
        }
    }

    /// The stuck removal ([`StuckRemoval`]), after the tick's poses are set: model-driven
    /// vehicles that stood stuck for its time, no client-driven agent near, leave the scene
    /// (retired, in `left` and `stuck`). Stuck: standing with free road ahead
    /// ([`crate::free_road`]) or in a gridlock while a guard or release acts on it, or standing
    /// whatever is ahead while a release moves it (pulled away or backing off); vehicles the
    /// model keeps queued behind another never count (counting every standing tick a guard
    /// acted on, a first version took 108 vehicles out of queues in 1 847 vehicle-minutes).
    /// Standing across or against every lanelet under it while a guard or release acts on it,
    /// whatever is ahead, it leaves after `disoriented_after_secs` of such ticks in a row.
    pub(super) fn remove_stuck(&mut self, removal: StuckRemoval) {
        let after_ticks = (removal.after_secs / STEP_SECS).round() as u32;
        let disoriented_after_ticks = removal
            .disoriented_after_secs
            .map(|secs| (secs / STEP_SECS).round() as u32);
        let present: Vec<usize> = (0..self.controllers.len())
            .filter(|&b| !self.retired[b])
            .collect();
        let (paths, standing) = self.blocked_paths(&present);
        let externals: Vec<DVec2> = present
            .iter()
            .filter(|&&b| self.controllers[b] == Controller::External)
            .map(|&b| self.poses[b].position_m())
            .collect();
        for &a in &present {
            if self.controllers[a] != Controller::Model {
                continue;
            }
            if !self.stands(a) {
                self.held[a].stuck_ticks = 0;
                self.held[a].disoriented_ticks = 0;
                continue;
            }
            // A release's own move that left it standing (pulled away or backing off, wedged
            // where it stands) counts whatever is ahead: a vehicle asked to back off against
            // the road's edge, another at its nose, stood 229 s in MA's box (issue 39).
            let released_in_vain = self.guarded.iter().any(|&(b, action)| {
                b == a && matches!(action, GuardAction::PulledAway | GuardAction::BackedOff)
            });
            let acted_on = self.guarded.iter().any(|&(b, _)| b == a);
            if acted_on
                && !self.held[a].giving_way
                && (paths.centre_rule_free(a)
                    || paths.in_gridlock(a, &standing)
                    || released_in_vain)
            {
                self.held[a].stuck_ticks += 1;
            }
            let at = self.poses[a].position_m();
            let disoriented = disoriented_after_ticks.is_some()
                && acted_on
                && self.map.as_ref().is_some_and(|m| {
                    let facing = DVec2::from_angle(self.heading_unwrapped[a]);
                    across_every_lane(m.get(), at, facing, DISORIENTED_MIN_RAD)
                });
            let memory = &mut self.held[a];
            memory.disoriented_ticks = if disoriented {
                memory.disoriented_ticks + 1
            } else {
                0
            };
            let disoriented_long =
                disoriented_after_ticks.is_some_and(|ticks| memory.disoriented_ticks >= ticks);
            let ego_near = externals
                .iter()
                .any(|e| e.distance(at) <= removal.clear_of_external_m);
            if (memory.stuck_ticks >= after_ticks || disoriented_long) && !ego_near {
                self.retired[a] = true;
                self.left.push(a);
                self.stuck.push(a);
            }
        }
    }

    /// The stall release ([`StallRelease`]): model-driven agents that stood still with free
    /// road ahead for its time pull away along their heading; their emitted states change.
    pub(super) fn release_stalls(
        &mut self,
        emitted: &mut [f32],
        heading_scale: f64,
        release: StallRelease,
    ) {
        let frame = &self.window.frame;
        let present: Vec<usize> = (0..self.controllers.len())
            .filter(|&a| !self.retired[a])
            .collect();
        let after_ticks = (release.after_secs / STEP_SECS).round() as u32;
        for memory in &mut self.held {
            memory.manoeuvred = false;
        }
        let (paths, standing) = self.blocked_paths(&present);
        // (asking, asked, again): `again`, asked by a wedged vehicle with the release's
        // `make_room_again`, also while giving way.
        let mut make_room = Vec::new();
        for &a in &present {
            if self.controllers[a] != Controller::Model || self.overrides[a].is_some() {
                continue;
            }
            let before = self.poses[a];
            let proposed = DVec2::from(frame.to_metres([emitted[3 * a], emitted[3 * a + 1]]));
            let model_speed = (proposed - before.position_m()).length() / STEP_SECS;
            // A gridlock (standing vehicles each in the path of the one before, round to the
            // first: two nose to nose, four round a crossing) has no free road anywhere, and
            // stood for minutes in issue 39's long sessions: of the vehicles that lock it
            // (`gridlock_core`), the lowest-numbered has the way and is pulled away as from a
            // stall, those in its way asked to make room (backing, one far off its lane turns
            // towards it: `backing_off_to`). Where that is an agent the model does
            // not drive (an ego, a scripted vehicle), or has one in its path, the gridlock is
            // left to that agent's driver: no model vehicle is pulled towards a client's. One
            // that stood `WAY_PASSES_AFTER_SECS` with the way passes it on to the next
            // (`way_out_of_gridlock`).
            self.held[a].passes_way_ticks = self.held[a].passes_way_ticks.saturating_sub(1);
            let gridlock = paths.gridlock(a, &standing);
            let core = gridlock_core(&gridlock, |b| self.nearest_in_path(&paths, b));
            let has_way_out_of_gridlock = self.held[a].pulling_out_of_gridlock
                || (way_out_of_gridlock(&core, &self.held) == Some(a)
                    && paths
                        .in_path(a)
                        .iter()
                        .all(|&b| self.controllers[b] == Controller::Model));
            // Waiting at a stop line for its way (the give-way rule) is no stall; a gridlock
            // it has the way out of is undone all the same, and so is a stand beside a vehicle
            // that waits for it ([`BlockedPaths::free_but_for_those_waiting`]).
            if (!paths.free_but_for_those_waiting(a, &standing) || self.held[a].giving_way)
                && !has_way_out_of_gridlock
            {
                self.held[a].end_pull_away();
                continue;
            }
            let map = self.map.as_ref().map(|m| m.get());
            let on_road = |p: DVec2| map.is_none_or(|m| m.lanelet_at(p.into()).is_some());
            // On the road, or out of the map through an open lane end (where it is retired): a
            // vehicle the model stopped at the map's end stood there for 38 s, every move of
            // the release refused as off the road (issue 39).
            let stays_or_exits = |to: DVec2| {
                on_road(to)
                    || map.is_some_and(|m| leaves_through_an_open_end(m, before.position_m(), to))
            };
            if !self.held[a].pulling_away {
                // Stood over the last tick, whatever the model asks: a model that drove a
                // vehicle at the road's edge off it every few ticks, each step stopped there
                // by the lane guard, restarted its release's count each time, and it stood for
                // 10 s and more (issue 39).
                // Crawling at the map's open end counts too: the model sees no lane past it
                // and crawled vehicles over the merge's last 10 m for 10–15 s, mostly faster
                // than a stand (issue 39).
                let ahead = before.position_m()
                    + DVec2::from_angle(self.heading_unwrapped[a]) * OPEN_END_AHEAD_M;
                let crawling_at_open_end = self.speed_mps[a] < CRAWL_MAX_SPEED_MPS
                    && map.is_some_and(|m| {
                        !on_road(ahead) && leaves_through_an_open_end(m, before.position_m(), ahead)
                    });
                let still = self.stands(a) || crawling_at_open_end;
                self.held[a].stalled_ticks = if still {
                    self.held[a].stalled_ticks + 1
                } else {
                    0
                };
                let wait_ticks = match release.gridlock_after_secs {
                    Some(secs) if has_way_out_of_gridlock => (secs / STEP_SECS).round() as u32,
                    _ => after_ticks,
                };
                if self.held[a].stalled_ticks < wait_ticks {
                    continue;
                }
                self.held[a].pulling_away = true;
                self.held[a].pulling_out_of_gridlock = has_way_out_of_gridlock;
            } else if has_way_out_of_gridlock {
                // Pulled away from a stall, then closed in by a gridlock (a vehicle stopped
                // across its nose, each in the other's path), it has the way out as any: it
                // braked for that vehicle every tick, crept 0.5 m in 14 s in MA's box, and
                // nobody was asked to make room (issue 39).
                self.held[a].pulling_out_of_gridlock = true;
            }
            if self.held[a].pulling_out_of_gridlock {
                // Standing on with the way, it passes the way on: the one it asks to make room
                // may have none (nose to nose, that one across the centre line against the
                // kerb, it stood 10–30 s in issue 39's long sessions), and the next may have it.
                let stands = self.stands(a);
                if self.held[a].passes_way_on(stands) {
                    continue;
                }
                // Those standing in its path make room (moving away from it), whether or not
                // its next step is blocked yet: the collision guard brakes it short of them.
                make_room.extend(
                    paths
                        .in_path(a)
                        .iter()
                        .filter(|&&b| standing[b])
                        .map(|&b| (a, b, false)),
                );
            }
            let speed = (self.speed_mps[a] + release.acceleration_mps2 * STEP_SECS)
                .min(release.release_speed_mps);
            // The model drives it on again once it moves at least as fast the same way (within
            // 30°), stays on the road and keeps clear of everyone as they stand: a model step
            // off the road would only be stopped at the edge again, and one into a neighbour
            // cut short by the collision guard (a vehicle pinned 1 cm from two others in an
            // intersection took the model's step back every 3 s, each cut to nothing, and stood
            // 20 s: issue 39).
            let model_step = proposed - before.position_m();
            let same_way = model_step
                .normalize_or_zero()
                .dot(DVec2::from_angle(self.heading_unwrapped[a]))
                >= 30f64.to_radians().cos();
            let model_heading = f64::from(emitted[3 * a + 2]) / heading_scale;
            // Only with its heading steady over the model's observed second: handed back in
            // the middle of the release's turn, the model carried the turn on, round into a
            // loop across FT's wide lanelet, and left the vehicle at the road's edge against
            // its lane, where jams formed round it (issue 39).
            let steady = self.held[a].turned_over_rad(HAND_BACK_STEADY_TICKS).abs()
                <= HAND_BACK_MAX_TURN_RAD;
            if steady
                && ((model_speed >= hand_back_speed_mps(speed, &release)
                    && same_way
                    && stays_or_exits(proposed)
                    && self
                        .blockers_of(a, proposed, model_heading, heading_scale)
                        .is_empty())
                    || self.speed_mps[a] >= release.release_speed_mps)
            {
                self.held[a].end_pull_away();
                continue;
            }
            // Along its heading, turned towards a point up to 6 m ahead on its lane
            // (`release_target`): a vehicle held at the road's edge gets back. It turns about its
            // rear axle no tighter than `RELEASE_TURN_RADIUS_M`, as a car does, and drives
            // straight on at first (turned from standstill, its tail swung into a neighbour
            // beside it and the collision guard held it there). Where that step would leave the
            // road (a vehicle at the edge, pointing off it) or run into a neighbour, it backs and
            // fills at full lock (`MANOEUVRE_SPEED_MPS`), forwards or else backwards, and only
            // where neither fits turns in place, by up to `RELEASE_TURN_IN_PLACE_RAD` a tick.
            // Every move it makes stays on the road and passes the collision guard's rule
            // against the others as they stand. A vehicle off the road turns in place towards
            // its lane until it points within 30° of it, then drives there; with no lane within
            // 10 m it is left where it stands.
            let heading_before = self.heading_unwrapped[a];
            let target = map.and_then(|m| release_target(m, before.position_m(), heading_before));
            let raw_turn = target.map_or(0.0, |target| {
                let wanted = (target - before.position_m()).to_angle();
                f64::from(wrap_angle((wanted - heading_before) as f32))
            });
            // Manoeuvring in place it keeps turning the same way: the lane point it turns
            // towards depends on its heading (two lanes running opposite ways, or one curving
            // lane's segments each on either side of 90° off it), and vehicles turned back and
            // forth between two such points for minutes (issue 39).
            let (turn, turn_sign) = held_turn(raw_turn, self.held[a].turn_sign);
            self.held[a].turn_sign = turn_sign;
            let spin = (
                before.position_m(),
                heading_before + turn.clamp(-RELEASE_TURN_IN_PLACE_RAD, RELEASE_TURN_IN_PLACE_RAD),
            );
            // About the rear axle, `distance_m` along the heading (negative: backwards), the
            // nose turned towards the target by at most `max_turn_rad`.
            let rear_axle_m = REAR_AXLE_SHARE_OF_LENGTH * f64::from(self.window.length_m[a]);
            let arc = |distance_m: f64, max_turn_rad: f64| {
                arc_about_rear_axle(
                    (before.position_m(), heading_before),
                    rear_axle_m,
                    distance_m,
                    turn.clamp(-max_turn_rad, max_turn_rad),
                )
            };
            let drive = || {
                let max_turn = if speed < RELEASE_STRAIGHT_BELOW_MPS {
                    0.0
                } else {
                    speed * STEP_SECS / RELEASE_TURN_RADIUS_M
                };
                arc(speed * STEP_SECS, max_turn)
            };
            // Backing and filling: at full lock, forwards or backwards (the nose turns towards
            // the target either way).
            let manoeuvre_m = MANOEUVRE_SPEED_MPS * STEP_SECS;
            let full_lock = manoeuvre_m / RELEASE_TURN_RADIUS_M;
            // Where the plain pull-away is blocked (off the road ahead, or a neighbour in the
            // way: issue 39's long stops were mostly a vehicle at the kerb whose turn in place
            // swung its tail into the nose of one behind it), it backs and fills.
            let (forward, backward) = (arc(manoeuvre_m, full_lock), arc(-manoeuvre_m, full_lock));
            let driving = drive();
            let (moves, on_road_too) = if on_road(before.position_m()) {
                // Once backing it backs on for `BACK_AND_FILL_M` where it can, as a driver in
                // a three-point turn does: choosing forwards first every tick, a vehicle at the
                // road's edge went 10 cm back and 10 cm forth each tick for minutes (issue 39).
                let backed_m = self.held[a].backed_m;
                let backing_on = backed_m > 0.0 && backed_m < BACK_AND_FILL_M;
                let moves = if backing_on {
                    vec![backward, driving, forward, spin]
                } else {
                    vec![driving, forward, backward, spin]
                };
                (moves, true)
            } else if target.is_none() {
                self.held[a].end_pull_away();
                continue;
            } else if turn.abs() > 30f64.to_radians() {
                (vec![spin], false)
            } else {
                (vec![driving], false)
            };
            // The first move on the road (where asked) that the collision guard will let through
            // against everyone standing as they are.
            let allowed = |m: &&(DVec2, f64)| !on_road_too || stays_or_exits(m.0);
            // A turn in place by nothing is no move: taken as one, a vehicle whose every other
            // move was blocked asked nobody to make room (issue 39).
            let moves_it = |m: &&(DVec2, f64)| {
                m.0.distance(before.position_m()) > 1e-6 || (m.1 - heading_before).abs() > 1e-6
            };
            let chosen = moves
                .iter()
                .filter(allowed)
                .filter(moves_it)
                .find(|&&(to, heading)| self.blockers_of(a, to, heading, heading_scale).is_empty())
                .copied();
            if chosen.is_none() {
                // Wedged: those standing in the way of its moves make room.
                for &(to, heading) in moves.iter().filter(allowed).filter(moves_it) {
                    make_room.extend(
                        self.blockers_of(a, to, heading, heading_scale)
                            .into_iter()
                            .map(|b| (a, b, release.make_room_again)),
                    );
                }
            }
            // Driving on, it turns as its lane does (it keeps its way only manoeuvring in
            // place, where its heading alone moves the lane point).
            if chosen == Some(driving) {
                self.held[a].turn_sign = 0;
            }
            self.held[a].backed_m = if chosen == Some(backward) {
                self.held[a].backed_m + manoeuvre_m
            } else {
                0.0
            };
            self.held[a].manoeuvred = manoeuvres_unanticipated(chosen, driving, speed);
            self.held[a].wedged = chosen.is_none();
            // Nothing feasible: it stands this tick, as the guard would have held it.
            let (to, heading) = chosen.unwrap_or((before.position_m(), heading_before));
            set_emitted(emitted, a, frame, to, heading, heading_scale);
            self.guarded.push((a, GuardAction::PulledAway));
        }
        self.make_room(&make_room, true);
    }

    /// The vehicle in agent `a`'s path ([`BlockedPaths::in_path`]) whose centre lies nearest
    /// its own.
    fn nearest_in_path(&self, paths: &BlockedPaths, a: usize) -> Option<usize> {
        let at = self.poses[a].position_m();
        paths.in_path(a).iter().copied().min_by(|&b, &c| {
            let from = |x: usize| self.poses[x].position_m().distance(at);
            from(b).total_cmp(&from(c))
        })
    }

    /// Where agent `a` backing off `distance_m` (at most [`BACK_OFF_SPEED_MPS`]'s step) ends,
    /// and its heading there. By preference ([`Self::preferred_back_off`]) straight back, or,
    /// pointing [`STEERED_BACK_OFF_MIN_RAD`] or more off its lane, turning towards it; where
    /// that step leaves the road or runs into a vehicle as they stand, straight back or at
    /// either full lock, the first that does neither ([`Self::back_off_steps`]); the preferred
    /// one where none is free (the guards then hold it). Backing its one way only, a vehicle
    /// nose to nose with one at a median's tip, asked to make room again and again, was stopped
    /// short by the collision guard within a step or two each time, and the pair stood 29 s
    /// (issue 39).
    fn backing_off_to(&self, a: usize, distance_m: f64, heading_scale: f64) -> (DVec2, f64) {
        let steps = self.back_off_steps(
            a,
            self.poses[a].position_m(),
            self.heading_unwrapped[a],
            distance_m,
        );
        let map = self.map.as_ref().map(|m| m.get());
        let stays_on_road = |to: DVec2| {
            map.is_none_or(|m| {
                m.lanelet_at(to.into()).is_some()
                    || leaves_through_an_open_end(m, self.poses[a].position_m(), to)
            })
        };
        steps
            .iter()
            .copied()
            .find(|&(to, heading)| {
                stays_on_road(to) && self.blockers_of(a, to, heading, heading_scale).is_empty()
            })
            .unwrap_or(steps[0])
    }

    /// The steps agent `a`, at `at` pointing `heading_rad`, may back off `distance_m` by,
    /// the preferred first ([`Self::preferred_back_off`]), then straight back and about its
    /// rear axle at either full lock ([`RELEASE_TURN_RADIUS_M`]).
    fn back_off_steps(
        &self,
        a: usize,
        at: DVec2,
        heading_rad: f64,
        distance_m: f64,
    ) -> [(DVec2, f64); 4] {
        let full_lock = distance_m / RELEASE_TURN_RADIUS_M;
        let rear_axle_m = REAR_AXLE_SHARE_OF_LENGTH * f64::from(self.window.length_m[a]);
        let arc = |turn_rad: f64| {
            arc_about_rear_axle((at, heading_rad), rear_axle_m, -distance_m, turn_rad)
        };
        [
            self.preferred_back_off(a, at, heading_rad, distance_m),
            arc(0.0),
            arc(full_lock),
            arc(-full_lock),
        ]
    }

    /// The step agent `a`, at `at` pointing `heading_rad`, backs off `distance_m` by, by
    /// preference: pointing [`STEERED_BACK_OFF_MIN_RAD`] or more off its lane (the turn towards the
    /// stall release's lane point, [`release_target`]), backwards about its rear axle, its nose
    /// turned towards that point at full lock ([`RELEASE_TURN_RADIUS_M`]), as the stall release
    /// backs and fills; otherwise, where that would leave the road, or without a map, straight
    /// back. Backing straight, a vehicle that had cut across the centre line towards an
    /// oncoming one stood nose to nose with it as before, and their gridlock lasted 15 s
    /// (issue 39).
    fn preferred_back_off(
        &self,
        a: usize,
        at: DVec2,
        heading_rad: f64,
        distance_m: f64,
    ) -> (DVec2, f64) {
        let straight = (
            at - DVec2::from_angle(heading_rad) * distance_m,
            heading_rad,
        );
        let Some(map) = self.map.as_ref().map(|m| m.get()) else {
            return straight;
        };
        let Some(target) = release_target(map, at, heading_rad) else {
            return straight;
        };
        let turn = f64::from(wrap_angle(((target - at).to_angle() - heading_rad) as f32));
        if turn.abs() < STEERED_BACK_OFF_MIN_RAD {
            return straight;
        }
        let full_lock = distance_m / RELEASE_TURN_RADIUS_M;
        let rear_axle_m = REAR_AXLE_SHARE_OF_LENGTH * f64::from(self.window.length_m[a]);
        let steered = arc_about_rear_axle(
            (at, heading_rad),
            rear_axle_m,
            -distance_m,
            turn.clamp(-full_lock, full_lock),
        );
        if map.lanelet_at(steered.0.into()).is_some() {
            steered
        } else {
            straight
        }
    }

    /// What stands in each present vehicle's path as the tick starts ([`BlockedPaths`]), and
    /// which agents stand.
    fn blocked_paths(&self, present: &[usize]) -> (BlockedPaths, Vec<bool>) {
        let size_m: Vec<[f64; 2]> = (0..self.poses.len())
            .map(|a| {
                [
                    f64::from(self.window.length_m[a]),
                    f64::from(self.window.width_m[a]),
                ]
            })
            .collect();
        let standing = (0..self.poses.len()).map(|a| self.stands(a)).collect();
        (BlockedPaths::new(&self.poses, &size_m, present), standing)
    }

    /// The present agents that agent `a`, moved to `to` and turned to `heading_rad`, would not
    /// keep clear of by the collision guard's rule ([`keeps_clear`]), the others as they stand.
    /// The move is tested as emitted (model units, `f32`), as the guard will read it: a move
    /// alongside a neighbour 1 cm away kept its gap in `f64` and closed it by micrometres once
    /// emitted, the guard stopped every such step short, and a vehicle pulled away stood 31 s
    /// (issue 39).
    fn blockers_of(&self, a: usize, to: DVec2, heading_rad: f64, heading_scale: f64) -> Vec<usize> {
        let frame = &self.window.frame;
        let to = DVec2::from(frame.to_metres(frame.to_norm(to.into())));
        let heading_rad = f64::from((heading_rad * heading_scale) as f32) / heading_scale;
        let box_of = |b: usize, pose: Pose| OrientedBox {
            pose,
            length_m: f64::from(self.window.length_m[b]),
            width_m: f64::from(self.window.width_m[b]),
        };
        let standing = box_of(
            a,
            Pose {
                heading_rad: self.heading_unwrapped[a],
                ..self.poses[a]
            },
        );
        let moved = box_of(a, Pose::at(to, heading_rad));
        (0..self.poses.len())
            .filter(|&b| {
                b != a
                    && !self.retired[b]
                    && !keeps_clear(&standing, &moved, &box_of(b, self.poses[b]))
            })
            .collect()
    }

    /// Vehicles asked to make room (`(asking, asked, again)`) by a wedged vehicle the stall
    /// release pulls away, or by one moving off into them, move off as in a deadlock
    /// ([`Self::back_off`]), away from the one asking: backwards when it stands ahead of them,
    /// forwards when behind (asked to back off, vehicles behind a wedged one backed into it,
    /// and jams stood for minutes: issue 39). Only those model-driven, standing, and not moving
    /// off or pulling away already: asked to back off while the release pulled it away, a
    /// vehicle at a kerb had both every tick for 29 s, and the long sessions' free-road stops
    /// were 29 against 15 (issue 39); but one the release found wedged this tick gives its
    /// pull-away up and makes room (`HeldMemory::wedged`). Asked `again` (by a vehicle the
    /// stall release found wedged, with its `make_room_again`), one that backed off and now
    /// gives way backs off again. With the stall release on (`can_pull_away`), one asked
    /// from behind that has free road ahead is pulled away instead: making room forwards 2 m,
    /// then standing 3 s, a vehicle the model kept stopped on a roundabout's ring led its
    /// queue round at 0.4 m/s for minutes (issue 39). Nor is one asked whose move would cross
    /// the road's edge ([`Self::backs_off_on_the_road`]).
    fn make_room(&mut self, asked: &[(usize, usize, bool)], can_pull_away: bool) {
        if asked.is_empty() {
            return;
        }
        let ticks = ((BACK_OFF_SECS + GIVE_WAY_SECS) / STEP_SECS).round() as u32;
        let give_way_ticks = (GIVE_WAY_SECS / STEP_SECS).round() as u32;
        let present: Vec<usize> = (0..self.controllers.len())
            .filter(|&b| !self.retired[b])
            .collect();
        let (paths, _) = self.blocked_paths(&present);
        for &(a, b, again) in asked {
            let memory = self.held[b];
            if self.controllers[b] != Controller::Model
                || self.overrides[b].is_some()
                || self.speed_mps[b] >= crate::free_road::STOPPED_MAX_SPEED_MPS
                || memory.backing_off_ticks >= give_way_ticks
                || (memory.backing_off_ticks > 0 && !again)
                || (memory.pulling_away && !memory.wedged)
            {
                continue;
            }
            let asking_ahead = (self.poses[a].position_m() - self.poses[b].position_m())
                .dot(DVec2::from_angle(self.heading_unwrapped[b]))
                > 0.0;
            if can_pull_away && !asking_ahead && paths.centre_rule_free(b) && !memory.giving_way {
                self.held[b].pulling_away = true;
                continue;
            }
            let sign = if asking_ahead { -1 } else { 1 };
            if !self.backs_off_on_the_road(b, sign) {
                continue;
            }
            // A pulled-away vehicle wedged itself gives its pull-away up to make room: two
            // pulled away tail to nose at a roundabout's island, each wedged against the
            // other and never asked, stood 27 s (issue 39).
            self.held[b].end_pull_away();
            self.held[b].backing_off_ticks = ticks;
            self.held[b].backing_off_sign = sign;
            self.held[b].held_streak_ticks = 0;
        }
    }

    /// Whether agent `b` backing off (`sign` −1 backwards, +1 forwards) keeps its centre on the
    /// road for its first [`BACK_OFF_MIN_ROOM_M`], step by step, or takes it out of the map
    /// through an open lane end; always, where no lane guard keeps it on the road. Backwards,
    /// each step may be any of [`Self::back_off_steps`] that stays on the road, as
    /// [`Self::backing_off_to`] takes them. Asked to back off over the road's edge, a vehicle
    /// with its centre on a median's kerb was stopped there by the lane guard, and its own
    /// pull-away, which the back-off overrides, never ran: two vehicles nose to nose on the
    /// roundabout's east arm stood 16 and 29 s (issue 39). Straight back alone, a vehicle with
    /// its centre 10 cm inside the road's edge and its nose 6° into the road (its tail over the
    /// edge) could not make room for one wedged against its nose, which stood 28 s (issue 39).
    fn backs_off_on_the_road(&self, b: usize, sign: i8) -> bool {
        let Some(map) = self.map.as_ref().filter(|_| self.keeps_on_road) else {
            return true;
        };
        let map = map.get();
        let step_m = BACK_OFF_SPEED_MPS * STEP_SECS;
        let steps = (BACK_OFF_MIN_ROOM_M / step_m).round() as usize;
        let (mut at, mut heading) = (self.poses[b].position_m(), self.heading_unwrapped[b]);
        for _ in 0..steps {
            let moves = if sign > 0 {
                vec![(at + DVec2::from_angle(heading) * step_m, heading)]
            } else {
                self.back_off_steps(b, at, heading, step_m).to_vec()
            };
            if moves
                .iter()
                .any(|&(to, _)| leaves_through_an_open_end(map, at, to))
            {
                return true;
            }
            let Some(&next) = moves
                .iter()
                .find(|&&(to, _)| map.lanelet_at(to.into()).is_some())
            else {
                return false;
            };
            (at, heading) = next;
        }
        true
    }

    /// Runs the collision guard on this tick's states (model units, overrides in): poses
    /// before the tick are `self.poses` (headings unwrapped), after it `emitted`.
    pub(super) fn guard(&mut self, emitted: &mut [f32], heading_scale: f64, guard: CollisionGuard) {
        let frame = &self.window.frame;
        // Retired agents are out of the scene: nobody brakes for them.
        let present: Vec<usize> = (0..self.controllers.len())
            .filter(|&a| !self.retired[a])
            .collect();
        let mut agents: Vec<GuardAgent> = present
            .iter()
            .map(|&a| {
                let p = frame.to_metres([emitted[3 * a], emitted[3 * a + 1]]);
                GuardAgent {
                    before: Pose {
                        heading_rad: self.heading_unwrapped[a],
                        ..self.poses[a]
                    },
                    proposed: Pose {
                        x_m: p[0],
                        y_m: p[1],
                        heading_rad: f64::from(emitted[3 * a + 2]) / heading_scale,
                    },
                    length_m: f64::from(self.window.length_m[a]),
                    width_m: f64::from(self.window.width_m[a]),
                    movable: self.controllers[a] == Controller::Model
                        && self.overrides[a].is_none(),
                    // One pulled out of a gridlock follows those making room for it without
                    // braking ahead of them (braked, it stood a metre short while they waited
                    // for it); the no-overlap rule still holds it.
                    anticipates_model_agents: self.held[a].breaking_deadlock_ticks == 0
                        && !self.held[a].pulling_out_of_gridlock
                        && !self.held[a].manoeuvred,
                }
            })
            .collect();
        let collision_actions: Vec<(usize, GuardAction)> = guard_step(&mut agents, &guard)
            .into_iter()
            .map(|(k, action)| (present[k], action))
            .collect();
        let map = self.map.as_ref().map(|m| m.get());
        for (k, &a) in present.iter().enumerate() {
            if !collision_actions.iter().any(|&(b, _)| b == a) {
                continue;
            }
            let (before, mut p) = (agents[k].before, agents[k].proposed);
            // A step cut short lies between two points on the road, not always on it: beside
            // a roundabout's island (a road edge curving into the road) the chord crosses the
            // kerb, and a vehicle braked there left the road (issue 39's long sessions). It
            // stands instead, as still as the guard would hold it.
            let off_road = |q: Pose| map.is_some_and(|m| m.lanelet_at([q.x_m, q.y_m]).is_none());
            if off_road(p)
                && !off_road(before)
                && !map.is_some_and(|m| {
                    leaves_through_an_open_end(m, before.position_m(), p.position_m())
                })
            {
                p = before;
            }
            set_emitted(
                emitted,
                a,
                frame,
                p.position_m(),
                p.heading_rad,
                heading_scale,
            );
        }
        self.guarded.extend(collision_actions.iter().copied());
        if let Some(after_secs) = guard.release_deadlock_after_secs {
            let after_ticks = (after_secs / STEP_SECS).round() as u32;
            let hold_ticks = (road_sched::DEADLOCK_RELEASE_HOLD_SECS / STEP_SECS).round() as u32;
            for &a in &present {
                let memory = &mut self.held[a];
                if memory.breaking_deadlock_ticks > 0 {
                    memory.breaking_deadlock_ticks -= 1;
                    continue;
                }
                let held = collision_actions.iter().any(|&(b, _)| b == a);
                memory.guard_held_ticks = if held { memory.guard_held_ticks + 1 } else { 0 };
                if memory.guard_held_ticks >= after_ticks {
                    memory.guard_held_ticks = 0;
                    memory.breaking_deadlock_ticks = hold_ticks;
                }
            }
            self.choose_who_backs_off(&present, &agents, &collision_actions, after_ticks);
        }
    }

    /// The deadlock release's second step: a vehicle held by the guard for `after_ticks` and
    /// now stopped short while it touches a vehicle of lower index that the guard holds too
    /// (each in the other's way: a gridlock that no brake undoes) backs off for
    /// [`BACK_OFF_SECS`], then stands for [`GIVE_WAY_SECS`] while the other goes; the lower
    /// index has the way. `agents` as the guard left them (indexed like `present`), `actions`
    /// its actions by agent.
    pub(super) fn choose_who_backs_off(
        &mut self,
        present: &[usize],
        agents: &[GuardAgent],
        actions: &[(usize, GuardAction)],
        after_ticks: u32,
    ) {
        let held = |a: usize| actions.iter().any(|&(b, _)| b == a);
        let box_of = |k: usize, margin_m: f64| OrientedBox {
            pose: agents[k].proposed,
            length_m: agents[k].length_m + 2.0 * margin_m,
            width_m: agents[k].width_m + 2.0 * margin_m,
        };
        for (k, &a) in present.iter().enumerate() {
            let stopped_short = actions.contains(&(a, GuardAction::StoppedShort));
            let memory = &mut self.held[a];
            memory.held_streak_ticks = if held(a) {
                memory.held_streak_ticks + 1
            } else {
                0
            };
            if memory.backing_off_ticks > 0
                || !stopped_short
                || memory.held_streak_ticks < after_ticks
            {
                continue;
            }
            let gives_way = present
                .iter()
                .enumerate()
                .any(|(j, &b)| b < a && held(b) && box_of(k, TOUCHING_M).overlaps(&box_of(j, 0.0)));
            if gives_way && self.backs_off_on_the_road(a, -1) {
                let memory = &mut self.held[a];
                memory.held_streak_ticks = 0;
                memory.backing_off_ticks =
                    ((BACK_OFF_SECS + GIVE_WAY_SECS) / STEP_SECS).round() as u32;
                memory.backing_off_sign = -1;
            }
        }
    }

    /// Moves the vehicles that give way in a deadlock ([`Self::choose_who_backs_off`]) or make
    /// room for a wedged one ([`Self::make_room`]) off at [`BACK_OFF_SPEED_MPS`]: backwards
    /// (one far off its lane turning towards it, [`Self::backing_off_to`]), or straight
    /// forwards when the one asking stands behind; then holds them where they stopped. The guards then
    /// check that step as any.
    pub(super) fn back_off(
        &mut self,
        emitted: &mut [f32],
        heading_scale: f64,
        can_pull_away: bool,
    ) {
        let frame = &self.window.frame;
        let give_way_ticks = (GIVE_WAY_SECS / STEP_SECS).round() as u32;
        let mut make_room = Vec::new();
        for a in 0..self.controllers.len() {
            if self.held[a].backing_off_ticks == 0 {
                continue;
            }
            self.held[a].backing_off_ticks -= 1;
            if self.retired[a]
                || self.controllers[a] != Controller::Model
                || self.overrides[a].is_some()
            {
                continue;
            }
            let heading = self.heading_unwrapped[a];
            let backing = self.held[a].backing_off_ticks >= give_way_ticks;
            let speed_mps = if backing { BACK_OFF_SPEED_MPS } else { 0.0 };
            let way = if self.held[a].backing_off_sign > 0 {
                DVec2::from_angle(heading)
            } else {
                -DVec2::from_angle(heading)
            };
            let (to, heading_to) = if backing && self.held[a].backing_off_sign <= 0 {
                self.backing_off_to(a, speed_mps * STEP_SECS, heading_scale)
            } else {
                (
                    self.poses[a].position_m() + way * speed_mps * STEP_SECS,
                    heading,
                )
            };
            if backing {
                // Those standing in its way make room in turn (a jam of four stood for
                // minutes: the vehicle asked to back off had another at its tail); those in the
                // way of the rest of its move, not only of this step: the collision guard
                // brakes for what lies within its horizon, and a jam on a roundabout stood for
                // minutes while a vehicle 0.4 m behind the one backing was never asked.
                let rest_m = f64::from(self.held[a].backing_off_ticks + 1 - give_way_ticks)
                    * speed_mps
                    * STEP_SECS;
                let end = self.poses[a].position_m() + way * rest_m;
                make_room.extend(
                    self.blockers_of(a, end, heading, heading_scale)
                        .into_iter()
                        .map(|b| (a, b, false)),
                );
            }
            set_emitted(emitted, a, frame, to, heading_to, heading_scale);
            self.guarded.push((a, GuardAction::BackedOff));
        }
        self.make_room(&make_room, can_pull_away);
    }
}

/// Whether the stall release's move this tick (`chosen`; `driving` its plain pull-away at
/// `speed_mps`) is a manoeuvre the collision guard leaves to its no-overlap rule: backing and
/// filling, turning in place, or starting off straight. The release has already kept it
/// clear of everyone as they stand; braked ahead as well (its 1 s horizon reaching a
/// neighbour a metre away), a vehicle backing and filling beside or behind others was cut to
/// centimetres a tick, about every other tick, and took 7–13 s to turn off a road's edge:
/// most of issue 39's remaining long stops.
fn manoeuvres_unanticipated(
    chosen: Option<(DVec2, f64)>,
    driving: (DVec2, f64),
    speed_mps: f64,
) -> bool {
    chosen.is_some_and(|m| m != driving || speed_mps < RELEASE_STRAIGHT_BELOW_MPS)
}

/// The vehicles of a gridlock ([`BlockedPaths::gridlock`], in index order) that lock it: those
/// on a cycle in which each has the next nearest in its path (`nearest_ahead`,
/// [`SceneRuntime::nearest_in_path`]); the whole gridlock where there is no such cycle. A
/// vehicle queued behind one of the gridlock, the gridlock's farther vehicle in its path too,
/// closes a cycle of paths without locking anything: with the way, it drove at the tail of the
/// one ahead, which was asked to make room forwards into the vehicle nose to nose with it, and
/// the gridlock stood 15 s (issue 39).
fn gridlock_core(gridlock: &[usize], nearest_ahead: impl Fn(usize) -> Option<usize>) -> Vec<usize> {
    let on_cycle = |start: usize| {
        let mut at = start;
        for _ in 0..gridlock.len() {
            match nearest_ahead(at) {
                Some(next) if gridlock.contains(&next) => at = next,
                _ => return false,
            }
            if at == start {
                return true;
            }
        }
        false
    };
    let core: Vec<usize> = gridlock.iter().copied().filter(|&b| on_cycle(b)).collect();
    if core.is_empty() {
        gridlock.to_vec()
    } else {
        core
    }
}

/// Which vehicle of a gridlock's core ([`gridlock_core`], in index order) has the way out of
/// it: the lowest-numbered one that has not passed the way on ([`HeldMemory::passes_way_on`]),
/// or the lowest-numbered when all have. `held` by agent. (Given to the vehicle pointing least
/// off its lane instead, the way made the INTERACTION maps' gridlocks worse: issue 39.)
fn way_out_of_gridlock(core: &[usize], held: &[HeldMemory]) -> Option<usize> {
    core.iter()
        .copied()
        .find(|&b| held[b].passes_way_ticks == 0)
        .or(core.first().copied())
}

/// A vehicle backing off steers towards its lane only pointing this far off it (radians, 20°;
/// [`SceneRuntime::backing_off_to`]): steering every vehicle that backed off, queues in the
/// INTERACTION maps' junction boxes turned towards one lane point after another, across each
/// other's paths, and stood longer (issue 39).
const STEERED_BACK_OFF_MIN_RAD: f64 = 20.0 * std::f64::consts::PI / 180.0;

/// A vehicle that stood this long (seconds) in a row with a gridlock's way passes it on to the
/// next vehicle of the gridlock: longer than a vehicle making room takes (`BACK_OFF_SECS`), so
/// that a holder following those backing off keeps it.
const WAY_PASSES_AFTER_SECS: f64 = 4.0;
/// For this long (seconds) a vehicle that passed the way on takes it from nobody.
const WAY_PASSED_FOR_SECS: f64 = 10.0;

/// A vehicle pointing more than this off every lanelet under it stands across or against its
/// lanes (`StuckRemoval::disoriented_after_secs`), radians: 60°, wider than a turn in a
/// junction or into a ring departs from the lanelets it turns across.
const DISORIENTED_MIN_RAD: f64 = std::f64::consts::FRAC_PI_3;
/// The stall release hands a vehicle back to the model only once it turned no more than
/// `HAND_BACK_MAX_TURN_RAD` over its last `HAND_BACK_STEADY_TICKS` (the model's observed
/// second).
const HAND_BACK_STEADY_TICKS: usize = 10;
const HAND_BACK_MAX_TURN_RAD: f64 = 0.4;

/// How far ahead of a vehicle the map's open end counts as near (metres), and the speed below
/// which a vehicle near it crawls (m/s), for the stall release.
const OPEN_END_AHEAD_M: f64 = 10.0;
const CRAWL_MAX_SPEED_MPS: f64 = 1.0;

/// Boxes closer than this touch, for the deadlock release (metres).
const TOUCHING_M: f64 = 0.1;
/// How long a vehicle that gives way in a deadlock (or makes room) backs off, seconds, and how
/// fast (m/s): 2 m. At 0.5 m/s its 1 m was too little room, and jams in junction boxes stood
/// on (issue 39's long sessions: stops of 10 s or more 127 at 0.5 m/s, 64 at 1 m/s). At
/// manoeuvring pace (`MANOEUVRE_SPEED_MPS`) since 2026-11-29: at 1 m/s the 2 m took 2 s of
/// every gridlock's release.
const BACK_OFF_SECS: f64 = 1.0;
/// How long it then stands while the vehicle that has the way goes, seconds.
const GIVE_WAY_SECS: f64 = 3.0;
const BACK_OFF_SPEED_MPS: f64 = MANOEUVRE_SPEED_MPS;
/// A vehicle asked to back off must have this much road behind it (metres, half its run):
/// less makes no room ([`SceneRuntime::backs_off_on_the_road`]).
const BACK_OFF_MIN_ROOM_M: f64 = 1.0;

/// The tightest circle a vehicle pulled away by the stall release turns on, metres.
const RELEASE_TURN_RADIUS_M: f64 = 4.0;
/// Below this speed a vehicle pulled away by the stall release drives straight on (m/s).
const RELEASE_STRAIGHT_BELOW_MPS: f64 = 1.0;
/// How fast a vehicle the stall release pulls away backs and fills (m/s): its manoeuvres at
/// full lock when the plain pull-away is blocked, a brisk parking pace. At 1 m/s a vehicle
/// turned 120–170° against its lane took 4–7 s of backing and filling to drive on, and such
/// vehicles stood 11–12 s by the long suite's count (issue 39).
const MANOEUVRE_SPEED_MPS: f64 = 2.0;
/// The most a vehicle the stall release holds at the road's edge turns in place a tick, radians.
const RELEASE_TURN_IN_PLACE_RAD: f64 = 0.05;
/// How far a car's rear axle lies behind its box's centre, as a share of its length (a 4.5 m
/// car's about 1.1 m).
const REAR_AXLE_SHARE_OF_LENGTH: f64 = 0.25;
/// How far a vehicle the stall release backs and fills backs on in one go, metres: 8 ticks
/// at `MANOEUVRE_SPEED_MPS`, turning 21° at full lock.
const BACK_AND_FILL_M: f64 = 1.5;
/// A turn of the stall release's smaller than this (radians) is no way to keep: the vehicle
/// points nearly where it wants to, and may turn either way to line up.
const KEEP_TURN_FROM_RAD: f64 = 0.2;

/// The least speed (m/s) the model must ask for to take back a vehicle the release now drives
/// at `release_speed_now_mps`: that speed, or `hand_back_speed_mps` when higher. Handed back at
/// the first step the model asked to crawl on, a vehicle the model kept stopping on free road
/// went 1.5 m every 5 s, its queue behind it (issue 39).
fn hand_back_speed_mps(release_speed_now_mps: f64, release: &StallRelease) -> f64 {
    release_speed_now_mps.max(release.hand_back_speed_mps.unwrap_or(0.0))
}

/// The turn the stall release makes towards its lane point (radians, positive
/// counter-clockwise), and the way it keeps from now on, given the turn towards this tick's
/// point (`raw_turn`) and the way it kept so far (`kept_sign`: ±1, or 0 before it turned). A
/// turn the other way than the kept one, unless small ([`KEEP_TURN_FROM_RAD`]), is made the
/// kept way by as much.
fn held_turn(raw_turn: f64, kept_sign: i8) -> (f64, i8) {
    match kept_sign {
        0 if raw_turn.abs() < KEEP_TURN_FROM_RAD => (raw_turn, 0),
        0 => (raw_turn, raw_turn.signum() as i8),
        sign if raw_turn.abs() < KEEP_TURN_FROM_RAD || raw_turn.signum() as i8 == sign => {
            (raw_turn, sign)
        }
        sign => (f64::from(sign) * raw_turn.abs(), sign),
    }
}

/// A car's move from `from` (position, heading in radians) by `distance_m` along its heading
/// (negative: backwards) about its rear axle, `rear_axle_m` behind its centre, its nose turned
/// by `turn_rad` (positive counter-clockwise): where its centre ends, and its heading.
fn arc_about_rear_axle(
    from: (DVec2, f64),
    rear_axle_m: f64,
    distance_m: f64,
    turn_rad: f64,
) -> (DVec2, f64) {
    let (at, heading_before) = from;
    let heading = heading_before + turn_rad;
    let rear_axle = at - DVec2::from_angle(heading_before) * rear_axle_m;
    let to = rear_axle
        + DVec2::from_angle(heading_before) * distance_m
        + DVec2::from_angle(heading) * rear_axle_m;
    (to, heading)
}

/// How far ahead along its lane (metres) the stall release's point lies, nearest last: the
/// first whose straight line from the vehicle stays on the road ([`release_target`]).
const RELEASE_TARGET_AHEAD_M: [f64; 3] = [6.0, 4.0, 2.0];
/// The spacing (metres) at which [`release_target`] tests a straight line for the road.
const ROAD_LINE_STEP_M: f64 = 0.25;

/// The point the stall release turns a vehicle at `at` towards ([`lane_line_near`]): the
/// farthest of [`RELEASE_TARGET_AHEAD_M`] whose straight line from `at` stays on the road, or
/// the farthest where none does (a vehicle off the road). Aiming 6 m ahead alone, a vehicle at
/// FT's kerb turned to point straight at its point, across a corner of the road's edge: every
/// step forward left the road, and it stood 30 s (issue 39).
fn release_target(map: &LaneletMap, at: DVec2, heading: f64) -> Option<DVec2> {
    let on_road_line = |to: DVec2| {
        let samples = (at.distance(to) / ROAD_LINE_STEP_M).ceil().max(1.0) as usize;
        (1..=samples).all(|i| {
            let p = at.lerp(to, i as f64 / samples as f64);
            map.lanelet_at(p.into()).is_some()
        })
    };
    let (closest, direction) = lane_line_near(map, at, heading)?;
    let point = |ahead_m: f64| closest + direction * ahead_m;
    RELEASE_TARGET_AHEAD_M
        .into_iter()
        .map(point)
        .find(|&p| on_road_line(p))
        .or(Some(point(RELEASE_TARGET_AHEAD_M[0])))
}

/// The centre line of a lane near `at`: its point nearest `at` and its direction there (along
/// its segment; points ahead lie straight on along it), the lane chosen in this order: one that `at`
/// lies on running within 90° of `heading` (radians); one that `at` lies on running any way
/// (a vehicle turned against its lane turns round rather than cross a median to the lane
/// beyond); the nearest within 10 m running within 90°; the nearest within 10 m. `None` when
/// no lane lies within 10 m.
fn lane_line_near(map: &LaneletMap, at: DVec2, heading: f64) -> Option<(DVec2, DVec2)> {
    let forward = DVec2::from_angle(heading);
    let its_way = |direction: DVec2| direction.dot(forward) > 0.0;
    let any_way = |_: DVec2| true;
    let under = || map.lanelets.iter().filter(|l| l.contains(at.into()));
    let near = |keep: &dyn Fn(DVec2) -> bool| {
        crate::initialisation::nearest_centre_where(map, at, keep)
            .filter(|&(dist_m, _, _)| dist_m <= super::exits::OFF_MAP_M)
    };
    crate::initialisation::nearest_centre_on(under(), at, its_way)
        .or_else(|| crate::initialisation::nearest_centre_on(under(), at, any_way))
        .or_else(|| near(&its_way))
        .or_else(|| near(&any_way))
        .map(|(_, closest, direction)| (closest, direction))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::DVec2;
    use road_data::LaneletMap;

    use super::{
        HeldMemory, KEEP_TURN_FROM_RAD, RELEASE_STRAIGHT_BELOW_MPS, StallRelease, gridlock_core,
        hand_back_speed_mps, held_turn, lane_line_near, manoeuvres_unanticipated, release_target,
        way_out_of_gridlock,
    };

    #[test]
    fn a_release_s_manoeuvres_are_left_to_the_no_overlap_rule_its_driving_is_not() {
        let driving = (DVec2::new(0.3, 0.0), 0.0);
        let backing = (DVec2::new(-0.1, 0.0), 0.02);
        let turning_in_place = (DVec2::ZERO, 0.05);
        // Backing and filling, or turning in place, at any speed the release has reached.
        assert!(manoeuvres_unanticipated(Some(backing), driving, 3.0));
        assert!(manoeuvres_unanticipated(
            Some(turning_in_place),
            driving,
            3.0
        ));
        // Driving on: only while it starts off straight, below the speed it turns from.
        assert!(manoeuvres_unanticipated(
            Some(driving),
            driving,
            0.5 * RELEASE_STRAIGHT_BELOW_MPS
        ));
        assert!(!manoeuvres_unanticipated(
            Some(driving),
            driving,
            RELEASE_STRAIGHT_BELOW_MPS
        ));
        // Standing (nothing feasible): no step to anticipate.
        assert!(!manoeuvres_unanticipated(None, driving, 0.5));
    }

    #[test]
    fn a_vehicle_that_stands_on_with_a_gridlock_s_way_passes_it_to_the_next() {
        // Vehicles 2, 5 and 7 locked in a gridlock: 2, the lowest-numbered, has the way.
        let gridlock = [2, 5, 7];
        let mut held = vec![HeldMemory::default(); 8];
        assert_eq!(way_out_of_gridlock(&gridlock, &held), Some(2));
        held[2].pulling_away = true;
        held[2].pulling_out_of_gridlock = true;
        // It stands with the way for 39 ticks, moves one, stands 39 more: it keeps the way.
        for moves in (0..39)
            .map(|_| false)
            .chain([true])
            .chain((0..39).map(|_| false))
        {
            assert!(!held[2].passes_way_on(!moves));
        }
        assert_eq!(way_out_of_gridlock(&gridlock, &held), Some(2));
        // Standing on (over 4 s in a row): it passes the way on to 5, its pull-away over, for
        // 10 s.
        assert!(held[2].passes_way_on(true));
        assert!(!held[2].pulling_away && !held[2].pulling_out_of_gridlock);
        assert_eq!(held[2].stood_with_way_ticks, 0);
        assert_eq!(held[2].passes_way_ticks, 100);
        assert_eq!(way_out_of_gridlock(&gridlock, &held), Some(5));
        // When every one has passed it, the lowest-numbered has it again.
        held[5].passes_way_ticks = 100;
        held[7].passes_way_ticks = 3;
        assert_eq!(way_out_of_gridlock(&gridlock, &held), Some(2));
        assert_eq!(way_out_of_gridlock(&[], &held), None);
    }

    #[test]
    fn a_vehicle_queued_behind_a_gridlock_s_vehicle_is_not_of_its_core() {
        // 0 and 5 nose to nose; 3 queued behind 0, its path on to 5, and 5's path past 0 on to
        // 3: paths make a gridlock of all three, nearest blockers of 0 and 5 alone.
        let nearest = |b: usize| match b {
            0 => Some(5),
            5 => Some(0),
            3 => Some(0),
            _ => None,
        };
        assert_eq!(gridlock_core(&[0, 3, 5], nearest), vec![0, 5]);
        // Four round a crossing, each the next's nearest: all of them.
        let round = |b: usize| Some([1, 2, 3, 0][b]);
        assert_eq!(gridlock_core(&[0, 1, 2, 3], round), vec![0, 1, 2, 3]);
        // No cycle of nearest blockers (one's nearest is outside the gridlock): the gridlock.
        let outside = |b: usize| Some(if b == 0 { 9 } else { 0 });
        assert_eq!(gridlock_core(&[0, 1], outside), vec![0, 1]);
    }

    #[test]
    fn a_vehicle_s_turn_is_read_over_its_last_ticks() {
        let mut memory = HeldMemory::default();
        // Nothing known yet, then one tick: no turn.
        assert_eq!(memory.turned_over_rad(10), 0.0);
        // 0.1 rad a tick for 30 ticks (the ring holds 21): over the last 10, 1 rad.
        for k in 0..30 {
            memory.record(DVec2::new(f64::from(k), 0.0), 0.1 * f64::from(k));
        }
        assert!((memory.turned_over_rad(10) - 1.0).abs() < 1e-9);
        // Over more ticks than the ring holds, over the ring's 20.
        assert!((memory.turned_over_rad(50) - 2.0).abs() < 1e-9);
        // Fewer known than asked: over those known.
        let mut young = HeldMemory::default();
        for k in 0..4 {
            young.record(DVec2::ZERO, 0.1 * f64::from(k));
        }
        assert!((young.turned_over_rad(10) - 0.3).abs() < 1e-9);
    }

    /// A 4 m wide road east along y = 0 up to x = 0, then bending 60° left: two lanelets of a
    /// Lanelet2 map.
    fn bending_road() -> LaneletMap {
        // Near (0, 0) a degree of latitude is 110 574 m, of longitude 111 320 m.
        let node = |id: u32, x: f64, y: f64| {
            format!(
                "<node id=\"{id}\" lat=\"{}\" lon=\"{}\"/>\n",
                y / 110_574.0,
                x / 111_320.0
            )
        };
        let (far_x, far_y) = (
            30.0 * 60f64.to_radians().cos(),
            30.0 * 60f64.to_radians().sin(),
        );
        let mut osm = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
        for (id, x, y) in [
            (1, -30.0, 2.0),
            (2, 0.0, 2.0),
            (3, -30.0, -2.0),
            (4, 0.0, -2.0),
            (5, far_x, 2.0 + far_y),
            (6, far_x, -2.0 + far_y),
        ] {
            osm += &node(id, x, y);
        }
        for (id, a, b) in [(10, 1, 2), (11, 3, 4), (12, 2, 5), (13, 4, 6)] {
            osm += &format!("<way id=\"{id}\"><nd ref=\"{a}\"/><nd ref=\"{b}\"/></way>\n");
        }
        for (id, left, right) in [(20, 10, 11), (21, 12, 13)] {
            osm += &format!(
                "<relation id=\"{id}\"><member type=\"way\" ref=\"{left}\" role=\"left\"/><member type=\"way\" ref=\"{right}\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/></relation>\n"
            );
        }
        osm += "</osm>\n";
        LaneletMap::parse(&osm, Path::new("bend.osm"), "bend").unwrap()
    }

    #[test]
    fn the_release_aims_at_a_lane_point_it_reaches_in_a_straight_line() {
        // At the inner edge just before the bend: 6 m (and 4 m) on along the first lanelet
        // lie off the road past the bend, and the line to them crosses the inner corner; 2 m
        // on, (0.5, 0), lies on the bend's lanelet, the line to it on the road.
        let map = bending_road();
        let at = DVec2::new(-1.5, 1.7);
        let (closest, direction) = lane_line_near(&map, at, 0.0).unwrap();
        let six = closest + direction * 6.0;
        assert!(
            map.lanelet_at(six.into()).is_none(),
            "6 m on lies off the road: {six}"
        );
        let target = release_target(&map, at, 0.0).unwrap();
        assert!(
            target.distance(DVec2::new(0.5, 0.0)) < 0.05,
            "aimed at {target}"
        );
    }

    #[test]
    fn the_model_takes_a_vehicle_back_from_the_hand_back_speed_on_when_one_is_set() {
        let release = StallRelease {
            after_secs: 3.0,
            acceleration_mps2: 1.5,
            release_speed_mps: 5.0,
            gridlock_after_secs: None,
            hand_back_speed_mps: None,
            make_room_again: false,
        };
        // Unset: as fast as the release drives it now.
        assert_eq!(hand_back_speed_mps(0.15, &release), 0.15);
        let set = StallRelease {
            hand_back_speed_mps: Some(5.0),
            ..release
        };
        // Set: a crawl asked at 1 m/s no longer takes it back; 5 m/s does.
        assert_eq!(hand_back_speed_mps(0.15, &set), 5.0);
        assert_eq!(hand_back_speed_mps(5.0, &set), 5.0);
    }

    #[test]
    fn a_turn_the_other_way_is_kept_the_first_way_unless_small() {
        let big = 2.0 * KEEP_TURN_FROM_RAD;
        let small = 0.5 * KEEP_TURN_FROM_RAD;
        // Nothing kept yet: a small turn keeps no way, a big one keeps its own.
        assert_eq!(held_turn(small, 0), (small, 0));
        assert_eq!(held_turn(-big, 0), (-big, -1));
        // Kept clockwise: a big counter-clockwise turn (the lane point jumped) turns clockwise
        // by as much; a small one (lining up) is made as asked; the kept way stays.
        assert_eq!(held_turn(big, -1), (-big, -1));
        assert_eq!(held_turn(small, -1), (small, -1));
        assert_eq!(held_turn(-big, -1), (-big, -1));
    }
}
