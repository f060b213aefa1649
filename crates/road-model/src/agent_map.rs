//! Agent-centric maps ([`crate::config::AgentMap`]): which lane polylines each agent attends
//! to and where their points lie in its anchor frame. Plain data preparation (no weights, no
//! gradient), shared by the candle model and the fast CPU engine so that both pick the same
//! polylines: the pick is discrete, and two implementations could break ties differently.

/// An agent's anchor pose as its map sees it: position in scene units and the heading's cosine
/// and sine. An agent without an anchor has [`MapAnchor::SCENE`]: the scene centre, heading 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapAnchor {
    pub x: f32,
    pub y: f32,
    pub cos: f32,
    pub sin: f32,
}

impl MapAnchor {
    pub const SCENE: Self = Self {
        x: 0.0,
        y: 0.0,
        cos: 1.0,
        sin: 0.0,
    };
}

/// Every agent row's anchor in noisy windows `x [B, A, W, 3]` with flags `valid [B, A, W]`:
/// its state at `anchor_slot` times its validity there (so an agent without an anchor sits at
/// the scene centre with heading 0), heading `x.heading / heading_scale`. `[B·A]`.
pub fn anchors_of(
    x: &[f32],
    valid: &[f32],
    slots: usize,
    anchor_slot: usize,
    heading_scale: f32,
) -> Vec<MapAnchor> {
    valid
        .chunks_exact(slots)
        .enumerate()
        .map(|(row, flags)| {
            let v = flags[anchor_slot];
            let state = &x[3 * (row * slots + anchor_slot)..][..3];
            let (sin, cos) = (state[2] * v / heading_scale).sin_cos();
            MapAnchor {
                x: state[0] * v,
                y: state[1] * v,
                cos,
                sin,
            }
        })
        .collect()
}

/// The number of polylines each agent gets when a scene offers `available` (padding included)
/// and the model asks for `wanted`.
pub fn polylines_per_agent(wanted: usize, available: usize) -> usize {
    wanted.min(available)
}

/// One agent's map: the `k` polylines of `map [P, Q, 2]` (flags `map_valid [P]`) nearest
/// `anchor` (least squared distance to any of their points; valid ones before padding; ties to
/// the lower index), written as `points [k, Q, 2]` in the anchor frame (forward, left; scene
/// units) with their flags in `valid [k]`. `k ≤ P`.
pub fn agent_map(
    anchor: MapAnchor,
    map: &[f32],
    map_valid: &[f32],
    points_per_polyline: usize,
    points: &mut [f32],
    valid: &mut [f32],
) {
    let q = points_per_polyline;
    let k = valid.len();
    let p = map_valid.len();
    debug_assert!(k <= p && map.len() == p * q * 2 && points.len() == k * q * 2);
    let mut order: Vec<(bool, f32, usize)> = (0..p)
        .map(|poly| {
            let nearest = map[poly * q * 2..][..q * 2]
                .chunks_exact(2)
                .map(|pt| {
                    let (dx, dy) = (pt[0] - anchor.x, pt[1] - anchor.y);
                    dx * dx + dy * dy
                })
                .fold(f32::INFINITY, f32::min);
            (map_valid[poly] <= 0.0, nearest, poly)
        })
        .collect();
    order.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
    for (slot, &(_, _, poly)) in order.iter().take(k).enumerate() {
        valid[slot] = map_valid[poly];
        let src = &map[poly * q * 2..][..q * 2];
        let dst = &mut points[slot * q * 2..][..q * 2];
        for (from, to) in src.chunks_exact(2).zip(dst.chunks_exact_mut(2)) {
            let (dx, dy) = (from[0] - anchor.x, from[1] - anchor.y);
            to[0] = anchor.cos * dx + anchor.sin * dy;
            to[1] = anchor.cos * dy - anchor.sin * dx;
        }
    }
}

