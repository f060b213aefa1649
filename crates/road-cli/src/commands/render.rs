//! `road render`: a scene recording of `road serve` (or `road demo`'s `demo.mcap`) as an
//! animated GIF. One frame per `/agents` message: the scene at creation, then every tick.
//! Lanes grey (`/map`), the model's vehicles orange, the client's (external) green, grey when
//! the model drove them for a late tick; agents in a collision or off road that tick
//! (`/road/npc`) outlined red, collisions circled. No text: a bar along the bottom shows time.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use plotters::style::{BLACK, RGBColor, WHITE};
use road_serve::record::AGENT_IDS_KEY;
use road_sim::Pose;
use road_sim::geometry::OrientedBox;
use serde_json::Value;

use crate::plot::{
    ADVERSARY, EGO, Footprint, HISTORY, LOGGED, MAP, PREDICTED, Ring, Stroke, View, draw_rgb,
};
use crate::recording::{Recording, topics};

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// A scene recording (`road serve --record`, `road demo`); a file cut off by a killed
    /// server renders up to its last complete chunk.
    pub file: PathBuf,
    /// The animation; default: FILE with the extension `.gif`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Frames per second (the server ticks at 10 Hz: 10 is real time).
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// Width and height of the animation, pixels.
    #[arg(long = "size", default_value_t = 800)]
    pub size_px: u32,
}

pub fn run(args: RenderArgs) -> Result<ExitCode> {
    let out_path = args
        .out
        .clone()
        .unwrap_or_else(|| args.file.with_extension("gif"));
    let recording = Recording::read(&args.file)?;
    let rendered = render_gif(&recording, &out_path, args.fps, args.size_px)?;
    out!(
        "road render: {} frames (the scene at creation and {} ticks), {} collision pair(s) and {} off-road agent(s) highlighted{}",
        rendered.frames,
        rendered.frames.saturating_sub(1),
        rendered.collisions,
        rendered.off_road,
        if recording.cut_off.is_some() {
            "; the recording was cut off, frames up to its last complete chunk"
        } else {
            ""
        }
    );
    out!("animation: {}", out_path.display());
    Ok(ExitCode::SUCCESS)
}

/// What an animation showed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rendered {
    pub frames: usize,
    /// Collision pairs and off-road agents highlighted, each counted once.
    pub collisions: usize,
    pub off_road: usize,
}

/// The colours of every frame; each pixel takes the nearest (plotters blends some edges).
const PALETTE: [RGBColor; 8] = [
    WHITE, MAP, LOGGED, PREDICTED, HISTORY, ADVERSARY, EGO, BLACK,
];

