//! The scene writer: a thread that owns every scene's recording and live-view channels, so
//! that the core's batched rounds never wait on MCAP writes, chunk compression or the
//! building of `foxglove.SceneUpdate` JSON.
//!
//! The core hands it jobs over a bounded channel, in order: nothing is dropped (a full queue
//! makes the core wait, it does not lose a message), and a scene's messages are written in
//! the order the core sent them. The writer flushes every recording at least once per
//! `flush_interval`, so a killed server's files read back to their last chunk.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use road_protocol::{AgentInfo, AgentPlan};
use road_sim::Pose;

use crate::live::{ChannelId, ChannelSpec, LiveView};
use crate::record::{Recorder, agents_update, clear_update, topics, unix_nanos};

/// Jobs the core may queue before it waits for the writer (about a minute of 128 scenes).
const QUEUE_JOBS: usize = 1 << 16;

/// How much lower than the rest of the server the writer runs (a nice increment, Linux): it
/// takes the time the engine's rounds leave (their gaps, the helpers' yields) instead of
/// preempting a worker mid-round, which stalls the whole batch at its next barrier. The
/// bounded queue limits how far it can fall behind.
const WRITER_NICE_INCREMENT: i32 = 10;

#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn lower_this_threads_priority() {
    // SAFETY: `nice` only changes the scheduling priority of the calling thread (on Linux,
    // glibc's nice is setpriority(PRIO_PROCESS, 0), which names the calling thread); no memory
    // is touched. Failure leaves the priority as it was, which is harmless.
    unsafe {
        *libc::__errno_location() = 0;
        if libc::nice(WRITER_NICE_INCREMENT) == -1 && *libc::__errno_location() != 0 {
            tracing::debug!("the scene writer keeps its priority (nice failed)");
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn lower_this_threads_priority() {}

/// A scene's channels in the live view: the topics of its recording under `/scene/<id>`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LiveChannels {
    pub map: ChannelId,
    pub agents: ChannelId,
}

impl LiveChannels {
    pub fn advertise(view: &LiveView, scene: u64) -> Self {
        let topic = |t: &str| ChannelSpec::scene_update(format!("/scene/{scene}{t}"));
        Self {
            map: view.advertise(topic(topics::MAP)),
            agents: view.advertise(topic(topics::AGENTS)),
        }
    }
}

/// A tick as published, for the scene's recording and live view: its NPC message, and every
/// agent's pose for the boxes (of the agents still `present`: not those that left the map).
#[derive(Debug)]
pub struct PublishedTick {
    pub npc_json: Vec<u8>,
    pub poses: Vec<Pose>,
    pub present: Vec<bool>,
    pub plans: Vec<AgentPlan>,
    /// The model drove the client's agents this tick (drawn grey).
    pub late: bool,
    pub at: SystemTime,
    /// The scene's agents by index, when vehicles entered before this tick (their indices
    /// may be those of vehicles that left).
    pub agents: Option<Vec<AgentInfo>>,
}

enum Job {
    /// A new scene: its recording (map and creation written already) and live channels.
    Start {
        scene: u64,
        agents: Vec<AgentInfo>,
        /// Boxed: an MCAP writer is over a kilobyte, the other jobs a few words.
        recorder: Option<Box<Recorder>>,
        channels: Option<LiveChannels>,
    },
    /// A raw protocol message for the scene's recording.
    Record {
        scene: u64,
        topic: &'static str,
        data: Vec<u8>,
        at: SystemTime,
    },
    /// A published tick (boxed: the queue's other jobs are small).
    Tick {
        scene: u64,
        tick: Box<PublishedTick>,
    },
    /// The scene closed: finish its file (the path comes back) and clear it from viewers.
    Finish {
        scene: u64,
        done: mpsc::Sender<Option<String>>,
    },
}

struct WriterScene {
    agents: Vec<AgentInfo>,
    recorder: Option<Box<Recorder>>,
    channels: Option<LiveChannels>,
}

/// The handle the core holds; dropping it finishes every open recording and joins the thread.
pub(crate) struct SceneWriter {
    jobs: Option<SyncSender<Job>>,
    thread: Option<JoinHandle<()>>,
}

impl SceneWriter {
    pub fn start(
        live_view: Option<Arc<LiveView>>,
        flush_interval: Duration,
    ) -> crate::Result<Self> {
        let (jobs, queue) = mpsc::sync_channel(QUEUE_JOBS);
        let thread = std::thread::Builder::new()
            .name("road-serve-writer".into())
            .spawn(move || {
                lower_this_threads_priority();
                run(queue, live_view, flush_interval)
            })
            .map_err(|e| crate::Error::Config(format!("cannot start the writer thread: {e}")))?;
        Ok(Self {
            jobs: Some(jobs),
            thread: Some(thread),
        })
    }

    fn send(&self, job: Job) {
        let sent = self.jobs.as_ref().map(|jobs| jobs.send(job));
        if !matches!(sent, Some(Ok(()))) {
            tracing::error!("the scene writer has stopped: a recording message is lost");
        }
    }

    pub fn start_scene(
        &self,
        scene: u64,
        agents: Vec<AgentInfo>,
        recorder: Option<Recorder>,
        channels: Option<LiveChannels>,
    ) {
        self.send(Job::Start {
            scene,
            agents,
            recorder: recorder.map(Box::new),
            channels,
        });
    }

    pub fn record(&self, scene: u64, topic: &'static str, data: Vec<u8>, at: SystemTime) {
        self.send(Job::Record {
            scene,
            topic,
            data,
            at,
        });
    }

    pub fn tick(&self, scene: u64, tick: PublishedTick) {
        self.send(Job::Tick {
            scene,
            tick: Box::new(tick),
        });
    }

    /// Finishes the scene's recording after everything queued before, and waits for it: the
    /// path of the finished file, or `None` (no recording, or it failed: logged).
    pub fn finish(&self, scene: u64) -> Option<String> {
        let (done, finished) = mpsc::channel();
        self.send(Job::Finish { scene, done });
        finished.recv().ok().flatten()
    }
}

impl Drop for SceneWriter {
    fn drop(&mut self) {
        // The thread finishes what is left once the queue is closed.
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            if thread.join().is_err() {
                tracing::error!("the scene writer panicked");
            }
        }
    }
}