/// Every agent's map of a batch: `anchors [B·A]`, `map [B, P, Q, 2]`, `map_valid [B, P]` →
/// (`points [B, A, K, Q, 2]`, `valid [B, A, K]`) with `K = polylines_per_agent(k, P)`.
pub fn agent_maps(
    anchors: &[MapAnchor],
    agents: usize,
    map: &[f32],
    map_valid: &[f32],
    points_per_polyline: usize,
    k: usize,
) -> (Vec<f32>, Vec<f32>) {
    let q = points_per_polyline;
    let scenes = anchors.len() / agents.max(1);
    let p = map_valid.len() / scenes.max(1);
    let k = polylines_per_agent(k, p);
    let mut points = vec![0.0; anchors.len() * k * q * 2];
    let mut valid = vec![0.0; anchors.len() * k];
    for (row, anchor) in anchors.iter().enumerate() {
        let scene = row / agents;
        agent_map(
            *anchor,
            &map[scene * p * q * 2..][..p * q * 2],
            &map_valid[scene * p..][..p],
            q,
            &mut points[row * k * q * 2..][..k * q * 2],
            &mut valid[row * k..][..k],
        );
    }
    (points, valid)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three two-point polylines: along +x at y = 0 (near the anchor), at y = 5 (far), and a
    /// padding one at the anchor itself (invalid: it must come last whatever its distance).
    fn map() -> (Vec<f32>, Vec<f32>) {
        #[rustfmt::skip]
        let map = vec![
            0.0, 0.0,  1.0, 0.0,
            0.0, 5.0,  1.0, 5.0,
            2.0, 1.0,  2.0, 1.0,
        ];
        (map, vec![1.0, 1.0, 0.0])
    }

    #[test]
    fn the_nearest_valid_polylines_come_first_in_the_anchor_frame() {
        let (map, map_valid) = map();
        // At (2, 1), heading +y (π/2): forward is the scene's +y, left the scene's −x.
        let anchor = MapAnchor {
            x: 2.0,
            y: 1.0,
            cos: 0.0,
            sin: 1.0,
        };
        let mut points = vec![0.0; 3 * 2 * 2];
        let mut valid = vec![0.0; 3];
        agent_map(anchor, &map, &map_valid, 2, &mut points, &mut valid);
        assert_eq!(valid, [1.0, 1.0, 0.0]);
        // Polyline 0: (0, 0) is 1 behind and 2 to the left; (1, 0) 1 behind, 1 left.
        // Polyline 1: (0, 5) is 4 ahead, 2 left; (1, 5) 4 ahead, 1 left. Padding: the anchor.
        let want = [-1.0, 2.0, -1.0, 1.0, 4.0, 2.0, 4.0, 1.0, 0.0, 0.0, 0.0, 0.0];
        for (got, want) in points.iter().zip(want) {
            assert!((got - want).abs() < 1e-6, "{points:?}");
        }
    }

    #[test]
    fn a_batch_gives_each_agent_its_own_pick_and_at_most_the_scene_s_polylines() {
        let (map, map_valid) = map();
        let near_far = MapAnchor {
            x: 0.0,
            y: 4.0,
            ..MapAnchor::SCENE
        };
        let (points, valid) = agent_maps(&[MapAnchor::SCENE, near_far], 2, &map, &map_valid, 2, 2);
        assert_eq!(valid, [1.0, 1.0, 1.0, 1.0]);
        // Agent 0 (the scene centre) starts with polyline 0, agent 1 (near y = 5) with 1.
        assert_eq!(&points[..4], &[0.0, 0.0, 1.0, 0.0]);
        assert_eq!(&points[8..12], &[0.0, 1.0, 1.0, 1.0]);
        let (_, valid) = agent_maps(&[MapAnchor::SCENE], 1, &map, &map_valid, 2, 10);
        assert_eq!(valid.len(), 3, "K is capped at the scene's polylines");
    }
}