/// Draws `recording` into the animated GIF `out` at `fps` frames per second, `size_px` square.
pub fn render_gif(recording: &Recording, out: &Path, fps: f64, size_px: u32) -> Result<Rendered> {
    anyhow::ensure!(
        fps.is_finite() && fps > 0.0 && fps <= 100.0,
        "--fps must be in (0, 100] (GIF delays are hundredths of a second), got {fps}"
    );
    anyhow::ensure!(
        (64..=4096).contains(&size_px),
        "--size must be 64 to 4096 pixels, got {size_px}"
    );
    let scene = Scene::parse(recording)?;
    // Around the agents rather than the whole map (its arms can be long): vehicles stay
    // large enough to see, with room for the lanes around them.
    let mut view = View::fit(
        scene
            .frames
            .iter()
            .flat_map(|f| f.boxes.iter().map(|b| b.centre)),
        15.0,
        size_px,
    );
    view.half_extent_m = view.half_extent_m.max(30.0);
    let lanes: Vec<Stroke> = scene
        .lanes
        .iter()
        .map(|points| Stroke {
            points: points.clone(),
            color: MAP,
            width: 2,
        })
        .collect();
    let mut background = vec![255u8; 3 * (size_px as usize).pow(2)];
    draw_rgb(&mut background, &view, &lanes, &[], &[])?;

    let side = u16::try_from(size_px).expect("checked above");
    let palette: Vec<u8> = PALETTE.iter().flat_map(|c| [c.0, c.1, c.2]).collect();
    let file = File::create(out).with_context(|| format!("cannot create {}", out.display()))?;
    let gif_err = |e: gif::EncodingError| anyhow::anyhow!("cannot write {}: {e}", out.display());
    let mut encoder =
        gif::Encoder::new(BufWriter::new(file), side, side, &palette).map_err(gif_err)?;
    encoder.set_repeat(gif::Repeat::Infinite).map_err(gif_err)?;
    let delay_cs = (100.0 / fps).round().clamp(1.0, f64::from(u16::MAX)) as u16;

    let (mut pairs, mut off) = (
        std::collections::BTreeSet::new(),
        std::collections::BTreeSet::new(),
    );
    let mut indices = Vec::with_capacity((size_px as usize).pow(2));
    let bar_y = view.centre.1 - view.half_extent_m * 0.98;
    let bar_x0 = view.centre.0 - view.half_extent_m;
    for (k, frame) in scene.frames.iter().enumerate() {
        let mut strokes = trails(&scene.frames[..=k]);
        let done = if scene.frames.len() > 1 {
            k as f64 / (scene.frames.len() - 1) as f64
        } else {
            1.0
        };
        // The NPCs' plans, when the scene asked for them: where each is heading.
        strokes.extend(frame.plans.iter().map(|points| Stroke {
            points: points.clone(),
            color: PREDICTED,
            width: 1,
        }));
        strokes.push(Stroke {
            points: vec![
                (bar_x0, bar_y),
                (bar_x0 + done * 2.0 * view.half_extent_m, bar_y),
            ],
            color: HISTORY,
            width: 4,
        });
        let footprints: Vec<Footprint> = frame
            .boxes
            .iter()
            .enumerate()
            .map(|(i, b)| {
                let flagged = frame.collided.contains(&i) || frame.off_road.contains(&i);
                Footprint {
                    corners: b.corners(),
                    color: if flagged { ADVERSARY } else { b.color() },
                    fill: Some(b.color()),
                }
            })
            .collect();
        let rings: Vec<Ring> = frame
            .collisions
            .iter()
            .map(|&(i, j)| {
                let (p, q) = (frame.boxes[i].centre, frame.boxes[j].centre);
                Ring {
                    centre: (0.5 * (p.0 + q.0), 0.5 * (p.1 + q.1)),
                    radius_m: 4.0,
                    color: ADVERSARY,
                }
            })
            .collect();
        pairs.extend(frame.collisions.iter().copied());
        off.extend(frame.off_road.iter().copied());

        let mut rgb = background.clone();
        draw_rgb(&mut rgb, &view, &strokes, &footprints, &rings)?;
        to_palette(&rgb, &mut indices);
        let mut gif_frame = gif::Frame::from_indexed_pixels(side, side, indices.as_slice(), None);
        gif_frame.delay = delay_cs;
        encoder.write_frame(&gif_frame).map_err(gif_err)?;
    }
    let mut writer = encoder.into_inner().map_err(gif_err)?;
    std::io::Write::flush(&mut writer)
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(Rendered {
        frames: scene.frames.len(),
        collisions: pairs.len(),
        off_road: off.len(),
    })
}

/// Each pixel's nearest palette entry.
fn to_palette(rgb: &[u8], indices: &mut Vec<u8>) {
    indices.clear();
    // Most pixels repeat their left neighbour: remember the last answer.
    let mut last: ([u8; 3], u8) = ([255, 255, 255], 0);
    for px in rgb.chunks_exact(3) {
        let px = [px[0], px[1], px[2]];
        if px != last.0 {
            let nearest = PALETTE
                .iter()
                .enumerate()
                .min_by_key(|(_, c)| {
                    [c.0, c.1, c.2]
                        .iter()
                        .zip(px)
                        .map(|(&a, b)| (i32::from(a) - i32::from(b)).pow(2))
                        .sum::<i32>()
                })
                .map(|(i, _)| i as u8)
                .expect("the palette is not empty");
            last = (px, nearest);
        }
        indices.push(last.1);
    }
}

