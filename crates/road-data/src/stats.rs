//! The figures `road data stats` prints, including a built-in check of the map projection:
//! per location, the median distance from track points to the nearest lane centre.

use std::collections::BTreeMap;

use glam::DVec2;
use serde::Serialize;

use crate::dataset::Dataset;

/// The projection check passes when every location's median is below this (metres).
pub const MAX_MEDIAN_LANE_DISTANCE_M: f64 = 1.5;

#[derive(Debug, Clone, Serialize)]
pub struct SplitStats {
    pub split: String,
    pub files: usize,
    pub hours: f64,
    pub windows: usize,
    pub agents_mean: f64,
    pub agents_p95: usize,
    pub agents_max: usize,
    /// RMS of valid agent positions around their window's centre, per axis (metres).
    pub position_rms_m: f64,
    pub windows_skipped_few_agents: usize,
    pub agents_dropped_over_max: usize,
    pub polylines_dropped_over_max: usize,
    pub missing_validation_files: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct LocationStats {
    pub location: String,
    pub files: usize,
    pub hours: f64,
    pub windows: usize,
    /// Lanelets, hence lane-centre polylines, in the map.
    pub polylines: usize,
    pub non_lanelet_relations: usize,
    pub track_points: usize,
    pub median_lane_distance_m: f64,
}

impl LocationStats {
    /// The projection check: the median is below the limit (a location without track points,
    /// whose median is NaN, fails).
    pub fn passes_projection_check(&self) -> bool {
        self.median_lane_distance_m < MAX_MEDIAN_LANE_DISTANCE_M
    }
}

pub fn split_stats(ds: &Dataset) -> SplitStats {
    let mut counts: Vec<usize> = ds.windows.iter().map(|w| w.agents.len()).collect();
    counts.sort_unstable();
    let mean = if counts.is_empty() {
        0.0
    } else {
        counts.iter().sum::<usize>() as f64 / counts.len() as f64
    };
    let p95 = percentile(&counts, 0.95);
    let (mut sum_sq, mut n) = (0.0f64, 0usize);
    for w in &ds.windows {
        let recording = &ds.recordings[w.recording as usize];
        for &t in &w.agents {
            let track = &recording.tracks[t as usize];
            for s in 0..ds.config.window_steps as u32 {
                if let Some([x, y, _]) = track.state_at(w.start_frame + s) {
                    let offset = DVec2::new(f64::from(x), f64::from(y)) - DVec2::from(w.origin_m);
                    sum_sq += offset.length_squared();
                    n += 2; // two axes
                }
            }
        }
    }
    SplitStats {
        split: ds.split.to_string(),
        files: ds.recordings.len(),
        hours: ds.recordings.iter().map(|r| r.duration_secs()).sum::<f64>() / 3600.0,
        windows: ds.windows.len(),
        agents_mean: mean,
        agents_p95: p95,
        agents_max: counts.last().copied().unwrap_or(0),
        position_rms_m: if n > 0 {
            (sum_sq / n as f64).sqrt()
        } else {
            0.0
        },
        windows_skipped_few_agents: ds.report.windows_skipped_few_agents,
        agents_dropped_over_max: ds.report.agents_dropped_over_max,
        polylines_dropped_over_max: ds.report.polylines_dropped_over_max,
        missing_validation_files: ds.report.missing_validation_files.clone(),
    }
}

/// Nearest-rank percentile of sorted values.
fn percentile(sorted: &[usize], q: f64) -> usize {
    if sorted.is_empty() {
        return 0;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

/// Per-location figures over several datasets (train and validation together).
pub fn location_stats(datasets: &[&Dataset]) -> Vec<LocationStats> {
    let mut by_location: BTreeMap<String, LocationStats> = BTreeMap::new();
    let mut distances: BTreeMap<String, Vec<f32>> = BTreeMap::new();
    for ds in datasets {
        for map in &ds.maps {
            let grid = map.centre_grid(10.0);
            let entry = by_location
                .entry(map.location.clone())
                .or_insert_with(|| LocationStats {
                    location: map.location.clone(),
                    files: 0,
                    hours: 0.0,
                    windows: 0,
                    polylines: map.lanelets.len(),
                    non_lanelet_relations: map.skipped.non_lanelet_relations,
                    track_points: 0,
                    median_lane_distance_m: f64::NAN,
                });
            let d = distances.entry(map.location.clone()).or_default();
            for recording in ds.recordings.iter().filter(|r| r.location == map.location) {
                entry.files += 1;
                entry.hours += recording.duration_secs() / 3600.0;
                for track in &recording.tracks {
                    for &[x, y, _] in &track.states {
                        let nearest = grid
                            .nearest_distance([f64::from(x), f64::from(y)])
                            .unwrap_or(f64::INFINITY);
                        d.push(nearest as f32);
                    }
                }
            }
        }
        for w in &ds.windows {
            let location = &ds.recordings[w.recording as usize].location;
            if let Some(entry) = by_location.get_mut(location) {
                entry.windows += 1;
            }
        }
    }
    for (location, entry) in &mut by_location {
        let d = distances
            .get_mut(location)
            .expect("every location has a distance list");
        entry.track_points = d.len();
        if !d.is_empty() {
            let mid = d.len() / 2;
            let (_, m, _) = d.select_nth_unstable_by(mid, f32::total_cmp);
            entry.median_lane_distance_m = f64::from(*m);
        }
    }
    by_location.into_values().collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentile() {
        let v: Vec<usize> = (1..=20).collect();
        assert_eq!(percentile(&v, 0.95), 19);
        assert_eq!(percentile(&v, 1.0), 20);
        assert_eq!(percentile(&[5], 0.95), 5);
        assert_eq!(percentile(&[], 0.95), 0);
    }
}
