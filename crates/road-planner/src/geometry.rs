//! Oriented boxes and the separating-axis test.

use glam::DVec2;

use crate::Pose;

/// An agent's footprint: a rectangle centred on its pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrientedBox {
    pub pose: Pose,
    pub length_m: f64,
    pub width_m: f64,
}

impl OrientedBox {
    /// The unit vector along the heading and the one to its left.
    fn axes(&self) -> (DVec2, DVec2) {
        let forward = DVec2::from_angle(self.pose.heading_rad);
        (forward, forward.perp())
    }

    /// The four corners, counter-clockwise.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        let centre = self.pose.position_m();
        let (forward, left) = self.axes();
        let (hl, hw) = (self.length_m / 2.0, self.width_m / 2.0);
        [(hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)]
            .map(|(l, w)| (centre + l * forward + w * left).to_array())
    }

    /// True when the boxes overlap (touching counts): no separating axis among the four edge
    /// normals.
    pub fn overlaps(&self, other: &OrientedBox) -> bool {
        let (a, b) = (self.corners(), other.corners());
        let ((fa, la), (fb, lb)) = (self.axes(), other.axes());
        [fa, la, fb, lb].iter().all(|axis| {
            let project = |pts: &[[f64; 2]; 4]| {
                pts.iter()
                    .map(|&p| DVec2::from(p).dot(*axis))
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                        (lo.min(v), hi.max(v))
                    })
            };
            let ((a0, a1), (b0, b1)) = (project(&a), project(&b));
            a0 <= b1 && b0 <= a1
        })
    }

    /// The distance between the two boxes' outlines (metres), 0 when they overlap. Two
    /// separate convex outlines are nearest at a corner of one and an edge of the other.
    pub fn gap_m(&self, other: &OrientedBox) -> f64 {
        if self.overlaps(other) {
            return 0.0;
        }
        let (a, b) = (
            self.corners().map(DVec2::from),
            other.corners().map(DVec2::from),
        );
        let to_outline = |p: DVec2, outline: &[DVec2; 4]| {
            (0..4)
                .map(|k| point_to_segment_m(p, outline[k], outline[(k + 1) % 4]))
                .fold(f64::INFINITY, f64::min)
        };
        a.iter()
            .map(|&p| to_outline(p, &b))
            .chain(b.iter().map(|&p| to_outline(p, &a)))
            .fold(f64::INFINITY, f64::min)
    }
}

/// The distance from `p` to the segment from `start` to `end` (metres).
fn point_to_segment_m(p: DVec2, start: DVec2, end: DVec2) -> f64 {
    let along = end - start;
    let t = if along.length_squared() > 0.0 {
        ((p - start).dot(along) / along.length_squared()).clamp(0.0, 1.0)
    } else {
        0.0
    };
    p.distance(start + t * along)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn car(x: f64, y: f64, h: f64) -> OrientedBox {
        OrientedBox {
            pose: Pose {
                x_m: x,
                y_m: y,
                heading_rad: h,
            },
            length_m: 4.0,
            width_m: 2.0,
        }
    }

    #[test]
    fn axis_aligned_and_rotated_cases() {
        assert!(car(0.0, 0.0, 0.0).overlaps(&car(3.9, 0.0, 0.0)));
        assert!(!car(0.0, 0.0, 0.0).overlaps(&car(4.1, 0.0, 0.0)));
        assert!(!car(0.0, 0.0, 0.0).overlaps(&car(0.0, 2.1, 0.0)));
        // Side by side but one turned 90°: its length now spans y.
        assert!(car(0.0, 0.0, 0.0).overlaps(&car(0.0, 2.9, std::f64::consts::FRAC_PI_2)));
        assert!(!car(0.0, 0.0, 0.0).overlaps(&car(0.0, 3.1, std::f64::consts::FRAC_PI_2)));
        // Diagonal near miss: corners pass each other at 45°.
        assert!(!car(0.0, 0.0, 0.0).overlaps(&car(3.3, 2.7, std::f64::consts::FRAC_PI_4)));
        assert!(car(0.0, 0.0, 0.0).overlaps(&car(3.2, 2.6, std::f64::consts::FRAC_PI_4)));
    }

    #[test]
    fn the_gap_between_outlines() {
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(car(0.0, 0.0, 0.0).gap_m(&car(4.5, 0.0, 0.0)), 0.5));
        assert!(close(car(0.0, 0.0, 0.0).gap_m(&car(1.0, 2.25, 0.0)), 0.25));
        assert_eq!(car(0.0, 0.0, 0.0).gap_m(&car(3.9, 0.0, 0.0)), 0.0);
        // Corner to corner: 4 × 2 boxes 8 m east and 4 m north of each other, the nearest
        // corners (2, 1) and (6, 3).
        assert!(close(
            car(0.0, 0.0, 0.0).gap_m(&car(8.0, 4.0, 0.0)),
            20f64.sqrt()
        ));
        // A box turned 90° with its side 1 m from the other's end.
        assert!(close(
            car(0.0, 0.0, 0.0).gap_m(&car(4.0, 0.0, std::f64::consts::FRAC_PI_2)),
            1.0
        ));
    }

    proptest! {
        #[test]
        fn the_gap_is_symmetric_and_zero_only_on_overlap(x in -8.0f64..8.0, y in -8.0f64..8.0, h1 in -3.2f64..3.2, h2 in -3.2f64..3.2) {
            let (a, b) = (car(0.0, 0.0, h1), car(x, y, h2));
            prop_assert!((a.gap_m(&b) - b.gap_m(&a)).abs() < 1e-9);
            prop_assert_eq!(a.gap_m(&b) == 0.0, a.overlaps(&b));
            // No farther than the centres, less the narrow sides' halves.
            prop_assert!(a.gap_m(&b) <= DVec2::new(x, y).length());
        }

        #[test]
        fn overlap_is_symmetric_and_rigid(x in -8.0f64..8.0, y in -8.0f64..8.0, h1 in -3.2f64..3.2, h2 in -3.2f64..3.2, shift in (-50.0f64..50.0, -50.0f64..50.0), turn in -3.2f64..3.2) {
            let (a, b) = (car(0.0, 0.0, h1), car(x, y, h2));
            prop_assert_eq!(a.overlaps(&b), b.overlaps(&a));
            // Moving and turning both boxes together changes nothing (exact touching, where
            // rounding could decide, has probability zero here).
            let (rotation, shift) = (DVec2::from_angle(turn), DVec2::from(shift));
            let moved = |o: &OrientedBox| {
                let position = rotation.rotate(o.pose.position_m()) + shift;
                OrientedBox { pose: Pose::at(position, o.pose.heading_rad + turn), ..*o }
            };
            prop_assert_eq!(a.overlaps(&b), moved(&a).overlaps(&moved(&b)));
            // Centres closer than the narrow side always overlap; farther than the diagonal never.
            let d = DVec2::new(x, y).length();
            if d < 2.0 { prop_assert!(a.overlaps(&b)); }
            if d > 2.0 * (4.0f64.hypot(2.0)) / 2.0 + 0.01 { prop_assert!(!a.overlaps(&b)); }
        }
    }
}
