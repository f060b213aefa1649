//! How realistic a scene's initial state is, against the recordings (`road eval --suite
//! initialisation`, issue 39): per vehicle its speed, its offset from the nearest lane centre,
//! its heading against that lane, the gap to the vehicle ahead; per scene the vehicles that
//! overlap another or stand off the road. Distributions compare by Jensen–Shannon distance
//! over fixed bins ([`js_distance`]).

use glam::DVec2;
use road_data::LaneletMap;
use road_data::tracks::STEP_SECS;

use crate::Pose;
use crate::geometry::OrientedBox;
use crate::infractions::{collisions, off_road};

/// The vehicle ahead: the nearest other vehicle whose centre lies ahead within this distance
/// (metres), within [`AHEAD_HALF_WIDTH_M`] of the vehicle's axis.
pub const AHEAD_MAX_M: f64 = 50.0;
pub const AHEAD_HALF_WIDTH_M: f64 = 2.0;

/// One vehicle of a scene at its initial step: where it is now and a step before, its size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InitialVehicle {
    pub before: Pose,
    pub now: Pose,
    pub length_m: f64,
    pub width_m: f64,
}

/// The features of a set of initial states, pooled over scenes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InitFeatures {
    pub speed_mps: Vec<f64>,
    /// Distance from the vehicle's centre to the nearest lane centre line.
    pub lane_offset_m: Vec<f64>,
    /// |heading − the direction of that nearest centre line| in [0, π/2] (lanes run either way
    /// under a vehicle on a two-way road's centre line, so the direction is taken modulo π).
    pub heading_offset_rad: Vec<f64>,
    /// Gap (centre to centre) to the vehicle ahead, where there is one within
    /// [`AHEAD_MAX_M`].
    pub gap_ahead_m: Vec<f64>,
    pub vehicles: usize,
    /// Vehicles overlapping another, and standing with their centre off every lanelet.
    pub overlapping: usize,
    pub off_road: usize,
}

impl InitFeatures {
    /// Adds one scene's vehicles; `counted[i]` false leaves vehicle `i` out of the per-vehicle
    /// features (a fixed ego) while it still counts as another's neighbour.
    pub fn add_scene(&mut self, map: &LaneletMap, vehicles: &[InitialVehicle], counted: &[bool]) {
        let boxes: Vec<Option<OrientedBox>> = vehicles
            .iter()
            .map(|v| {
                Some(OrientedBox {
                    pose: v.now,
                    length_m: v.length_m,
                    width_m: v.width_m,
                })
            })
            .collect();
        let mut overlapping = vec![false; vehicles.len()];
        for (i, j) in collisions(&boxes) {
            overlapping[i] = true;
            overlapping[j] = true;
        }
        let off = off_road(&boxes, map);
        for (i, v) in vehicles.iter().enumerate() {
            if !counted[i] {
                continue;
            }
            self.vehicles += 1;
            self.overlapping += usize::from(overlapping[i]);
            self.off_road += usize::from(off.contains(&i));
            let step = v.now.position_m() - v.before.position_m();
            self.speed_mps.push(step.length() / STEP_SECS);
            if let Some((offset, direction)) = nearest_centre(map, v.now.position_m()) {
                self.lane_offset_m.push(offset);
                let turn = (v.now.heading_rad - direction).rem_euclid(std::f64::consts::PI);
                self.heading_offset_rad
                    .push(turn.min(std::f64::consts::PI - turn));
            }
            let forward = DVec2::from_angle(v.now.heading_rad);
            let gap = vehicles
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .filter_map(|(_, o)| {
                    let d = o.now.position_m() - v.now.position_m();
                    let along = d.dot(forward);
                    (along > 0.0
                        && along <= AHEAD_MAX_M
                        && d.perp_dot(forward).abs() <= AHEAD_HALF_WIDTH_M)
                        .then_some(d.length())
                })
                .fold(f64::INFINITY, f64::min);
            if gap.is_finite() {
                self.gap_ahead_m.push(gap);
            }
        }
    }

    pub fn overlapping_share(&self) -> f64 {
        self.overlapping as f64 / self.vehicles.max(1) as f64
    }

    pub fn off_road_share(&self) -> f64 {
        self.off_road as f64 / self.vehicles.max(1) as f64
    }
}

/// The distance from `at` to the nearest lane centre line of `map`, and that line's direction
/// there (radians); `None` for a map without lanes.
pub fn nearest_centre(map: &LaneletMap, at: DVec2) -> Option<(f64, f64)> {
    nearest_centre_where(map, at, |_| true).map(|(dist, _, direction)| (dist, direction.to_angle()))
}

/// The point nearest `at` on the centre lines of `map` whose segments `keep` (given a segment's
/// unit direction): its distance, the point, the segment's unit direction.
pub fn nearest_centre_where(
    map: &LaneletMap,
    at: DVec2,
    keep: impl Fn(DVec2) -> bool,
) -> Option<(f64, DVec2, DVec2)> {
    nearest_centre_on(&map.lanelets, at, keep)
}

/// [`nearest_centre_where`] over the centre lines of `lanes` only.
pub fn nearest_centre_on<'a>(
    lanes: impl IntoIterator<Item = &'a road_data::map::Lanelet>,
    at: DVec2,
    keep: impl Fn(DVec2) -> bool,
) -> Option<(f64, DVec2, DVec2)> {
    let mut best: Option<(f64, DVec2, DVec2)> = None;
    for lane in lanes {
        for seg in lane.centre_m.windows(2) {
            let (p, q) = (DVec2::from(seg[0]), DVec2::from(seg[1]));
            let d = q - p;
            let len2 = d.length_squared();
            if len2 < 1e-12 {
                continue;
            }
            let direction = d / len2.sqrt();
            if !keep(direction) {
                continue;
            }
            let t = ((at - p).dot(d) / len2).clamp(0.0, 1.0);
            let closest = p + d * t;
            let dist = (at - closest).length();
            if best.is_none_or(|(b, _, _)| dist < b) {
                best = Some((dist, closest, direction));
            }
        }
    }
    best
}

