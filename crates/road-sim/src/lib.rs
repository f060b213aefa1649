//! `road-sim`: what a simulation needs around an engine, engine-agnostic:
//! - [`geometry`]: oriented boxes from (x, y, heading, length, width) and their overlap;
//! - [`guard`]: the collision guard, a planner option: model-driven agents brake ahead of a
//!   predicted collision and never step into another agent's box;
//! - [`lane_guard`]: the lane guard, a planner option: a model-driven agent about to leave
//!   every lanelet steers back towards its lane, or stops at the road's edge;
//! - [`infractions`]: collisions between agents and off-road positions per tick;
//! - [`controllers`]: non-model controllers: constant velocity, and the paper's adversarial
//!   agent (its logged path, slowed to cover only half of it by the end);
//! - [`metrics`]: minSceneADE / minSceneFDE and the miss rate (math doc, "Evaluation");
//! - [`closed_loop`]: scenes simulated tick by tick on an engine, each agent with its
//!   [`closed_loop::Controller`] (model, replay, adversarial, constant velocity, external);
//! - [`procedural`]: a redistributable scene built from code (the `road demo` default).
//!
//! All positions are metres in the map frame; headings radians.

pub mod closed_loop;
pub mod controllers;
pub mod geometry;
pub mod guard;
pub mod infractions;
pub mod kinematics;
pub mod lane_guard;
pub mod metrics;
pub mod procedural;

/// Errors of the simulation layer.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Model(#[from] road_model::Error),
    /// A simulation set up inconsistently (counts that do not match, agents absent).
    #[error("simulation setup: {0}")]
    Config(String),
    /// An external driver could not give an agent's pose.
    #[error("scene {scene}, agent {agent}: external driver: {reason}")]
    External {
        scene: usize,
        agent: usize,
        reason: String,
    },
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

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
