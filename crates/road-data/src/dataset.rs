//! Scene windows over recordings, in a normalised scene frame.
//!
//! A dataset keeps its recordings' tracks and maps once and indexes windows into them
//! ([`WindowRef`]: which agents and polylines, where the scene centre is), so the cache stays
//! small; [`Dataset::window`] materialises one [`SceneWindow`] on demand.
//!
//! Heading: stored unwrapped along each agent's window (continuous, the first valid step in
//! (−π, π]), so that it does not break at ±π; the model chooses its own encoding.

use std::path::Path;

use glam::{DVec2, Vec2};
use serde::{Deserialize, Serialize};

use crate::geometry::{Point, dist, resample};
use crate::map::LaneletMap;
use crate::sources::{SourceSet, Split, TrackSource};
use crate::tracks::{AgentType, Recording};
use crate::{Error, Result};

/// How windows are cut. `Default` matches `configs/data.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WindowConfig {
    /// Steps per window (10 Hz): 40 = 1 s observed + 3 s future.
    pub window_steps: usize,
    /// Steps between the starts of consecutive windows.
    pub stride_steps: usize,
    /// The window's "present" step: agents valid here belong to the window and the scene
    /// centre is their mean position here.
    pub reference_step: usize,
    /// Windows with fewer agents are skipped (and counted).
    pub min_agents: usize,
    /// Agents beyond this, farthest from the centre first, are dropped (and counted).
    pub max_agents: usize,
    /// Lanelets with any bound point within this distance of the centre are the window's map.
    pub map_radius_m: f64,
    /// Points per map polyline (lane centre line, resampled).
    pub polyline_points: usize,
    /// Polylines beyond this, farthest first, are dropped (and counted).
    pub max_polylines: usize,
    /// Metres per normalised unit: positions are `(p − centre) / position_scale_m`.
    pub position_scale_m: f64,
}

impl Default for WindowConfig {
    fn default() -> Self {
        Self {
            window_steps: 40,
            stride_steps: 10,
            reference_step: 9,
            min_agents: 2,
            max_agents: 32,
            map_radius_m: 60.0,
            polyline_points: 20,
            max_polylines: 96,
            position_scale_m: 40.0,
        }
    }
}

impl WindowConfig {
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: Self = toml::from_str(&text).map_err(|e| Error::Config {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        config.validate().map_err(|reason| Error::Config {
            path: path.to_owned(),
            reason,
        })?;
        Ok(config)
    }

    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.window_steps < 2 {
            return Err(format!(
                "window_steps must be at least 2, got {}",
                self.window_steps
            ));
        }
        if self.stride_steps == 0 {
            return Err("stride_steps must be at least 1".into());
        }
        if self.reference_step >= self.window_steps {
            return Err(format!(
                "reference_step ({}) must be below window_steps ({})",
                self.reference_step, self.window_steps
            ));
        }
        if self.min_agents == 0 || self.max_agents < self.min_agents {
            return Err(format!(
                "need 1 ≤ min_agents ≤ max_agents, got {} and {}",
                self.min_agents, self.max_agents
            ));
        }
        if self.polyline_points < 2 {
            return Err("polyline_points must be at least 2".into());
        }
        if !(self.position_scale_m > 0.0 && self.map_radius_m > 0.0) {
            return Err("position_scale_m and map_radius_m must be positive".into());
        }
        Ok(())
    }
}

/// The normalised scene frame: `p_norm = (p_m − origin_m) / scale_m`; headings unchanged.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneFrame {
    pub origin_m: [f64; 2],
    pub scale_m: f64,
}

impl SceneFrame {
    pub fn to_norm(&self, p_m: Point) -> [f32; 2] {
        ((DVec2::from(p_m) - DVec2::from(self.origin_m)) / self.scale_m)
            .as_vec2()
            .into()
    }

    /// The inverse transform back to metres.
    pub fn to_metres(&self, p: [f32; 2]) -> Point {
        (Vec2::from(p).as_dvec2() * self.scale_m + DVec2::from(self.origin_m)).into()
    }
}

