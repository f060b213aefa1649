//! One MCAP file per scene: the creation request and reply, every ego input (log time = when
//! it was received) and NPC output (log time = when it was published), the errors, the map
//! once; and `foxglove.SceneUpdate` messages in JSON (lane lines on `/map`, agent boxes on
//! `/agents`) that Foxglove's 3D panel shows without configuration. Chunks are written out at
//! least every `flush_interval`, so a killed server's file reads back to its last chunk with a
//! stream reader, and [`crate::recover`] (`road recover`, or the next server's start) rewrites
//! it whole for the readers that need its summary. A recorder holds its file's lock
//! ([`try_lock_exclusive`]) while it writes.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use glam::{DQuat, DVec3};
use road_data::LaneletMap;
use road_protocol::{AgentInfo, AgentPlan};
use road_sim::Pose;
use serde_json::{Value, json};

use crate::{Error, Result};

/// Topics of a recording.
pub mod topics {
    /// [`road_protocol::CreateScene`] as received.
    pub const CREATE: &str = "/road/create";
    /// [`road_protocol::SceneCreated`] as sent.
    pub const CREATED: &str = "/road/created";
    /// Every [`road_protocol::EgoTick`] accepted, as received.
    pub const EGO: &str = "/road/ego";
    /// Every [`road_protocol::NpcTick`] as published.
    pub const NPC: &str = "/road/npc";
    /// Every [`road_protocol::ErrorReply`] the scene's client got.
    pub const ERROR: &str = "/road/error";
    /// `foxglove.SceneUpdate`: the map's lane bounds, once.
    pub const MAP: &str = "/map";
    /// `foxglove.SceneUpdate`: every agent's box, per tick.
    pub const AGENTS: &str = "/agents";
}

/// The frame every pose is in.
const FRAME: &str = "map";

/// A JSON Schema for the part of `foxglove.SceneUpdate` the recordings use (Foxglove knows the
/// schema by its name; this is for other readers). The live view advertises it too.
pub const SCENE_UPDATE_SCHEMA: &str = include_str!("scene_update.schema.json");

/// The recorder of one scene.
pub struct Recorder {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    channels: BTreeMap<&'static str, u16>,
    sequence: u32,
    dirty: bool,
    last_flush: Instant,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.path)
            .field("sequence", &self.sequence)
            .finish_non_exhaustive()
    }
}

/// Nanoseconds since the Unix epoch.
pub fn unix_nanos(t: SystemTime) -> u64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

/// Where scene `scene`'s recording goes in `dir` (created if missing): `scene-<id>.mcap`, or
/// `scene-<id>-<k>.mcap` with the smallest free k ≥ 2 when an earlier run of the server (whose
/// scene ids started at 1 too) left that name.
pub fn free_path(dir: &Path, scene: u64) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Io {
        path: dir.to_owned(),
        source,
    })?;
    let first = dir.join(format!("scene-{scene}.mcap"));
    if !first.exists() {
        return Ok(first);
    }
    (2u64..)
        .map(|k| dir.join(format!("scene-{scene}-{k}.mcap")))
        .find(|p| !p.exists())
        .ok_or_else(|| Error::Config(format!("no free recording name in {}", dir.display())))
}

/// Whether `name` is a recording's file name as [`free_path`] gives it: `scene-<id>.mcap` or
/// `scene-<id>-<k>.mcap` (what a restarted server recovers when a killed one left it cut off,
/// [`crate::recover`]).
pub fn is_recording_name(name: &str) -> bool {
    let Some(stem) = name
        .strip_prefix("scene-")
        .and_then(|s| s.strip_suffix(".mcap"))
    else {
        return false;
    };
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    match stem.split_once('-') {
        Some((id, k)) => digits(id) && digits(k),
        None => digits(stem),
    }
}

