//! Tests on the shared INTERACTION data (`ROAD_DATA`, else `../shared/data/interaction` beside
//! the clone). Missing data is a failure: these run in CI.

use std::path::PathBuf;

use road_data::stats::{self, MAX_MEDIAN_LANE_DISTANCE_M};
use road_data::{Dataset, SourceSet, Split, WindowConfig, cache};

fn data_dir() -> PathBuf {
    road_data::testing::interaction_dir()
}

#[test]
fn split_follows_the_official_list() {
    let sources = SourceSet::discover(&data_dir()).unwrap();
    assert_eq!(sources.train.len(), 132);
    assert_eq!(sources.validation.len(), 24);
    assert!(
        sources
            .missing_validation
            .iter()
            .any(|m| m.starts_with("DR_DEU_Merging_MT/"))
    );
    // No file is in both splits.
    for v in &sources.validation {
        assert!(
            !sources
                .train
                .iter()
                .any(|t| t.relative_path == v.relative_path)
        );
    }
}

/// The built-in check of the projection, over every track point of both splits.
#[test]
fn track_points_lie_on_lane_centres_at_every_location() {
    let sources = SourceSet::discover(&data_dir()).unwrap();
    let config = WindowConfig::default();
    let train = Dataset::build(&sources, Split::Train, &config).unwrap();
    let validation = Dataset::build(&sources, Split::Validation, &config).unwrap();
    let locations = stats::location_stats(&[&train, &validation]);
    assert_eq!(locations.len(), 8, "every location with tracks");
    for l in &locations {
        assert!(
            l.median_lane_distance_m < MAX_MEDIAN_LANE_DISTANCE_M,
            "{}: median distance to the nearest lane centre {:.2} m",
            l.location,
            l.median_lane_distance_m
        );
        assert!(l.track_points > 10_000 && l.polylines > 10, "{l:?}");
    }
    let s = stats::split_stats(&train);
    assert!((s.hours - 9.9).abs() < 0.2, "train hours {}", s.hours);
    assert!(s.agents_max <= config.max_agents);
}

#[test]
fn real_windows_are_well_formed_and_round_trip_through_the_cache() {
    let sources = SourceSet::discover(&data_dir()).unwrap();
    let config = WindowConfig::default();
    let ds = Dataset::build(&sources, Split::Validation, &config).unwrap();
    assert!(ds.len() > 1000, "{} windows", ds.len());
    for index in (0..ds.len()).step_by(37) {
        let w = ds.window(index).unwrap();
        assert!(w.agents >= config.min_agents && w.agents <= config.max_agents);
        assert!(w.polyline_count() > 0, "window {index} has no map");
        let recording = ds
            .recordings
            .iter()
            .find(|r| r.file == w.file && r.location == w.location)
            .unwrap();
        for a in 0..w.agents {
            // Every agent is present at the reference step.
            let s = w
                .state(a, config.reference_step)
                .expect("agent present at the reference step");
            // Normalised positions are O(1); metres come back exactly.
            assert!(
                s[0].abs() < 10.0 && s[1].abs() < 10.0,
                "window {index} agent {a}: {s:?}"
            );
            let track = recording
                .tracks
                .iter()
                .find(|t| t.track_id == w.track_ids[a])
                .unwrap();
            let raw = track
                .state_at(w.start_frame + config.reference_step as u32)
                .unwrap();
            let back = w.frame.to_metres([s[0], s[1]]);
            assert!(
                (back[0] - f64::from(raw[0])).abs() < 1e-3
                    && (back[1] - f64::from(raw[1])).abs() < 1e-3
            );
            // Headings are continuous: no ±2π jumps between valid neighbours.
            for t in 1..w.steps {
                if let (Some(p), Some(q)) = (w.state(a, t - 1), w.state(a, t)) {
                    assert!(
                        (q[2] - p[2]).abs() < 1.0,
                        "window {index} agent {a} step {t}: {} → {}",
                        p[2],
                        q[2]
                    );
                }
            }
        }
        assert!(
            w.states.iter().all(|v| v.is_finite()) && w.polylines.iter().all(|v| v.is_finite())
        );
    }

    let dir = std::env::temp_dir().join(format!("road-data-it-{}", std::process::id()));
    let path = cache::cache_path(&dir, Split::Validation);
    cache::save(&ds, &path).unwrap();
    let back =
        cache::load_checked(&path, Split::Validation, Some(&config), Some(&sources)).unwrap();
    assert_eq!(back.len(), ds.len());
    assert_eq!(
        back.window(ds.len() / 2).unwrap(),
        ds.window(ds.len() / 2).unwrap()
    );
    let other = WindowConfig {
        stride_steps: 20,
        ..config
    };
    assert!(
        cache::load_checked(&path, Split::Validation, Some(&other), None)
            .unwrap_err()
            .to_string()
            .contains("stale")
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Every map's priority rules are read: each right of way names lanelets that give way and
/// lanelets that have it, and each yield lanelet's traffic leaves it into a junction.
#[test]
fn every_map_s_priority_rules_are_read() {
    use road_data::LaneletMap;
    use road_data::rules::RuleKind;
    let mut seen = Vec::new();
    for entry in std::fs::read_dir(data_dir().join("maps")).unwrap() {
        let path = entry.unwrap().path();
        let location = path.file_stem().unwrap().to_string_lossy().into_owned();
        let map = LaneletMap::load(&path, &location).unwrap();
        for rule in &map.priority_rules {
            let junction: usize = rule.junction.len();
            let conflicts: usize = rule.junction.iter().map(|(_, c)| c.len()).sum();
            eprintln!(
                "{location} {} {:?}: yield {:?}, priority {:?}, junction {junction} lanelets, {conflicts} conflicts",
                rule.id, rule.kind, rule.yield_lanelets, rule.priority_lanelets
            );
            assert!(!rule.yield_lanelets.is_empty());
            assert_eq!(
                rule.kind == RuleKind::Yield,
                !rule.priority_lanelets.is_empty(),
                "{location} {}",
                rule.id
            );
        }
        seen.push((location, map.priority_rules.len()));
    }
    seen.sort();
    let count = |name: &str| seen.iter().find(|(l, _)| l == name).map(|(_, n)| *n);
    assert_eq!(count("DR_USA_Roundabout_FT"), Some(7), "{seen:?}");
    assert_eq!(count("DR_USA_Intersection_MA"), Some(2), "{seen:?}");
    assert_eq!(count("DR_CHN_Merging_ZS"), Some(0), "{seen:?}");
}