/// One window of the index: enough to materialise it from the dataset's recordings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WindowRef {
    pub recording: u32,
    pub start_frame: u32,
    pub origin_m: [f64; 2],
    /// Track indices in the recording, nearest to the centre first.
    pub agents: Vec<u32>,
    /// Lanelet indices in the location's map, nearest first.
    pub polylines: Vec<u32>,
}

/// What a build skipped or dropped on purpose.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct BuildReport {
    pub files: usize,
    pub windows: usize,
    /// Window positions with fewer than `min_agents` agents present at the reference step.
    pub windows_skipped_few_agents: usize,
    /// Agents left out because a window held more than `max_agents`.
    pub agents_dropped_over_max: usize,
    /// Polylines left out because a window had more than `max_polylines` nearby.
    pub polylines_dropped_over_max: usize,
    /// Validation-list files absent from this copy (only reported with the validation split).
    pub missing_validation_files: Vec<String>,
}

/// One materialised window, normalised.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneWindow {
    pub location: String,
    pub file: String,
    pub start_frame: u32,
    pub frame: SceneFrame,
    pub agents: usize,
    pub steps: usize,
    /// `[agents, steps, 3]`: normalised x, y and unwrapped heading (rad); 0 where invalid.
    pub states: Vec<f32>,
    /// `[agents, steps]`.
    pub valid: Vec<bool>,
    pub track_ids: Vec<u32>,
    pub agent_types: Vec<AgentType>,
    pub length_m: Vec<f32>,
    pub width_m: Vec<f32>,
    pub polyline_points: usize,
    /// `[polylines, points, 2]`, normalised.
    pub polylines: Vec<f32>,
    pub polyline_lanelet_ids: Vec<i64>,
}

impl SceneWindow {
    pub fn state(&self, agent: usize, step: usize) -> Option<[f32; 3]> {
        let i = agent * self.steps + step;
        self.valid[i].then(|| {
            [
                self.states[3 * i],
                self.states[3 * i + 1],
                self.states[3 * i + 2],
            ]
        })
    }

    pub fn polyline_count(&self) -> usize {
        self.polyline_lanelet_ids.len()
    }
}

/// A split's recordings, maps and window index.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Dataset {
    pub split: Split,
    pub config: WindowConfig,
    pub sources: Vec<TrackSource>,
    pub maps: Vec<LaneletMap>,
    pub recordings: Vec<Recording>,
    /// Map index of each recording.
    pub recording_map: Vec<u32>,
    pub windows: Vec<WindowRef>,
    pub report: BuildReport,
}

