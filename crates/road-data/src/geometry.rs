//! Small 2-D geometry: polyline resampling, point-to-segment distance, point in polygon, and a
//! uniform grid over segments for nearest-distance queries.
//!
//! Points are stored as `[f64; 2]` (the cache format); the math converts to `glam::DVec2` at
//! each function's boundary.

use glam::DVec2;
use serde::{Deserialize, Serialize};

pub type Point = [f64; 2];

pub fn dist(a: Point, b: Point) -> f64 {
    hypot_length(DVec2::from(a) - DVec2::from(b))
}

/// The length of `v` by `hypot`, the metric of [`dist`]. Not `DVec2::length` (`√(x² + y²)`),
/// which can differ in the last bit: the lanelet centre lines, window origins and polyline
/// choices stored in the dataset caches depend on it, and a rebuild must reproduce them.
pub fn hypot_length(v: DVec2) -> f64 {
    v.x.hypot(v.y)
}

/// Length of a polyline in its own units.
pub fn polyline_length(points: &[Point]) -> f64 {
    points.windows(2).map(|w| dist(w[0], w[1])).sum()
}

/// Resamples a polyline to `count` points evenly spaced by arc length (endpoints kept).
/// A polyline of one point (or zero length) repeats that point.
pub fn resample(points: &[Point], count: usize) -> Vec<Point> {
    assert!(count >= 2, "resample needs at least two output points");
    if points.is_empty() {
        return Vec::new();
    }
    let total = polyline_length(points);
    if points.len() == 1 || total == 0.0 {
        return vec![points[0]; count];
    }
    let mut out = Vec::with_capacity(count);
    let mut seg = 0;
    let mut seg_start = 0.0; // arc length at points[seg]
    for i in 0..count {
        let target = total * i as f64 / (count - 1) as f64;
        while seg + 2 < points.len() && seg_start + dist(points[seg], points[seg + 1]) < target {
            seg_start += dist(points[seg], points[seg + 1]);
            seg += 1;
        }
        let len = dist(points[seg], points[seg + 1]);
        let t = if len > 0.0 {
            ((target - seg_start) / len).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // `lerp_monotonic`, a + (b − a)·t, not `lerp`, a·(1 − t) + b·t: the form the cached
        // centre lines were resampled with, bit for bit.
        let (a, b) = (DVec2::from(points[seg]), DVec2::from(points[seg + 1]));
        out.push(a.lerp_monotonic(b, t).into());
    }
    out
}

/// Distance from `p` to segment `a–b`.
pub fn point_segment_distance(p: Point, a: Point, b: Point) -> f64 {
    let (p, a) = (DVec2::from(p), DVec2::from(a));
    let along = DVec2::from(b) - a;
    let length_sq = along.length_squared();
    let t = if length_sq > 0.0 {
        ((p - a).dot(along) / length_sq).clamp(0.0, 1.0)
    } else {
        0.0
    };
    hypot_length(p - (a + along * t))
}

/// Even-odd rule; the polygon is implicitly closed.
pub fn point_in_polygon(p: Point, polygon: &[Point]) -> bool {
    let mut inside = false;
    let n = polygon.len();
    for i in 0..n {
        let (a, b) = (polygon[i], polygon[(i + 1) % n]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                inside = !inside;
            }
        }
    }
    inside
}

/// Axis-aligned bounding box.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Point,
    pub max: Point,
}

impl Aabb {
    pub fn of(points: &[Point]) -> Self {
        let (min, max) = points
            .iter()
            .map(|&p| DVec2::from(p))
            .fold((DVec2::INFINITY, DVec2::NEG_INFINITY), |(min, max), p| {
                (min.min(p), max.max(p))
            });
        Self {
            min: min.into(),
            max: max.into(),
        }
    }

    pub fn contains(&self, p: Point) -> bool {
        p[0] >= self.min[0] && p[0] <= self.max[0] && p[1] >= self.min[1] && p[1] <= self.max[1]
    }

    /// Whether the two boxes share a point.
    pub fn overlaps(&self, other: &Aabb) -> bool {
        self.min[0] <= other.max[0]
            && other.min[0] <= self.max[0]
            && self.min[1] <= other.max[1]
            && other.min[1] <= self.max[1]
    }

    /// Distance from `p` to the box (0 inside).
    pub fn distance(&self, p: Point) -> f64 {
        let p = DVec2::from(p);
        let gap = (DVec2::from(self.min) - p)
            .max(p - DVec2::from(self.max))
            .max(DVec2::ZERO);
        hypot_length(gap)
    }
}

/// Uniform grid over line segments for nearest-segment distance queries.
#[derive(Debug, Clone)]
pub struct SegmentGrid {
    cell_m: f64,
    origin: DVec2,
    cols: usize,
    rows: usize,
    cells: Vec<Vec<u32>>, // [rows * cols] → segment indices
    segments: Vec<(Point, Point)>,
}

