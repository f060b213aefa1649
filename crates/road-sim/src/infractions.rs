//! Infractions of one tick: collisions (oriented boxes) and off-road (centre outside every
//! lanelet).

use road_data::LaneletMap;

use crate::geometry::OrientedBox;

/// Pairs `(i, j)`, `i < j`, of present agents whose boxes overlap.
pub fn collisions(boxes: &[Option<OrientedBox>]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    for i in 0..boxes.len() {
        let Some(a) = &boxes[i] else { continue };
        for (j, b) in boxes.iter().enumerate().skip(i + 1) {
            if let Some(b) = b {
                if a.overlaps(b) {
                    out.push((i, j));
                }
            }
        }
    }
    out
}

/// Agents (indices) whose centre lies outside every lanelet of `map`.
pub fn off_road(boxes: &[Option<OrientedBox>], map: &LaneletMap) -> Vec<usize> {
    boxes
        .iter()
        .enumerate()
        .filter_map(|(i, b)| {
            b.as_ref()
                .filter(|b| map.lanelet_at([b.pose.x_m, b.pose.y_m]).is_none())
                .map(|_| i)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Pose;

    #[test]
    fn collisions_skip_absent_agents() {
        let car = |x: f64| {
            Some(OrientedBox {
                pose: Pose {
                    x_m: x,
                    y_m: 0.0,
                    heading_rad: 0.0,
                },
                length_m: 4.0,
                width_m: 2.0,
            })
        };
        assert_eq!(
            collisions(&[car(0.0), None, car(3.0), car(20.0)]),
            vec![(0, 2)]
        );
        assert!(collisions(&[car(0.0), car(10.0)]).is_empty());
    }
}
