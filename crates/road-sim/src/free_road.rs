//! Whether a vehicle stands with free road ahead: what the stall release
//! (`road_sched::StallRelease`) and the long sessions' counts (`crate::session`) both ask.

use glam::DVec2;

use crate::Pose;

/// Slower than this, a vehicle is stopped (m/s).
pub const STOPPED_MAX_SPEED_MPS: f64 = 0.3;
/// The road ahead of a stopped vehicle is free when no other vehicle's centre lies within this
/// distance ahead of it (metres), within [`FREE_ROAD_HALF_WIDTH_M`] of its axis.
pub const FREE_ROAD_AHEAD_M: f64 = 15.0;
pub const FREE_ROAD_HALF_WIDTH_M: f64 = 3.0;

/// Whether no other present vehicle's centre lies ahead of `agent` within
/// [`FREE_ROAD_AHEAD_M`] and [`FREE_ROAD_HALF_WIDTH_M`] of its axis.
pub fn road_ahead_free(agent: usize, poses: &[Pose], present: &[usize]) -> bool {
    let me = poses[agent];
    let forward = DVec2::from_angle(me.heading_rad);
    present.iter().filter(|&&b| b != agent).all(|&b| {
        let d = poses[b].position_m() - me.position_m();
        let along = d.dot(forward);
        let across = d.perp_dot(forward).abs();
        !(along > 0.0 && along <= FREE_ROAD_AHEAD_M && across <= FREE_ROAD_HALF_WIDTH_M)
    })
}
