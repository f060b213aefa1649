//! Scenes whose every agent is scripted (replay, adversarial, constant velocity): the
//! non-reactive baselines, and the scripted agents of a closed loop.

use road_data::{LaneletMap, SceneWindow, wrap_angle};

use super::{Controller, SceneTick, SimScene, boxes, start_poses};
use crate::controllers::{constant_velocity, slowed_replay};
use crate::infractions::{collisions, off_road};
use crate::{Error, Pose, Result};

/// Simulates a scene whose every agent is scripted (replay, adversarial, constant velocity):
/// the non-reactive baselines, with no model. Reports like [`ClosedLoop::tick`](super::ClosedLoop::tick).
pub fn simulate_scripted(
    scene: &SimScene,
    map: Option<&LaneletMap>,
    steps: usize,
) -> Result<Vec<SceneTick>> {
    let start = start_poses(scene, 1)?;
    let w = &scene.window;
    let reference = scene.observed_steps - 1;
    if let Some(a) = scene
        .controllers
        .iter()
        .position(|c| matches!(c, Controller::Model | Controller::External))
    {
        return Err(Error::Config(format!(
            "{} {} frame {}: agent {a} is not scripted ({:?})",
            w.location, w.file, w.start_frame, scene.controllers[a]
        )));
    }
    let scripted: Vec<Vec<Pose>> = (0..w.agents)
        .map(|a| script(w, a, reference, steps, scene.controllers[a]))
        .collect();
    let initial_boxes = boxes(w, &start);
    let initial_overlaps = collisions(&initial_boxes);
    let initially_off = map.map(|m| off_road(&initial_boxes, m)).unwrap_or_default();
    Ok((0..steps)
        .map(|t| {
            let poses: Vec<Pose> = scripted
                .iter()
                .map(|p| Pose {
                    heading_rad: f64::from(wrap_angle(p[t].heading_rad as f32)),
                    ..p[t]
                })
                .collect();
            let b = boxes(w, &poses);
            let mut hits = collisions(&b);
            hits.retain(|pair| !initial_overlaps.contains(pair));
            let mut off = map.map(|m| off_road(&b, m)).unwrap_or_default();
            off.retain(|a| !initially_off.contains(a));
            SceneTick {
                poses,
                collisions: hits,
                off_road: off,
                guarded: Vec::new(),
                plans: Vec::new(),
                left: Vec::new(),
                stuck: Vec::new(),
            }
        })
        .collect())
}

/// The scripted poses of agent `a` for ticks `0..steps` (pose after each tick); empty for the
/// model's and external agents.
pub(super) fn script(
    w: &SceneWindow,
    a: usize,
    reference: usize,
    steps: usize,
    controller: Controller,
) -> Vec<Pose> {
    let last = crate::window_pose(w, a, reference).expect("checked present at the reference step");
    let previous = reference
        .checked_sub(1)
        .and_then(|t| crate::window_pose(w, a, t))
        .unwrap_or(last);
    match controller {
        Controller::Model | Controller::External => Vec::new(),
        Controller::ConstantVelocity => constant_velocity(previous, last, steps),
        Controller::Replay => {
            let mut out = Vec::with_capacity(steps);
            let (mut prev, mut cur) = (previous, last);
            for t in 1..=steps {
                let next = crate::window_pose(w, a, reference + t).unwrap_or_else(|| {
                    // The log ends (or the agent left): carry on at constant velocity.
                    constant_velocity(prev, cur, 1)[0]
                });
                out.push(next);
                (prev, cur) = (cur, next);
            }
            out
        }
        Controller::Adversarial => {
            let logged: Vec<Pose> = (reference..w.steps)
                .map_while(|t| crate::window_pose(w, a, t))
                .collect();
            slowed_replay(&logged, steps)
        }
    }
}

/// The reactivity test's adversarial agent: the one with the longest logged path over the
/// window's steps after `reference` (it must be present throughout), `None` when nobody moves.
pub fn pick_adversary(w: &SceneWindow, reference: usize) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for a in 0..w.agents {
        let path: Option<Vec<Pose>> = (reference..w.steps)
            .map(|t| crate::window_pose(w, a, t))
            .collect();
        let Some(path) = path else { continue };
        let length: f64 = path.windows(2).map(|p| p[0].distance_m(p[1])).sum();
        if length > 1.0 && best.is_none_or(|(_, l)| length > l) {
            best = Some((a, length));
        }
    }
    best.map(|b| b.0)
}