/// Takes the advisory lock (`flock`, exclusive, without waiting) that marks a recording as
/// being written: a recorder holds it on its file until the file is finished, and recovery
/// leaves a file whose lock is held alone (another server, sharing the folder, is writing
/// it). The lock goes with the file's descriptor, and with its process however it ends: a
/// killed server's files are free. `Ok(false)`: another open file holds the lock.
#[allow(unsafe_code)]
pub(crate) fn try_lock_exclusive(file: &File) -> std::io::Result<bool> {
    use std::os::fd::AsRawFd;
    // SAFETY: flock reads only the descriptor's number, which `file` keeps open for the call;
    // no memory is shared.
    let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if rc == 0 {
        return Ok(true);
    }
    let err = std::io::Error::last_os_error();
    if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
        Ok(false)
    } else {
        Err(err)
    }
}

fn stamp(nanos: u64) -> Value {
    json!({ "sec": nanos / 1_000_000_000, "nsec": nanos % 1_000_000_000 })
}

impl Recorder {
    /// Starts the recording of scene `scene` at [`free_path`]`(dir, scene)` with the creation
    /// request and reply and the map.
    pub fn start(
        dir: &Path,
        scene: u64,
        request: &[u8],
        created: &[u8],
        map: Option<&LaneletMap>,
        at: SystemTime,
    ) -> Result<Self> {
        let path = free_path(dir, scene)?;
        let map_update = map.map(|m| map_update(m, unix_nanos(at)).to_string());
        Self::start_at(
            &path,
            request,
            created,
            map_update.as_deref().map(str::as_bytes),
            at,
        )
    }

