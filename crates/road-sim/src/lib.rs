//! `road-sim`: what a simulation needs around an engine, engine-agnostic:
//! - [`infractions`]: collisions between agents and off-road positions per tick;
//! - [`controllers`]: non-model controllers: constant velocity, and the paper's adversarial
//!   agent (its logged path, slowed to cover only half of it by the end);
//! - [`metrics`]: minSceneADE / minSceneFDE and the miss rate (math doc, "Evaluation");
//! - [`closed_loop`]: scenes simulated tick by tick on an engine, each agent with its
//!   [`closed_loop::Controller`] (model, replay, adversarial, constant velocity, external);
//! - [`procedural`]: a redistributable scene built from code (the `road demo` default);
//! - [`populate`]: vehicles put on a map that has none (placement, then the model's refinement
//!   of their histories), and vehicles entering at its entry lanes.
//!
//! The planner's guards that the closed loop applies each tick live in `road-planner`.
//!
//! All positions are metres in the map frame; headings radians.

pub mod closed_loop;
pub mod controllers;
pub mod free_road;
pub mod infractions;
pub mod initialisation;
pub mod kinematics;
pub mod metrics;
pub mod populate;
pub mod procedural;
pub mod route;
pub mod session;

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

pub use road_planner::Pose;

/// Agent `agent`'s pose at step `step` of `window` in metres and radians (as the window holds
/// its heading); `None` where it is absent.
pub fn window_pose(window: &road_data::SceneWindow, agent: usize, step: usize) -> Option<Pose> {
    window.state(agent, step).map(|s| {
        let p = window.frame.to_metres([s[0], s[1]]);
        Pose {
            x_m: p[0],
            y_m: p[1],
            heading_rad: f64::from(s[2]),
        }
    })
}
/// Oriented boxes (`road_planner::geometry`), re-exported for the simulation's users.
pub use road_planner::geometry;
