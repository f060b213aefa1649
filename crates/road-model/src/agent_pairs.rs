//! Agent–agent pair features ([`crate::config::AgentPairs`]): what agent attention adds to each
//! (query agent, key agent) pair of a slot. Plain data preparation (no weights, no gradient),
//! shared by the candle model and the fast CPU engine; `shaders/agent_pairs.wgsl` computes the
//! same on the device and is tested against [`pair_features`].

use crate::agent_map::MapAnchor;
use crate::config::AgentPairs;

/// Features per pair: direction (forward, left), proximity (near, far), heading difference
/// (cos, sin).
pub const PAIR_FEATURES: usize = 6;

/// [`AgentPairs`]' length scales in scene units (the states' unit), ready for the features.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairScales {
    pub direction: f32,
    pub near: f32,
    pub far: f32,
    /// State units per radian (`ModelConfig::heading_scale`).
    pub heading_scale: f32,
}

impl PairScales {
    pub fn new(pairs: &AgentPairs, position_scale_m: f64, heading_scale: f64) -> Self {
        let units = |metres: f64| (metres / position_scale_m) as f32;
        Self {
            direction: units(pairs.direction_scale_m),
            near: units(pairs.near_scale_m),
            far: units(pairs.far_scale_m),
            heading_scale: heading_scale as f32,
        }
    }
}

/// The features of key agent state `key` (x, y, heading state) seen from query agent state
/// `query` of the same slot, whose agent's anchor is `anchor`: j's offset turned into i's
/// anchor heading (forward, left) as `offset / (distance + direction scale)`, the proximities
/// `exp(−distance / scale)`, and the cosine and sine of j's heading minus i's.
pub fn pair_features(
    query: &[f32],
    anchor: MapAnchor,
    key: &[f32],
    scales: PairScales,
) -> [f32; PAIR_FEATURES] {
    let (dx, dy) = (key[0] - query[0], key[1] - query[1]);
    let forward = dx * anchor.cos + dy * anchor.sin;
    let left = dy * anchor.cos - dx * anchor.sin;
    let distance = (forward * forward + left * left).sqrt();
    let squash = 1.0 / (distance + scales.direction);
    let (sin, cos) = ((key[2] - query[2]) / scales.heading_scale).sin_cos();
    [
        forward * squash,
        left * squash,
        (-distance / scales.near).exp(),
        (-distance / scales.far).exp(),
        cos,
        sin,
    ]
}

/// Every pair of every slot of windows `x [B, A, W, 3]` whose agents have `anchors [B·A]`
/// (from [`crate::agent_map::anchors_of`]): `[B, W, A (query), A (key), F]`. Padding and
/// invalid tokens get features too (bounded: their keys are masked, their outputs unused).
pub fn pair_features_of(
    x: &[f32],
    anchors: &[MapAnchor],
    agents: usize,
    slots: usize,
    scales: PairScales,
) -> Vec<f32> {
    let scenes = anchors.len() / agents.max(1);
    let f = PAIR_FEATURES;
    let mut out = vec![0.0; scenes * slots * agents * agents * f];
    let state = |scene: usize, agent: usize, slot: usize| {
        &x[3 * ((scene * agents + agent) * slots + slot)..][..3]
    };
    for scene in 0..scenes {
        for slot in 0..slots {
            for i in 0..agents {
                let query = state(scene, i, slot);
                let anchor = anchors[scene * agents + i];
                for j in 0..agents {
                    let at = (((scene * slots + slot) * agents + i) * agents + j) * f;
                    out[at..at + f].copy_from_slice(&pair_features(
                        query,
                        anchor,
                        state(scene, j, slot),
                        scales,
                    ));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCALES: PairScales = PairScales {
        direction: 0.25,
        near: 0.125,
        far: 0.5,
        heading_scale: 0.25,
    };

    #[test]
    fn a_car_ahead_reads_ahead_in_every_orientation() {
        // Query at the origin heading north (π/2); key 0.1 units (4 m) north of it, same heading.
        let heading = std::f32::consts::FRAC_PI_2;
        let anchor = MapAnchor {
            x: 0.0,
            y: 0.0,
            cos: heading.cos(),
            sin: heading.sin(),
        };
        let query = [0.0, 0.0, heading * 0.25];
        let key = [0.0, 0.1, heading * 0.25];
        let f = pair_features(&query, anchor, &key, SCALES);
        assert!((f[0] - 0.1 / 0.35).abs() < 1e-6, "forward {f:?}");
        assert!(f[1].abs() < 1e-6, "left {f:?}");
        assert!((f[2] - (-0.8f32).exp()).abs() < 1e-6);
        assert!((f[3] - (-0.2f32).exp()).abs() < 1e-6);
        assert!((f[4] - 1.0).abs() < 1e-6 && f[5].abs() < 1e-6);
        // The same pair turned by any angle about any point gives the same features.
        let (s, c) = 1.1f32.sin_cos();
        let turn = |p: [f32; 3]| {
            [
                c * p[0] - s * p[1] + 3.0,
                s * p[0] + c * p[1] - 2.0,
                p[2] + 1.1 * 0.25,
            ]
        };
        let (query2, key2) = (turn(query), turn(key));
        let anchor2 = MapAnchor {
            x: query2[0],
            y: query2[1],
            cos: (heading + 1.1).cos(),
            sin: (heading + 1.1).sin(),
        };
        let g = pair_features(&query2, anchor2, &key2, SCALES);
        for (a, b) in f.iter().zip(&g) {
            assert!((a - b).abs() < 1e-5, "{f:?} against {g:?}");
        }
    }

    #[test]
    fn an_agent_seen_from_itself_is_near_and_aligned() {
        let f = pair_features(
            &[0.3, -0.2, 0.1],
            MapAnchor::SCENE,
            &[0.3, -0.2, 0.1],
            SCALES,
        );
        assert_eq!(f, [0.0, 0.0, 1.0, 1.0, 1.0, 0.0]);
    }

    #[test]
    fn all_pairs_are_laid_out_query_major_per_slot() {
        // One scene, 2 agents, 2 slots: agent 1 sits 0.1 units east of agent 0 at slot 1 only.
        let x = [
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, // agent 0, slots 0 and 1
            0.0, 0.0, 0.0, 0.1, 0.0, 0.0, // agent 1
        ];
        let anchors = [MapAnchor::SCENE; 2];
        let out = pair_features_of(&x, &anchors, 2, 2, SCALES);
        assert_eq!(out.len(), 2 * 2 * 2 * PAIR_FEATURES);
        let at = |slot: usize, i: usize, j: usize| {
            &out[((slot * 2 + i) * 2 + j) * PAIR_FEATURES..][..PAIR_FEATURES]
        };
        assert_eq!(at(0, 0, 1)[0], 0.0);
        assert!(at(1, 0, 1)[0] > 0.0, "agent 1 ahead of agent 0 at slot 1");
        assert!(at(1, 1, 0)[0] < 0.0, "agent 0 behind agent 1");
    }
}
