//! `road-planner`: what the default planner does to the model's emitted states before they join
//! the history and the window, all of it deviations from the paper, each a planner option of
//! `configs/planners.toml` (off unless a planner sets it) and measured in `docs/results.md`:
//! - [`smoothing`] (run by `road-rollout`'s driver, for every engine): acceleration smoothing,
//!   plan smoothing, least-jerk tracking of the model's plan, headings that follow the course;
//! - [`lane_guard`] (run by `road-sim`'s closed loop, after the controllers): a vehicle about
//!   to leave every lanelet steers back towards its lane or stops at the edge, with nudges
//!   ahead of the edge and its plan turned with it;
//! - [`collision_guard`] (after the lane guard): model-driven agents brake ahead of a predicted
//!   collision and never step into another's box;
//! - [`geometry`]: the oriented boxes both guards and the infraction checks use.
//!
//! The order each tick: the model emits, the driver smooths, the controllers overwrite the
//! agents they drive, the lane guard, then the collision guard; the guarded state is what the
//! model plans on from. All positions are metres in the map frame, headings radians, except in
//! [`smoothing`], which works on the model's own units.

pub mod collision_guard;
pub mod geometry;
pub mod lane_guard;
pub mod smoothing;

/// A pose in metres and radians.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    pub x_m: f64,
    pub y_m: f64,
    pub heading_rad: f64,
}

impl Pose {
    /// The pose at `position_m` with heading `heading_rad`.
    pub fn at(position_m: glam::DVec2, heading_rad: f64) -> Self {
        Self {
            x_m: position_m.x,
            y_m: position_m.y,
            heading_rad,
        }
    }

    /// The position (metres), for vector math.
    pub fn position_m(self) -> glam::DVec2 {
        glam::DVec2::new(self.x_m, self.y_m)
    }

    /// Distance between the two positions (metres), by `hypot` as before glam: paths and
    /// speeds measured with it (the adversarial agent, kinematic realism) keep their bits.
    pub fn distance_m(self, other: Pose) -> f64 {
        road_data::geometry::hypot_length(other.position_m() - self.position_m())
    }
}
