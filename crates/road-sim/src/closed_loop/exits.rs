//! Vehicles leaving the map: an agent off every lanelet past an open end of the lane it was last
//! on (the end of a lane with no successor, or the start of one with no predecessor) is retired,
//! and so is one farther than [`OFF_MAP_M`] from every lane, however it got there.

use glam::DVec2;
use road_data::LaneletMap;

use super::{Controller, SceneRuntime};

impl SceneRuntime<'_> {
    /// Marks the agents (not the client's) that have just driven out of the map through an
    /// open end of the lanelet they were last on: off every lanelet, ahead of the end of a lane
    /// with no successor (or behind the start of one with no predecessor, a vehicle that drifted
    /// onto the opposite lane) and within [`EXIT_LATERAL_MARGIN_M`] of the lane's width sideways;
    /// or farther than [`OFF_MAP_M`] from every lane's centre line.
    pub(super) fn retire_exits(&mut self, map: &LaneletMap) {
        for a in 0..self.poses.len() {
            if self.retired[a] || self.controllers[a] == Controller::External {
                continue;
            }
            let at = [self.poses[a].x_m, self.poses[a].y_m];
            if let Some(l) = map.lanelet_at(at) {
                self.last_lanelet[a] = Some(l);
                continue;
            }
            // Beyond every lane's reach it has left the map, with or without a lane to leave
            // through: an INTERACTION scene's vehicle that started off its crop's lanes never
            // had one, and the model drove it 30 s off the lanes and stood it 54 m from
            // any lane for 478 s (issue 39's long sessions, FT seed 26).
            if crate::initialisation::nearest_centre(map, DVec2::from(at))
                .is_none_or(|(distance_m, _)| distance_m > OFF_MAP_M)
            {
                self.retired[a] = true;
                self.left.push(a);
                continue;
            }
            let Some(lane) = self.last_lanelet[a].map(|l| &map.lanelets[l]) else {
                continue;
            };
            let last = self.last_lanelet[a].expect("set above") as u32;
            let open_start = || !map.lanelets.iter().any(|l| l.successors.contains(&last));
            if (lane.successors.is_empty()
                && past_lane_end(&lane.centre_m, lane_end_width(lane, true), at))
                || (open_start()
                    && past_lane_end(&reversed(&lane.centre_m), lane_end_width(lane, false), at))
            {
                self.retired[a] = true;
                self.left.push(a);
            }
        }
    }
}

/// An agent off every lanelet and farther than this from every lane's centre line has left
/// the map (metres): as far as the stall release looks for a lane to turn back to.
pub const OFF_MAP_M: f64 = 10.0;

/// How far sideways of a lane's end an agent may be and still count as having left the map
/// through it (beyond half the lane's width).
pub const EXIT_LATERAL_MARGIN_M: f64 = 2.0;

/// Whether `at` lies ahead of the end of the centre line `centre` (past the line square to its
/// last segment [`EXIT_BACK_SLACK_M`] before its last point) and within half the lane's end width (`width_m`)
/// plus [`EXIT_LATERAL_MARGIN_M`] of that line's axis. For a lane's start, its centre line
/// reversed.
fn past_lane_end(
    centre: &[road_data::geometry::Point],
    width_m: f64,
    at: road_data::geometry::Point,
) -> bool {
    let [.., before, end] = centre else {
        return false;
    };
    let (end, before) = (DVec2::from(*end), DVec2::from(*before));
    let Some(along) = (end - before).try_normalize() else {
        return false;
    };
    let offset = DVec2::from(at) - end;
    offset.dot(along) > -EXIT_BACK_SLACK_M
        && offset.perp_dot(along).abs() <= 0.5 * width_m + EXIT_LATERAL_MARGIN_M
}

/// How far before the end of a lane's centre line an agent off every lanelet counts as past
/// it (metres): INTERACTION's lanes end on oblique lines, and a vehicle leaving through one is
/// off the lanelet a few ticks before its centre passes the centre line's end.
const EXIT_BACK_SLACK_M: f64 = 2.0;

/// The width of `lane` at its end (`at_end`) or its start, metres (0 without bounds).
fn lane_end_width(lane: &road_data::map::Lanelet, at_end: bool) -> f64 {
    let ends = if at_end {
        (lane.left_m.last(), lane.right_m.last())
    } else {
        (lane.left_m.first(), lane.right_m.first())
    };
    match ends {
        (Some(&l), Some(&r)) => DVec2::from(l).distance(DVec2::from(r)),
        _ => 0.0,
    }
}

fn reversed(line: &[road_data::geometry::Point]) -> Vec<road_data::geometry::Point> {
    line.iter().rev().copied().collect()
}