/// Equal bins over `[low, high)`; values outside fall in the first or last.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bins {
    pub low: f64,
    pub high: f64,
    pub count: usize,
}

impl Bins {
    fn histogram(&self, values: &[f64]) -> Vec<f64> {
        let mut h = vec![0.0; self.count];
        let width = (self.high - self.low) / self.count as f64;
        for &v in values {
            let k = ((v - self.low) / width).floor();
            let k = if k.is_nan() { 0.0 } else { k };
            h[(k.max(0.0) as usize).min(self.count - 1)] += 1.0;
        }
        let total: f64 = h.iter().sum();
        if total > 0.0 {
            h.iter_mut().for_each(|x| *x /= total);
        }
        h
    }
}

/// The bins of each feature: speed 0–20 m/s by 1, lane offset 0–4 m by 0.25, heading offset
/// 0–π/2 by 5°, gap ahead 0–50 m by 2.5.
pub const SPEED_BINS: Bins = Bins {
    low: 0.0,
    high: 20.0,
    count: 20,
};
pub const LANE_OFFSET_BINS: Bins = Bins {
    low: 0.0,
    high: 4.0,
    count: 16,
};
pub const HEADING_OFFSET_BINS: Bins = Bins {
    low: 0.0,
    high: std::f64::consts::FRAC_PI_2,
    count: 18,
};
pub const GAP_BINS: Bins = Bins {
    low: 0.0,
    high: 50.0,
    count: 20,
};

/// The Jensen–Shannon distance (the square root of the divergence, base 2: 0 for equal
/// distributions, 1 for disjoint ones) between the histograms of `a` and `b` over `bins`;
/// NaN when either is empty.
pub fn js_distance(a: &[f64], b: &[f64], bins: Bins) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::NAN;
    }
    let (p, q) = (bins.histogram(a), bins.histogram(b));
    let kl = |x: &[f64], m: &[f64]| -> f64 {
        x.iter()
            .zip(m)
            .filter(|&(&xi, _)| xi > 0.0)
            .map(|(&xi, &mi)| xi * (xi / mi).log2())
            .sum()
    };
    let m: Vec<f64> = p.iter().zip(&q).map(|(x, y)| 0.5 * (x + y)).collect();
    (0.5 * kl(&p, &m) + 0.5 * kl(&q, &m)).max(0.0).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural::{ProceduralMap, procedural};
    use road_data::WindowConfig;

    #[test]
    fn js_distance_is_zero_for_equal_and_one_for_disjoint_samples() {
        let a = [1.0, 2.0, 3.0];
        assert!(js_distance(&a, &a, SPEED_BINS).abs() < 1e-12);
        assert!((js_distance(&[1.5], &[10.5], SPEED_BINS) - 1.0).abs() < 1e-12);
        let half = js_distance(&[1.5, 10.5], &[1.5], SPEED_BINS);
        assert!(half > 0.0 && half < 1.0);
        assert!(js_distance(&[], &a, SPEED_BINS).is_nan());
    }

    #[test]
    fn features_of_a_vehicle_on_a_lane_and_one_behind_it() {
        let scene = procedural(ProceduralMap::Merge, &WindowConfig::default(), 10).unwrap();
        // Two vehicles on the main road (along +x at y = 0), 20 m apart, at 8 m/s; a third
        // 1 m off the centre line, turned 10° off it.
        let at = |x: f64, y: f64, h: f64| Pose {
            x_m: x,
            y_m: y,
            heading_rad: h,
        };
        let car = |x: f64, y: f64, h: f64| InitialVehicle {
            before: at(x - 0.8 * h.cos(), y - 0.8 * h.sin(), h),
            now: at(x, y, h),
            length_m: 4.5,
            width_m: 1.8,
        };
        let vehicles = [
            car(-60.0, 0.0, 0.0),
            car(-40.0, 0.0, 0.0),
            car(-10.0, 1.0, 10f64.to_radians()),
        ];
        let mut f = InitFeatures::default();
        f.add_scene(&scene.map, &vehicles, &[true, true, true]);
        assert_eq!(f.vehicles, 3);
        assert!(f.speed_mps.iter().all(|&v| (v - 8.0).abs() < 1e-9));
        assert!(f.lane_offset_m[0] < 1e-6 && (f.lane_offset_m[2] - 1.0).abs() < 1e-6);
        assert!((f.heading_offset_rad[2] - 10f64.to_radians()).abs() < 1e-6);
        // Vehicle 0 has 1 ahead at 20 m; 1 has 2 ahead at 30 m and 1 m aside; 2 none.
        assert_eq!(f.gap_ahead_m.len(), 2);
        assert!((f.gap_ahead_m[0] - 20.0).abs() < 1e-9);
        assert_eq!((f.overlapping, f.off_road), (0, 0));
        // Left out of the features, still a neighbour.
        let mut g = InitFeatures::default();
        g.add_scene(&scene.map, &vehicles, &[true, false, false]);
        assert_eq!((g.vehicles, g.gap_ahead_m.len()), (1, 1));
    }
}