/// Every agent's path up to the last of `frames`, thin, in its colour.
fn trails(frames: &[Frame]) -> Vec<Stroke> {
    let last = frames.last().expect("at least one frame");
    (0..last.boxes.len())
        .map(|i| Stroke {
            // Frames with another number of boxes (none in the server's recordings) are left
            // out of the trail rather than mixed up.
            points: frames
                .iter()
                .filter(|f| f.boxes.len() == last.boxes.len())
                .map(|f| f.boxes[i].centre)
                .collect(),
            color: last.boxes[i].color(),
            width: 1,
        })
        .collect()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Driver {
    Model,
    External,
    /// External, but the model drove it this tick (the client's ego came late).
    LateExternal,
}

#[derive(Debug, Clone)]
struct AgentBox {
    centre: (f64, f64),
    heading_rad: f64,
    length_m: f64,
    width_m: f64,
    driver: Driver,
}

impl AgentBox {
    fn color(&self) -> RGBColor {
        match self.driver {
            Driver::Model => PREDICTED,
            Driver::External => EGO,
            Driver::LateExternal => LOGGED,
        }
    }

    fn corners(&self) -> [[f64; 2]; 4] {
        OrientedBox {
            pose: Pose {
                x_m: self.centre.0,
                y_m: self.centre.1,
                heading_rad: self.heading_rad,
            },
            length_m: self.length_m,
            width_m: self.width_m,
        }
        .corners()
    }
}

/// One `/agents` message with the infractions of its tick (box indices).
#[derive(Debug, Clone, Default)]
struct Frame {
    boxes: Vec<AgentBox>,
    collisions: Vec<(usize, usize)>,
    collided: Vec<usize>,
    off_road: Vec<usize>,
    /// The NPCs' planned paths (the recorder's lines on `/agents`), metres.
    plans: Vec<Vec<(f64, f64)>>,
}

/// What the animation draws, read from the recording.
#[derive(Debug)]
struct Scene {
    lanes: Vec<Vec<(f64, f64)>>,
    frames: Vec<Frame>,
}

impl Scene {
    fn parse(recording: &Recording) -> Result<Self> {
        let path = recording.path.display();
        let json = |m: &mcap::Message<'_>| -> Result<Value> {
            serde_json::from_slice(&m.data).with_context(|| {
                format!(
                    "bad {} message (sequence {}) in {path}",
                    m.channel.topic, m.sequence
                )
            })
        };
        anyhow::ensure!(
            recording.on(topics::MAP).next().is_some(),
            "not a scene recording of `road serve`: no {} messages (lane lines) in {path}",
            topics::MAP
        );
        anyhow::ensure!(
            recording.on(topics::AGENTS).next().is_some(),
            "not a scene recording of `road serve`, or one cut off before its first tick: no {} messages (agent boxes) in {path}",
            topics::AGENTS
        );
        let mut lanes = Vec::new();
        for m in recording.on(topics::MAP) {
            for entity in array(&json(m)?["entities"]) {
                for line in array(&entity["lines"]) {
                    lanes.push(array(&line["points"]).iter().map(xy).collect::<Vec<_>>());
                }
            }
        }
        // Each box's agent: the `/agents` entity names them (`AGENT_IDS_KEY`); recordings from
        // before it did have the boxes in the order of the creation reply's agents. The
        // creation's external flags tell the client's agents; the tick's infractions name
        // agents by id.
        let agents: Vec<(u64, bool)> = match recording.on(topics::CREATED).next() {
            Some(m) => array(&json(m)?["agents"])
                .iter()
                .filter_map(|a| Some((a["id"].as_u64()?, a["external"].as_bool()?)))
                .collect(),
            None => {
                tracing::warn!(
                    "no {} message in {path}: agents' roles from their colours, infractions not shown",
                    topics::CREATED
                );
                Vec::new()
            }
        };
        let external = |id: u64| agents.iter().any(|&(a, external)| a == id && external);
        let mut frames = Vec::new();
        let mut tick: Option<Value> = None;
        for m in &recording.messages {
            if m.channel.topic == topics::NPC {
                // Its boxes follow on `/agents` with the same log time.
                tick = Some(json(m)?);
                continue;
            }
            if m.channel.topic != topics::AGENTS {
                continue;
            }
            let npc = tick.take().unwrap_or(Value::Null);
            let late = !array(&npc["late_external"]).is_empty();
            let mut frame = Frame::default();
            // The boxes' agent ids, in order.
            let mut ids: Vec<u64> = Vec::new();
            for entity in array(&json(m)?["entities"]) {
                let named = array(&entity["metadata"])
                    .iter()
                    .find(|kv| kv["key"] == AGENT_IDS_KEY)
                    .and_then(|kv| kv["value"].as_str());
                match named {
                    Some(list) => {
                        ids.extend(list.split(',').filter_map(|id| id.parse::<u64>().ok()))
                    }
                    None => ids.extend(agents.iter().map(|a| a.0)),
                }
                for line in array(&entity["lines"]) {
                    frame
                        .plans
                        .push(array(&line["points"]).iter().map(xy).collect());
                }
                for cube in array(&entity["cubes"]) {
                    let i = frame.boxes.len();
                    let external = match ids.get(i) {
                        Some(&id) if !agents.is_empty() => external(id),
                        // The recorder's colours: external agents green.
                        _ => cube["color"]["g"].as_f64() > cube["color"]["r"].as_f64(),
                    };
                    let q = &cube["pose"]["orientation"];
                    let [qx, qy, qz, qw] = ["x", "y", "z", "w"].map(|k| num(&q[k]));
                    frame.boxes.push(AgentBox {
                        centre: xy(&cube["pose"]["position"]),
                        // Yaw of the quaternion (the boxes only turn about z).
                        heading_rad: (2.0 * (qw * qz + qx * qy))
                            .atan2(1.0 - 2.0 * (qy * qy + qz * qz)),
                        length_m: num(&cube["size"]["x"]),
                        width_m: num(&cube["size"]["y"]),
                        driver: match (external, late) {
                            (false, _) => Driver::Model,
                            (true, false) => Driver::External,
                            (true, true) => Driver::LateExternal,
                        },
                    });
                }
            }
            let n = frame.boxes.len();
            let index = |id: &Value| id.as_u64().and_then(|id| ids.iter().position(|&b| b == id));
            for pair in array(&npc["collisions"]) {
                if let (Some(i), Some(j)) = (index(&pair[0]), index(&pair[1])) {
                    if i < n && j < n {
                        frame.collisions.push((i, j));
                        frame.collided.extend([i, j]);
                    }
                }
            }
            frame.off_road = array(&npc["off_road"])
                .iter()
                .filter_map(index)
                .filter(|&i| i < n)
                .collect();
            frames.push(frame);
        }
        Ok(Self { lanes, frames })
    }
}