    /// Starts a recording at `path`, a file that must not exist yet (a recording is never
    /// overwritten), with the creation request and reply and the map's `SceneUpdate` JSON
    /// ([`map_update`]; built by the caller, which hands the same bytes to the live view).
    pub fn start_at(
        path: &Path,
        request: &[u8],
        created: &[u8],
        map_update: Option<&[u8]>,
        at: SystemTime,
    ) -> Result<Self> {
        let path = path.to_owned();
        let file = File::options()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|source| Error::Io {
                path: path.clone(),
                source,
            })?;
        // Held until the file is finished (or the process ends): recovery leaves it alone.
        match try_lock_exclusive(&file) {
            Ok(true) => {}
            Ok(false) => {
                return Err(Error::RecordingInUse { path });
            }
            Err(source) => return Err(Error::Io { path, source }),
        }
        let rec_err = |path: &Path, e: mcap::McapError| Error::Record {
            path: path.to_owned(),
            reason: e.to_string(),
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .profile("")
            .library(concat!("road-serve ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(|e| rec_err(&path, e))?;
        let scene_update = writer
            .add_schema(
                "foxglove.SceneUpdate",
                "jsonschema",
                SCENE_UPDATE_SCHEMA.as_bytes(),
            )
            .map_err(|e| rec_err(&path, e))?;
        let mut channels = BTreeMap::new();
        let metadata = BTreeMap::new();
        for topic in [
            topics::CREATE,
            topics::CREATED,
            topics::EGO,
            topics::NPC,
            topics::ERROR,
        ] {
            // Raw protocol messages: JSON without a schema (docs/protocol.md has theirs).
            let id = writer
                .add_channel(0, topic, "json", &metadata)
                .map_err(|e| rec_err(&path, e))?;
            channels.insert(topic, id);
        }
        for topic in [topics::MAP, topics::AGENTS] {
            let id = writer
                .add_channel(scene_update, topic, "json", &metadata)
                .map_err(|e| rec_err(&path, e))?;
            channels.insert(topic, id);
        }
        let mut recorder = Self {
            path,
            writer,
            channels,
            sequence: 0,
            dirty: false,
            last_flush: Instant::now(),
        };
        recorder.write(topics::CREATE, request, at)?;
        recorder.write(topics::CREATED, created, at)?;
        if let Some(update) = map_update {
            recorder.write(topics::MAP, update, at)?;
        }
        // The first flush right away: the file is readable from the start.
        recorder.flush()?;
        Ok(recorder)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes one message on `topic` with log and publish time `at`.
    pub fn write(&mut self, topic: &'static str, data: &[u8], at: SystemTime) -> Result<()> {
        let channel_id = *self.channels.get(topic).ok_or_else(|| Error::Record {
            path: self.path.clone(),
            reason: format!("no channel {topic}"),
        })?;
        let nanos = unix_nanos(at);
        self.sequence += 1;
        self.writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: self.sequence,
                    log_time: nanos,
                    publish_time: nanos,
                },
                data,
            )
            .map_err(|e| Error::Record {
                path: self.path.clone(),
                reason: e.to_string(),
            })?;
        self.dirty = true;
        Ok(())
    }

    /// The agents' boxes at `at` (external agents green, the model's orange, external agents
    /// the model drove for a late tick grey), and the NPCs' plans when the scene has them.
    pub fn agents(
        &mut self,
        agents: &[AgentInfo],
        poses: &[Pose],
        plans: &[AgentPlan],
        late: bool,
        at: SystemTime,
    ) -> Result<()> {
        let update = agents_update(agents, poses, None, plans, late, unix_nanos(at));
        self.write(topics::AGENTS, update.to_string().as_bytes(), at)
    }

    /// Writes out the open chunk if anything was written since the last flush and
    /// `interval` has passed.
    pub fn flush_if_due(&mut self, interval: Duration) -> Result<()> {
        if self.dirty && self.last_flush.elapsed() >= interval {
            self.flush()?;
        }
        Ok(())
    }

    /// Writes out the open chunk now.
    pub fn flush(&mut self) -> Result<()> {
        self.writer.flush().map_err(|e| Error::Record {
            path: self.path.clone(),
            reason: e.to_string(),
        })?;
        self.dirty = false;
        self.last_flush = Instant::now();
        Ok(())
    }

    /// Finishes the file (summary and index).
    pub fn finish(mut self) -> Result<PathBuf> {
        self.writer.finish().map_err(|e| Error::Record {
            path: self.path.clone(),
            reason: e.to_string(),
        })?;
        Ok(self.path)
    }
}

fn color(r: f64, g: f64, b: f64, a: f64) -> Value {
    json!({ "r": r, "g": g, "b": b, "a": a })
}

fn entity(
    id: &str,
    nanos: u64,
    cubes: Vec<Value>,
    lines: Vec<Value>,
    metadata: Vec<Value>,
) -> Value {
    json!({
        "timestamp": stamp(nanos),
        "frame_id": FRAME,
        "id": id,
        "lifetime": { "sec": 0, "nsec": 0 },
        "frame_locked": false,
        "metadata": metadata,
        "arrows": [],
        "cubes": cubes,
        "spheres": [],
        "cylinders": [],
        "lines": lines,
        "triangles": [],
        "texts": [],
        "models": [],
    })
}

fn identity_pose() -> Value {
    json!({
        "position": { "x": 0.0, "y": 0.0, "z": 0.0 },
        "orientation": { "x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0 },
    })
}

/// The map's lane bounds as line strips, one entity.
pub fn map_update(map: &LaneletMap, nanos: u64) -> Value {
    let lines: Vec<Value> = map
        .lanelets
        .iter()
        .flat_map(|l| [&l.left_m, &l.right_m])
        .map(|bound| {
            let points: Vec<Value> = bound
                .iter()
                .map(|p| json!({ "x": p[0], "y": p[1], "z": 0.0 }))
                .collect();
            json!({
                "type": 0,
                "pose": identity_pose(),
                "thickness": 0.15,
                "scale_invariant": false,
                "points": points,
                "color": color(0.6, 0.6, 0.6, 1.0),
                "colors": [],
                "indices": [],
            })
        })
        .collect();
    json!({ "deletions": [], "entities": [entity("lanes", nanos, vec![], lines, vec![])] })
}

/// Removes every entity of the topic: what a viewer gets when a scene closes, so that its
/// boxes do not stay on screen.
pub fn clear_update(nanos: u64) -> Value {
    json!({
        "deletions": [{ "timestamp": stamp(nanos), "type": 1, "id": "" }],
        "entities": [],
    })
}

/// The `/agents` entity's metadata key whose value lists the boxes' agent ids, comma-separated.
pub const AGENT_IDS_KEY: &str = "agent_ids";

/// Every agent's box at one step (of the agents `present`, all when `None`), one entity
/// (replacing the previous step's), with each planned path (`plans`, by agent id) as a thin
/// line from the agent's pose.
pub fn agents_update(
    agents: &[AgentInfo],
    poses: &[Pose],
    present: Option<&[bool]>,
    plans: &[AgentPlan],
    late: bool,
    nanos: u64,
) -> Value {
    const HEIGHT_M: f64 = 1.5;
    let shown: Vec<(&AgentInfo, &Pose)> = agents
        .iter()
        .zip(poses)
        .enumerate()
        // An agent that left the scene (`present` false) has no box.
        .filter(|&(i, _)| present.is_none_or(|here| here[i]))
        .map(|(_, shown)| shown)
        .collect();
    // Which agent each box is, in the boxes' order: once vehicles leave and enter, the order
    // is no longer the creation's (`road render` finds a tick's infractions by these ids).
    let ids = shown
        .iter()
        .map(|(a, _)| a.id.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let metadata = vec![json!({ "key": AGENT_IDS_KEY, "value": ids })];
    let cubes: Vec<Value> = shown
        .into_iter()
        .map(|(a, p)| {
            let q = DQuat::from_rotation_z(p.heading_rad);
            let centre = DVec3::new(p.x_m, p.y_m, 0.5 * HEIGHT_M);
            let c = match (a.external, late) {
                (true, false) => color(0.1, 0.7, 0.2, 0.9),
                (true, true) => color(0.5, 0.5, 0.5, 0.9),
                (false, _) => color(1.0, 0.55, 0.1, 0.9),
            };
            json!({
                "pose": {
                    "position": { "x": centre.x, "y": centre.y, "z": centre.z },
                    "orientation": { "x": q.x, "y": q.y, "z": q.z, "w": q.w },
                },
                "size": { "x": a.length_m, "y": a.width_m, "z": HEIGHT_M },
                "color": c,
            })
        })
        .collect();
    let lines: Vec<Value> = plans
        .iter()
        .filter_map(|plan| {
            let start = agents.iter().position(|a| a.id == plan.id)?;
            let from = poses.get(start)?;
            let points: Vec<Value> = std::iter::once((from.x_m, from.y_m))
                .chain(plan.poses.iter().map(|p| (p.x_m, p.y_m)))
                .map(|(x, y)| json!({ "x": x, "y": y, "z": 0.2 }))
                .collect();
            Some(json!({
                "type": 0,
                "pose": identity_pose(),
                "thickness": 0.1,
                "scale_invariant": false,
                "points": points,
                "color": color(1.0, 0.55, 0.1, 0.6),
                "colors": [],
                "indices": [],
            }))
        })
        .collect();
    json!({ "deletions": [], "entities": [entity("agents", nanos, cubes, lines, metadata)] })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn agent(id: u32, external: bool) -> AgentInfo {
        AgentInfo {
            id,
            length_m: 4.0,
            width_m: 2.0,
            external,
            history: vec![],
        }
    }

    /// Once vehicles leave, the boxes skip them: the entity names each box's agent.
    #[test]
    fn the_boxes_name_their_agents_in_order() {
        let agents = [agent(1, true), agent(2, false), agent(9, false)];
        let pose = |x_m| Pose {
            x_m,
            y_m: 0.0,
            heading_rad: 0.0,
        };
        let poses = [pose(0.0), pose(10.0), pose(20.0)];
        let v = agents_update(&agents, &poses, Some(&[true, false, true]), &[], false, 0);
        let entity = &v["entities"][0];
        assert_eq!(entity["metadata"][0]["key"], AGENT_IDS_KEY);
        assert_eq!(entity["metadata"][0]["value"], "1,9");
        let cubes = entity["cubes"].as_array().unwrap();
        assert_eq!(cubes.len(), 2);
        assert_eq!(cubes[1]["pose"]["position"]["x"], 20.0);
    }

    #[test]
    fn a_restarted_server_never_overwrites_a_recording() {
        let dir = std::env::temp_dir().join(format!("road-record-free-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let first = Recorder::start(&dir, 1, b"{}", b"{\"run\":1}", None, t0).unwrap();
        first.finish().unwrap();
        let kept = std::fs::read(dir.join("scene-1.mcap")).unwrap();
        assert_eq!(free_path(&dir, 1).unwrap(), dir.join("scene-1-2.mcap"));
        let second = Recorder::start(&dir, 1, b"{}", b"{\"run\":2}", None, t0).unwrap();
        second.finish().unwrap();
        assert_eq!(std::fs::read(dir.join("scene-1.mcap")).unwrap(), kept);
        assert!(dir.join("scene-1-2.mcap").exists());
        assert_eq!(free_path(&dir, 1).unwrap(), dir.join("scene-1-3.mcap"));
        let taken = dir.join("scene-1.mcap");
        assert!(Recorder::start_at(&taken, b"{}", b"{}", None, t0).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_recording_round_trips_in_memory_and_after_a_flush() {
        let dir = std::env::temp_dir().join(format!("road-record-{}", std::process::id()));
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let mut rec =
            Recorder::start(&dir, 7, b"{\"create\":1}", b"{\"scene\":7}", None, t0).unwrap();
        let agents = [agent(1, true), agent(2, false)];
        let poses = [
            Pose {
                x_m: 1.0,
                y_m: 2.0,
                heading_rad: std::f64::consts::FRAC_PI_2,
            },
            Pose {
                x_m: 5.0,
                y_m: 2.0,
                heading_rad: 0.0,
            },
        ];
        for t in 1..=3u64 {
            let at = t0 + Duration::from_millis(100 * t);
            rec.write(topics::EGO, format!("{{\"tick\":{t}}}").as_bytes(), at)
                .unwrap();
            rec.write(topics::NPC, format!("{{\"tick\":{t}}}").as_bytes(), at)
                .unwrap();
            rec.agents(&agents, &poses, &[], false, at).unwrap();
        }
        rec.flush().unwrap();
        // Before finishing: what a killed server leaves.
        let bytes = std::fs::read(rec.path()).unwrap();
        let mut options = enumset::EnumSet::empty();
        options.insert(mcap::read::Options::IgnoreEndMagic);
        let flushed: Vec<String> = mcap::MessageStream::new_with_options(&bytes, options)
            .unwrap()
            .map_while(|m| m.ok())
            .map(|m| m.channel.topic.clone())
            .collect();
        assert_eq!(flushed.iter().filter(|t| *t == topics::NPC).count(), 3);
        let path = rec.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let messages: Vec<mcap::Message> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .collect::<std::result::Result<_, _>>()
            .unwrap();
        assert_eq!(messages.len(), 2 + 3 * 3);
        let boxes = messages
            .iter()
            .find(|m| m.channel.topic == topics::AGENTS)
            .unwrap();
        assert_eq!(
            boxes.channel.schema.as_ref().unwrap().name,
            "foxglove.SceneUpdate"
        );
        let v: Value = serde_json::from_slice(&boxes.data).unwrap();
        let cube = &v["entities"][0]["cubes"][0];
        // A quarter turn about z: w = z = cos 45°.
        let w = cube["pose"]["orientation"]["w"].as_f64().unwrap();
        assert!((w - std::f64::consts::FRAC_1_SQRT_2).abs() < 1e-9);
        assert_eq!(
            messages[2].log_time,
            unix_nanos(t0 + Duration::from_millis(100))
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