fn run(queue: Receiver<Job>, live_view: Option<Arc<LiveView>>, flush_interval: Duration) {
    let mut scenes: BTreeMap<u64, WriterScene> = BTreeMap::new();
    let mut last_flush = Instant::now();
    loop {
        let wait = (last_flush + flush_interval).saturating_duration_since(Instant::now());
        match queue.recv_timeout(wait) {
            Ok(job) => handle(job, &mut scenes, live_view.as_deref()),
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => break,
        }
        if last_flush.elapsed() >= flush_interval {
            last_flush = Instant::now();
            for (id, scene) in &mut scenes {
                if let Some(rec) = scene.recorder.as_mut() {
                    if let Err(e) = rec.flush_if_due(Duration::ZERO) {
                        tracing::warn!(scene = id, "recording: {e}");
                    }
                }
            }
        }
    }
    for (id, scene) in scenes {
        finish(id, scene, live_view.as_deref());
    }
}

fn handle(job: Job, scenes: &mut BTreeMap<u64, WriterScene>, view: Option<&LiveView>) {
    match job {
        Job::Start {
            scene,
            agents,
            recorder,
            channels,
        } => {
            scenes.insert(
                scene,
                WriterScene {
                    agents,
                    recorder,
                    channels,
                },
            );
        }
        Job::Record {
            scene,
            topic,
            data,
            at,
        } => {
            if let Some(rec) = scenes.get_mut(&scene).and_then(|s| s.recorder.as_mut()) {
                if let Err(e) = rec.write(topic, &data, at) {
                    tracing::warn!(scene, "recording: {e}");
                }
            }
        }
        Job::Tick { scene, tick } => {
            let PublishedTick {
                npc_json,
                poses,
                present,
                plans,
                late,
                at,
                agents,
            } = *tick;
            let Some(s) = scenes.get_mut(&scene) else {
                return;
            };
            if let Some(agents) = agents {
                s.agents = agents;
            }
            let nanos = unix_nanos(at);
            let boxes =
                agents_update(&s.agents, &poses, Some(&present), &plans, late, nanos).to_string();
            if let Some(rec) = s.recorder.as_mut() {
                let written = rec
                    .write(topics::NPC, &npc_json, at)
                    .and_then(|()| rec.write(topics::AGENTS, boxes.as_bytes(), at));
                if let Err(e) = written {
                    tracing::warn!(scene, "recording: {e}");
                }
            }
            if let (Some(view), Some(channels)) = (view, s.channels) {
                view.publish(channels.agents, nanos, boxes.into_bytes());
            }
        }
        Job::Finish { scene, done } => {
            let path = scenes.remove(&scene).and_then(|s| finish(scene, s, view));
            let _ = done.send(path);
        }
    }
}

fn finish(id: u64, scene: WriterScene, view: Option<&LiveView>) -> Option<String> {
    let path = scene.recorder.and_then(|r| match r.finish() {
        Ok(path) => Some(path.display().to_string()),
        Err(e) => {
            tracing::warn!(scene = id, "recording: {e}");
            None
        }
    });
    if let (Some(view), Some(channels)) = (view, scene.channels) {
        // Viewers clear the scene's entities before its channels go.
        let nanos = unix_nanos(SystemTime::now());
        let clear = clear_update(nanos).to_string();
        view.publish_reliable(channels.agents, nanos, clear.clone().into_bytes());
        view.publish_reliable(channels.map, nanos, clear.into_bytes());
        view.unadvertise(channels.agents);
        view.unadvertise(channels.map);
    }
    path
}