impl SegmentGrid {
    pub fn new(segments: Vec<(Point, Point)>, cell_m: f64) -> Self {
        let pts: Vec<Point> = segments.iter().flat_map(|&(a, b)| [a, b]).collect();
        let bounds = if pts.is_empty() {
            Aabb {
                min: [0.0; 2],
                max: [0.0; 2],
            }
        } else {
            Aabb::of(&pts)
        };
        let (min, max) = (DVec2::from(bounds.min), DVec2::from(bounds.max));
        let spanned = ((max - min) / cell_m).floor();
        let (cols, rows) = (spanned.x as usize + 1, spanned.y as usize + 1);
        let mut grid = Self {
            cell_m,
            origin: min,
            cols,
            rows,
            cells: vec![Vec::new(); cols * rows],
            segments,
        };
        for (i, &(a, b)) in grid.segments.iter().enumerate() {
            let bb = Aabb::of(&[a, b]);
            let (c0, r0) = grid.cell_of(bb.min);
            let (c1, r1) = grid.cell_of(bb.max);
            for r in r0..=r1 {
                for c in c0..=c1 {
                    grid.cells[r * cols + c].push(i as u32);
                }
            }
        }
        grid
    }

    fn cell_of(&self, p: Point) -> (usize, usize) {
        let last = DVec2::new((self.cols - 1) as f64, (self.rows - 1) as f64);
        let cell = ((DVec2::from(p) - self.origin) / self.cell_m)
            .floor()
            .clamp(DVec2::ZERO, last);
        (cell.x as usize, cell.y as usize)
    }

    /// Distance from `p` to the nearest segment; `None` when the grid holds none.
    pub fn nearest_distance(&self, p: Point) -> Option<f64> {
        if self.segments.is_empty() {
            return None;
        }
        let (pc, pr) = self.cell_of(p);
        // Distance from p to the grid's own box: rings closer than that hold nothing.
        let outside = Aabb {
            min: self.origin.into(),
            max: (self.origin + DVec2::new(self.cols as f64, self.rows as f64) * self.cell_m)
                .into(),
        }
        .distance(p);
        let mut best = f64::INFINITY;
        let max_ring = self.cols.max(self.rows);
        for ring in 0..=max_ring {
            // Every segment not yet seen lies at least this far away.
            let ring_floor = outside.max((ring as f64 - 1.0) * self.cell_m);
            if best <= ring_floor {
                break;
            }
            let (r0, r1) = (pr.saturating_sub(ring), (pr + ring).min(self.rows - 1));
            let (c0, c1) = (pc.saturating_sub(ring), (pc + ring).min(self.cols - 1));
            for r in r0..=r1 {
                for c in c0..=c1 {
                    let on_ring = r == pr.saturating_sub(ring) && pr >= ring
                        || r == pr + ring
                        || c == pc.saturating_sub(ring) && pc >= ring
                        || c == pc + ring;
                    if ring > 0 && !on_ring {
                        continue;
                    }
                    for &s in &self.cells[r * self.cols + c] {
                        let (a, b) = self.segments[s as usize];
                        best = best.min(point_segment_distance(p, a, b));
                    }
                }
            }
        }
        Some(best)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn resample_keeps_endpoints_and_spacing() {
        let line = [[0.0, 0.0], [1.0, 0.0], [1.0, 3.0]];
        let r = resample(&line, 5);
        assert_eq!(r.len(), 5);
        assert_eq!(r[0], [0.0, 0.0]);
        assert_eq!(r[4], [1.0, 3.0]);
        assert!((dist(r[1], [1.0, 0.0])).abs() < 1e-12);
        for w in r.windows(2) {
            assert!((dist(w[0], w[1]) - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn polygon_containment() {
        let square = [[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]];
        assert!(point_in_polygon([1.0, 1.0], &square));
        assert!(!point_in_polygon([3.0, 1.0], &square));
        assert!(!point_in_polygon([1.0, -0.1], &square));
    }

    proptest! {
        #[test]
        fn grid_matches_brute_force(
            segs in prop::collection::vec(((-50.0f64..50.0, -50.0f64..50.0), (-50.0f64..50.0, -50.0f64..50.0)), 1..40),
            p in (-120.0f64..120.0, -120.0f64..120.0),
            cell in 1.0f64..20.0,
        ) {
            let segments: Vec<(Point, Point)> = segs.iter().map(|&((ax, ay), (bx, by))| ([ax, ay], [bx, by])).collect();
            let brute = segments.iter().map(|&(a, b)| point_segment_distance([p.0, p.1], a, b)).fold(f64::INFINITY, f64::min);
            let grid = SegmentGrid::new(segments, cell);
            let got = grid.nearest_distance([p.0, p.1]).unwrap();
            prop_assert!((got - brute).abs() < 1e-9, "grid {got} vs brute force {brute}");
        }
    }
}