fn array(v: &Value) -> &[Value] {
    v.as_array().map(Vec::as_slice).unwrap_or_default()
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(0.0)
}

fn xy(v: &Value) -> (f64, f64) {
    (num(&v["x"]), num(&v["y"]))
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, SystemTime};

    use road_serve::record::{Recorder, agents_update};

    use super::*;

    /// Vehicle 2 leaves after the first tick and vehicle 9 enters in its place: the boxes are
    /// then 1, 9 and 3, and a collision of 3 and 9 is drawn on their boxes (by the creation's
    /// order 9 had no box and the collision was not drawn).
    #[test]
    fn infractions_land_on_their_agents_boxes_after_vehicles_leave_and_enter() {
        let dir = std::env::temp_dir().join(format!("road-render-ids-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let map = road_sim::procedural::procedural(
            road_sim::procedural::ProceduralMap::Roundabout,
            &road_data::WindowConfig::default(),
            2,
        )
        .unwrap()
        .map;
        let agent = |id, external| road_protocol::AgentInfo {
            id,
            length_m: 4.5,
            width_m: 1.8,
            external,
            history: vec![],
        };
        let created = serde_json::json!({
            "scene": 7, "agents": [agent(1, true), agent(2, false), agent(3, false)] });
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let mut rec = Recorder::start(
            &dir,
            7,
            br#"{"client":"ego-7"}"#,
            created.to_string().as_bytes(),
            Some(&map),
            t0,
        )
        .unwrap();
        let pose = |x_m| Pose {
            x_m,
            y_m: 0.0,
            heading_rad: 0.0,
        };
        // After tick 1 the engine's index 1 holds vehicle 9 (2's index, reused).
        let ticks = [
            (
                vec![agent(1, true), agent(2, false), agent(3, false)],
                vec![true; 3],
                vec![],
            ),
            (
                vec![agent(1, true), agent(9, false), agent(3, false)],
                vec![true; 3],
                vec![[3, 9]],
            ),
        ];
        for (t, (agents, present, collisions)) in ticks.into_iter().enumerate() {
            let at = t0 + Duration::from_millis(100 * (t as u64 + 1));
            let npc = serde_json::json!({ "scene": 7, "tick": t + 1, "collisions": collisions });
            rec.write(topics::NPC, npc.to_string().as_bytes(), at)
                .unwrap();
            let poses = [pose(0.0), pose(10.0), pose(20.0)];
            let boxes = agents_update(&agents, &poses, Some(&present), &[], false, 0);
            rec.write(topics::AGENTS, boxes.to_string().as_bytes(), at)
                .unwrap();
        }
        let path = rec.finish().unwrap();
        let scene = Scene::parse(&Recording::read(&path).unwrap()).unwrap();
        let last = scene.frames.last().unwrap();
        // Boxes in the engine's order: 1 (the client's), 9, 3.
        assert_eq!(last.boxes.len(), 3);
        assert!(matches!(last.boxes[0].driver, Driver::External));
        assert!(matches!(last.boxes[1].driver, Driver::Model));
        assert_eq!(last.collisions, vec![(2, 1)]);
        std::fs::remove_dir_all(&dir).ok();
    }
}
