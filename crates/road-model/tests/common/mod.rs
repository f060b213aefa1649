//! Small in-memory scenes shared by the tests of the denoiser (`road-model`) and of its
//! rollouts on the CPU engines (`road-cpu`, which includes this file by path).
#![allow(dead_code)] // each test crate uses its own share

use std::path::Path;

use road_data::{AgentType, Dataset, LaneletMap, Recording, Split, Track, WindowConfig};
use road_model::checkpoint::DataIdentity;
use road_model::{ModelConfig, RunConfig, TrainConfig};
/// Two straight lanes along +x, 4 m wide, 200 m long (lat/lon around (0, 0)).
pub fn map() -> LaneletMap {
    let deg_per_m = 1.0 / 111_320.0;
    let mut s = String::from("<osm>\n");
    for (row, y) in [0.0, 4.0, 8.0].iter().enumerate() {
        for (col, x) in [0.0, 100.0, 200.0].iter().enumerate() {
            s += &format!(
                "<node id=\"{}\" lat=\"{}\" lon=\"{}\"/>\n",
                100 + row * 10 + col,
                y * deg_per_m,
                x * deg_per_m
            );
        }
    }
    for row in 0..3 {
        s += &format!(
            "<way id=\"{}\"><nd ref=\"{}\"/><nd ref=\"{}\"/><nd ref=\"{}\"/></way>\n",
            row + 1,
            100 + row * 10,
            101 + row * 10,
            102 + row * 10
        );
    }
    for lane in 0..2 {
        s += &format!(
            "<relation id=\"{}\"><member type=\"way\" ref=\"{}\" role=\"left\"/><member type=\"way\" ref=\"{}\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/></relation>\n",
            500 + lane,
            lane + 2,
            lane + 1
        );
    }
    s += "</osm>\n";
    LaneletMap::parse(&s, Path::new("lanes.osm"), "LANES").unwrap()
}

/// Cars driving along the two lanes at different speeds, entering at different times.
pub fn dataset(split: Split) -> Dataset {
    let mut tracks = Vec::new();
    for i in 0..6u32 {
        let lane_y = if i % 2 == 0 { 2.0 } else { 6.0 };
        let speed = 4.0 + i as f32;
        let first = i * 3;
        let states = (0..60)
            .map(|t| [5.0 + 6.0 * i as f32 + speed * 0.1 * t as f32, lane_y, 0.0])
            .collect();
        tracks.push(Track {
            track_id: i + 1,
            agent_type: AgentType::Car,
            length_m: 4.5,
            width_m: 1.8,
            first_frame: first,
            states,
        });
    }
    let last = tracks.iter().map(Track::last_frame).max().unwrap();
    let recording = Recording {
        location: "LANES".into(),
        file: "synthetic.csv".into(),
        tracks,
        first_frame: 0,
        last_frame: last,
    };
    let config = WindowConfig {
        stride_steps: 3,
        ..WindowConfig::default()
    };
    Dataset::from_parts(split, &config, vec![map()], vec![recording], vec![0]).unwrap()
}

pub fn run_config() -> RunConfig {
    RunConfig {
        name: "tiny".into(),
        model: ModelConfig {
            hidden: 16,
            heads: 2,
            blocks: 1,
            map_polylines: 8,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            batch_scenes: 4,
            steps: 400,
            learning_rate: 3e-3,
            warmup_steps: 5,
            val_batches: 2,
            val_every_steps: 1000,
            checkpoint_every_secs: 3600,
            ..TrainConfig::default()
        },
        ..RunConfig::default()
    }
}

pub fn identity() -> DataIdentity {
    DataIdentity {
        train_cache: "memory".into(),
        train_windows: 0,
        validation_windows: 0,
        source: "synthetic".into(),
    }
}

pub fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("road-model-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}
