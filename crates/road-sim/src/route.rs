//! A path to drive along (a route through lane centre lines), by arc length: the procedural
//! maps' scripted vehicles and the placed vehicles' histories follow one.

use glam::DVec2;
use road_data::geometry::{Point, dist};

use crate::Pose;

/// A path to drive along, by arc length.
#[derive(Debug, Clone, PartialEq)]
pub struct Route {
    points: Vec<Point>,
    arc_m: Vec<f64>,
}

impl Route {
    /// A route through `points` (consecutive duplicates dropped).
    pub fn new(points: Vec<Point>) -> Self {
        let mut kept: Vec<Point> = Vec::with_capacity(points.len());
        for p in points {
            if kept.last().is_none_or(|&q| dist(p, q) > 1e-6) {
                kept.push(p);
            }
        }
        let mut arc_m = vec![0.0; kept.len()];
        for i in 1..kept.len() {
            arc_m[i] = arc_m[i - 1] + dist(kept[i - 1], kept[i]);
        }
        Self {
            points: kept,
            arc_m,
        }
    }

    /// The points it runs through.
    pub fn into_points(self) -> Vec<Point> {
        self.points
    }

    pub fn length_m(&self) -> f64 {
        self.arc_m.last().copied().unwrap_or(0.0)
    }

    /// The pose at arc length `s_m`, clamped to the route; the heading is the segment's.
    pub fn pose_at(&self, s_m: f64) -> Pose {
        let s = s_m.clamp(0.0, self.length_m());
        let seg = self
            .arc_m
            .partition_point(|&a| a < s)
            .clamp(1, self.points.len() - 1);
        let (a, b) = (
            DVec2::from(self.points[seg - 1]),
            DVec2::from(self.points[seg]),
        );
        let len = self.arc_m[seg] - self.arc_m[seg - 1];
        let t = if len > 0.0 {
            (s - self.arc_m[seg - 1]) / len
        } else {
            0.0
        };
        // a + (b − a)·t, the form used before glam (`lerp` rounds differently).
        Pose::at(a.lerp_monotonic(b, t), (b - a).to_angle())
    }
}