impl Dataset {
    /// Parses one split's files and cuts its windows.
    pub fn build(sources: &SourceSet, split: Split, config: &WindowConfig) -> Result<Self> {
        config.validate().map_err(|reason| Error::Config {
            path: "window config".into(),
            reason,
        })?;
        let files = sources.split(split);
        let mut maps: Vec<LaneletMap> = Vec::new();
        let mut recordings = Vec::with_capacity(files.len());
        let mut recording_map = Vec::with_capacity(files.len());
        // Two workers: parsing dominates and the machine has two cores.
        let parsed: Vec<Result<Recording>> = std::thread::scope(|s| {
            let chunks: Vec<&[TrackSource]> =
                files.chunks(files.len().div_ceil(2).max(1)).collect();
            let handles: Vec<_> = chunks
                .into_iter()
                .map(|chunk| {
                    s.spawn(move || {
                        chunk
                            .iter()
                            .map(|f| {
                                Recording::load(&sources.root.join(&f.relative_path), &f.location)
                            })
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().expect("parser thread panicked"))
                .collect()
        });
        for recording in parsed {
            let recording = recording?;
            let map_index = match maps.iter().position(|m| m.location == recording.location) {
                Some(i) => i,
                None => {
                    let path = &sources.maps[&recording.location];
                    maps.push(LaneletMap::load(path, &recording.location)?);
                    maps.len() - 1
                }
            };
            recordings.push(recording);
            recording_map.push(map_index as u32);
        }
        let mut ds = Self::from_parts(split, config, maps, recordings, recording_map)?;
        ds.sources = files.to_vec();
        if split == Split::Validation {
            ds.report.missing_validation_files = sources.missing_validation.clone();
        }
        Ok(ds)
    }

    /// Cuts the windows of recordings already in memory (tests, generated scenes);
    /// `recording_map[i]` is the index in `maps` of recording `i`'s map.
    pub fn from_parts(
        split: Split,
        config: &WindowConfig,
        maps: Vec<LaneletMap>,
        recordings: Vec<Recording>,
        recording_map: Vec<u32>,
    ) -> Result<Self> {
        config.validate().map_err(|reason| Error::Config {
            path: "window config".into(),
            reason,
        })?;
        if recording_map.len() != recordings.len()
            || recording_map.iter().any(|&m| m as usize >= maps.len())
        {
            return Err(Error::Config {
                path: "recording_map".into(),
                reason: "one valid map index per recording".into(),
            });
        }
        let mut report = BuildReport {
            files: recordings.len(),
            ..BuildReport::default()
        };
        let mut windows = Vec::new();
        for (r, recording) in recordings.iter().enumerate() {
            let map = &maps[recording_map[r] as usize];
            cut_windows(r as u32, recording, map, config, &mut windows, &mut report);
        }
        report.windows = windows.len();
        Ok(Self {
            split,
            config: config.clone(),
            sources: Vec::new(),
            maps,
            recordings,
            recording_map,
            windows,
            report,
        })
    }

    pub fn len(&self) -> usize {
        self.windows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.windows.is_empty()
    }

    pub fn map_of(&self, window: &WindowRef) -> &LaneletMap {
        &self.maps[self.recording_map[window.recording as usize] as usize]
    }

    /// Materialises window `index`.
    pub fn window(&self, index: usize) -> Result<SceneWindow> {
        let w = self.windows.get(index).ok_or(Error::WindowIndex {
            index,
            len: self.windows.len(),
        })?;
        let recording = &self.recordings[w.recording as usize];
        let map = self.map_of(w);
        let steps = self.config.window_steps;
        let frame = SceneFrame {
            origin_m: w.origin_m,
            scale_m: self.config.position_scale_m,
        };
        let a = w.agents.len();
        let mut states = vec![0.0f32; a * steps * 3]; // [agents, steps, 3]
        let mut valid = vec![false; a * steps]; // [agents, steps]
        let mut out = SceneWindow {
            location: recording.location.clone(),
            file: recording.file.clone(),
            start_frame: w.start_frame,
            frame,
            agents: a,
            steps,
            states: Vec::new(),
            valid: Vec::new(),
            track_ids: Vec::with_capacity(a),
            agent_types: Vec::with_capacity(a),
            length_m: Vec::with_capacity(a),
            width_m: Vec::with_capacity(a),
            polyline_points: self.config.polyline_points,
            polylines: Vec::with_capacity(w.polylines.len() * self.config.polyline_points * 2),
            polyline_lanelet_ids: Vec::with_capacity(w.polylines.len()),
        };
        for (i, &t) in w.agents.iter().enumerate() {
            let track = &recording.tracks[t as usize];
            out.track_ids.push(track.track_id);
            out.agent_types.push(track.agent_type);
            out.length_m.push(track.length_m);
            out.width_m.push(track.width_m);
            let mut previous_heading: Option<f32> = None;
            for s in 0..steps {
                let Some([x, y, psi]) = track.state_at(w.start_frame + s as u32) else {
                    continue;
                };
                let p = frame.to_norm([f64::from(x), f64::from(y)]);
                let heading = match previous_heading {
                    None => wrap_angle(psi),
                    Some(prev) => prev + wrap_angle(psi - prev),
                };
                previous_heading = Some(heading);
                let k = i * steps + s;
                valid[k] = true;
                states[3 * k..3 * k + 3].copy_from_slice(&[p[0], p[1], heading]);
            }
        }
        out.states = states;
        out.valid = valid;
        for &l in &w.polylines {
            let lanelet = &map.lanelets[l as usize];
            for p in resample(&lanelet.centre_m, self.config.polyline_points) {
                out.polylines.extend_from_slice(&frame.to_norm(p));
            }
            out.polyline_lanelet_ids.push(lanelet.id);
        }
        Ok(out)
    }
}

/// Wraps an angle to (−π, π].
pub fn wrap_angle(a: f32) -> f32 {
    use std::f32::consts::PI;
    let w = (a + PI).rem_euclid(2.0 * PI) - PI;
    if w <= -PI { w + 2.0 * PI } else { w }
}

fn cut_windows(
    recording_index: u32,
    recording: &Recording,
    map: &LaneletMap,
    config: &WindowConfig,
    windows: &mut Vec<WindowRef>,
    report: &mut BuildReport,
) {
    let steps = config.window_steps as u32;
    let mut start = recording.first_frame;
    let mut present: Vec<(f64, u32, Point)> = Vec::new(); // (distance, track, position)
    while start + steps - 1 <= recording.last_frame {
        let reference = start + config.reference_step as u32;
        present.clear();
        for (t, track) in recording.tracks.iter().enumerate() {
            if let Some([x, y, _]) = track.state_at(reference) {
                present.push((0.0, t as u32, [f64::from(x), f64::from(y)]));
            }
        }
        if present.len() < config.min_agents {
            report.windows_skipped_few_agents += 1;
            start += config.stride_steps as u32;
            continue;
        }
        let mean = mean_position(&present);
        for p in &mut present {
            p.0 = dist(p.2, mean);
        }
        present.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        if present.len() > config.max_agents {
            report.agents_dropped_over_max += present.len() - config.max_agents;
            present.truncate(config.max_agents);
        }
        // The centre is the mean of the agents kept.
        let origin = mean_position(&present);
        let mut near: Vec<(f64, u32)> = map
            .lanelets
            .iter()
            .enumerate()
            .filter(|(_, l)| l.bounds.distance(origin) <= config.map_radius_m)
            .filter_map(|(i, l)| {
                let d = l
                    .centre_m
                    .iter()
                    .map(|&p| dist(p, origin))
                    .fold(f64::INFINITY, f64::min);
                (d <= config.map_radius_m).then_some((d, i as u32))
            })
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        if near.len() > config.max_polylines {
            report.polylines_dropped_over_max += near.len() - config.max_polylines;
            near.truncate(config.max_polylines);
        }
        windows.push(WindowRef {
            recording: recording_index,
            start_frame: start,
            origin_m: origin,
            agents: present.iter().map(|p| p.1).collect(),
            polylines: near.iter().map(|p| p.1).collect(),
        });
        start += config.stride_steps as u32;
    }
}

/// The mean of the positions of `present` (`(distance, track, position)`), summed as
/// `Σ p / n`: the order the window origins stored in the caches were computed in.
fn mean_position(present: &[(f64, u32, Point)]) -> Point {
    let n = present.len() as f64;
    present
        .iter()
        .fold(DVec2::ZERO, |sum, &(_, _, p)| sum + DVec2::from(p) / n)
        .into()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tracks::Track;

    fn track(id: u32, first_frame: u32, states: Vec<[f32; 3]>) -> Track {
        Track {
            track_id: id,
            agent_type: AgentType::Car,
            length_m: 4.0,
            width_m: 2.0,
            first_frame,
            states,
        }
    }

    fn map() -> LaneletMap {
        LaneletMap::parse(&crate::map::tests::fixture_osm(), Path::new("f.osm"), "FIX").unwrap()
    }

    fn dataset(tracks: Vec<Track>, config: WindowConfig) -> Dataset {
        let first = tracks.iter().map(|t| t.first_frame).min().unwrap();
        let last = tracks.iter().map(Track::last_frame).max().unwrap();
        let recording = Recording {
            location: "FIX".into(),
            file: "t.csv".into(),
            tracks,
            first_frame: first,
            last_frame: last,
        };
        let mut windows = Vec::new();
        let mut report = BuildReport::default();
        let map = map();
        cut_windows(0, &recording, &map, &config, &mut windows, &mut report);
        report.windows = windows.len();
        Dataset {
            split: Split::Train,
            config,
            sources: vec![],
            maps: vec![map],
            recordings: vec![recording],
            recording_map: vec![0],
            windows,
            report,
        }
    }

    fn config() -> WindowConfig {
        WindowConfig {
            window_steps: 4,
            stride_steps: 2,
            reference_step: 1,
            min_agents: 2,
            max_agents: 2,
            ..WindowConfig::default()
        }
    }

    #[test]
    fn windows_keep_the_nearest_agents_and_count_the_rest() {
        let still = |x: f32| (0..10).map(|_| [x, 2.0, 0.0]).collect::<Vec<_>>();
        let ds = dataset(
            vec![
                track(1, 0, still(0.0)),
                track(2, 0, still(4.0)),
                track(3, 0, still(100.0)),
            ],
            config(),
        );
        // Frames 0..=9, windows of 4 with stride 2: starts 0, 2, 4, 6.
        assert_eq!(ds.len(), 4);
        // Three present, max two: the far one goes, once per window.
        assert_eq!(ds.report.agents_dropped_over_max, 4);
        let w = ds.window(0).unwrap();
        assert_eq!(w.track_ids.len(), 2);
        assert!(!w.track_ids.contains(&3));
        // Centre is the mean of the kept agents: x = 2 m; normalised back to metres exactly.
        assert!((w.frame.origin_m[0] - 2.0).abs() < 1e-9);
        let s = w.state(0, 0).unwrap();
        let back = w.frame.to_metres([s[0], s[1]]);
        assert!((back[1] - 2.0).abs() < 1e-5);
        assert!(w.polyline_count() > 0);
        assert_eq!(
            w.polylines.len(),
            w.polyline_count() * w.polyline_points * 2
        );
        assert!(
            ds.window(4)
                .unwrap_err()
                .to_string()
                .contains("no window 4")
        );
    }

    #[test]
    fn too_few_agents_are_counted_and_validity_follows_tracks() {
        let moving = |n: usize| (0..n).map(|i| [i as f32, 0.0, 0.0]).collect::<Vec<_>>();
        // Track 2 exists only on frames 3..=5.
        let ds = dataset(
            vec![track(1, 0, moving(10)), track(2, 3, moving(3))],
            config(),
        );
        // Reference frames 1, 3, 5, 7: only 3 and 5 have two agents.
        assert_eq!(ds.len(), 2);
        assert_eq!(ds.report.windows_skipped_few_agents, 2);
        let w = ds.window(0).unwrap(); // start 2: frames 2..=5
        let second = w.track_ids.iter().position(|&id| id == 2).unwrap();
        assert_eq!(
            (0..4)
                .map(|s| w.state(second, s).is_some())
                .collect::<Vec<_>>(),
            [false, true, true, true]
        );
    }

    #[test]
    fn heading_is_unwrapped_across_pi() {
        let turn = vec![
            [0.0, 0.0, 3.1],
            [0.0, 0.0, -3.1],
            [0.0, 0.0, -3.0],
            [0.0, 0.0, 3.0],
        ];
        let other = vec![[5.0, 0.0, 0.0]; 4];
        let ds = dataset(
            vec![track(1, 0, turn), track(2, 0, other)],
            WindowConfig {
                stride_steps: 1,
                ..config()
            },
        );
        let w = ds.window(0).unwrap();
        let a = w.track_ids.iter().position(|&id| id == 1).unwrap();
        let h: Vec<f32> = (0..4).map(|s| w.state(a, s).unwrap()[2]).collect();
        assert!(
            (h[1] - (2.0 * std::f32::consts::PI - 3.1)).abs() < 1e-5,
            "{h:?}"
        );
        assert!(h.windows(2).all(|p| (p[1] - p[0]).abs() < 0.5), "{h:?}");
    }

    #[test]
    fn config_errors_name_the_key() {
        let bad = WindowConfig {
            reference_step: 40,
            ..WindowConfig::default()
        };
        assert!(bad.validate().unwrap_err().contains("reference_step"));
        let dir = std::env::temp_dir().join(format!("road-data-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("c.toml");
        std::fs::write(&path, "window_step = 3\n").unwrap();
        let err = WindowConfig::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("window_step") && err.contains("c.toml"),
            "{err}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
