//! `road-sim`: what a simulation needs around an engine, engine-agnostic:
//! - [`geometry`]: oriented boxes from (x, y, heading, length, width) and their overlap;
//! - [`infractions`]: collisions between agents and off-road positions per tick;
//! - [`controllers`]: non-model controllers: constant velocity, and the paper's adversarial
//!   agent (its logged path, slowed to cover only half of it by the end);
//! - [`metrics`]: minSceneADE / minSceneFDE and the miss rate (math doc, "Evaluation").
//!
//! All positions are metres in the map frame; headings radians.

pub mod controllers;
pub mod geometry;
pub mod infractions;
pub mod metrics;

/// A pose in metres and radians.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    pub x_m: f64,
    pub y_m: f64,
    pub heading_rad: f64,
}
