//! `road replay`: a scene recording's protocol messages published again over zenoh, at the
//! pace they were recorded (log-time gaps divided by `--speed`), on the keys a live server
//! uses for that scene: the client's ego ticks on `<prefix>/client/<client>/scene/<id>/ego`,
//! the server's NPC
//! ticks on `…/npc` and its errors on `…/error`. Ego stacks, viewers and bridges can be tried
//! against a recorded scene without a server. The creation request and reply (a query and
//! its answer, no key to put them on) and the Foxglove topics are not replayed.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use road_client::ZenohArgs;
use road_protocol::Keys;
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::recording::{Recording, topics};

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// A scene recording (`road serve --record`, `road demo`); a file cut off by a killed
    /// server replays up to its last complete chunk.
    pub file: PathBuf,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Key expressions live under this prefix. A live server on the same prefix would take
    /// the replayed ego ticks for its own scene of that id: use another prefix beside one.
    #[arg(long, default_value = road_protocol::DEFAULT_PREFIX)]
    pub prefix: String,
    /// The client id in the keys; default: the recording's (its creation request's).
    #[arg(long)]
    pub client: Option<String>,
    /// Replay speed: 2 plays twice as fast as recorded.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Seconds to wait for a subscriber of the scene's keys before the first message (zenoh
    /// learns of remote subscribers shortly after connecting); 0 starts at once.
    #[arg(long, default_value_t = 2.0)]
    pub wait_s: f64,
}

pub fn run(args: ReplayArgs) -> Result<ExitCode> {
    anyhow::ensure!(
        args.speed.is_finite() && args.speed > 0.0,
        "--speed must be positive, got {}",
        args.speed
    );
    anyhow::ensure!(
        args.wait_s.is_finite() && args.wait_s >= 0.0,
        "--wait-s must be 0 or more, got {}",
        args.wait_s
    );
    let keys = Keys::new(&args.prefix);
    anyhow::ensure!(
        !keys.prefix().is_empty(),
        "--prefix must name at least one key chunk"
    );
    let recording = Recording::read(&args.file)?;
    let path = recording.path.display();
    let scene = recording.scene_id().with_context(|| {
        format!(
            "no scene id (no {} or {} message) in {path}",
            topics::CREATED,
            topics::NPC
        )
    })?;
    let client = match args.client {
        Some(client) => client,
        None => recording.client_id().with_context(|| {
            format!(
                "no client id (no {} or {} message naming one) in {path}: give --client",
                topics::CREATE,
                topics::EGO
            )
        })?,
    };
    anyhow::ensure!(
        road_protocol::valid_client_id(&client),
        "client id {client:?} in {path}: expected 1 to 64 ASCII letters, digits, '-' or '_'"
    );
    let routes = [
        (topics::EGO, keys.ego(&client, scene)),
        (topics::NPC, keys.npc(&client, scene)),
        (topics::ERROR, keys.error(&client, &scene.to_string())),
    ];
    let queue: Vec<(usize, &mcap::Message<'static>)> = recording
        .messages
        .iter()
        .filter_map(|m| {
            let route = routes.iter().position(|(t, _)| *t == m.channel.topic)?;
            Some((route, m))
        })
        .collect();
    anyhow::ensure!(
        !queue.is_empty(),
        "nothing to replay: no {}, {} or {} messages in {path}",
        topics::EGO,
        topics::NPC,
        topics::ERROR
    );

    let session = zenoh::open(args.zenoh.to_config()?)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot open a zenoh session: {e}"))?;
    let publishers = routes
        .iter()
        .map(|(_, key)| {
            session
                .declare_publisher(key.clone())
                // A replay is the record of what was said: none of it dropped.
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(|e| anyhow::anyhow!("cannot publish on {key}: {e}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let deadline = Instant::now() + Duration::from_secs_f64(args.wait_s);
    loop {
        let mut matched = false;
        for p in &publishers {
            matched |= p
                .matching_status()
                .wait()
                .map_err(|e| anyhow::anyhow!("zenoh: {e}"))?
                .matching();
        }
        if matched {
            break;
        }
        if Instant::now() >= deadline {
            if args.wait_s > 0.0 {
                tracing::warn!(
                    "no subscriber of {} after {} s: replaying anyway",
                    routes[1].1,
                    args.wait_s
                );
            }
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }

    let first_ns = queue[0].1.log_time;
    let started = Instant::now();
    let mut counts = [0usize; 3];
    for &(route, m) in &queue {
        let recorded_s = m.log_time.saturating_sub(first_ns) as f64 * 1e-9;
        let due = started + Duration::from_secs_f64(recorded_s / args.speed);
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        publishers[route]
            .put(m.data.to_vec())
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot publish on {}: {e}", routes[route].1))?;
        counts[route] += 1;
    }
    let replayed_s = started.elapsed().as_secs_f64();
    drop(publishers);
    // Closing drains what is still queued for the subscribers.
    session
        .close()
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot close the zenoh session: {e}"))?;

    let recorded_s = queue[queue.len() - 1].1.log_time.saturating_sub(first_ns) as f64 * 1e-9;
    out!(
        "road replay: {path}: scene {scene}, {} messages, {recorded_s:.2} s recorded, replayed in {replayed_s:.2} s (speed {})",
        queue.len(),
        args.speed
    );
    for ((topic, key), count) in routes.iter().zip(counts) {
        out!("  {topic} -> {key}: {count} published");
    }
    let mut skipped = std::collections::BTreeMap::<&str, usize>::new();
    for m in &recording.messages {
        if !routes.iter().any(|(t, _)| *t == m.channel.topic) {
            *skipped.entry(m.channel.topic.as_str()).or_default() += 1;
        }
    }
    for (topic, count) in skipped {
        out!("  {topic}: {count} not replayed (no key to put it on)");
    }
    if recording.cut_off.is_some() {
        out!("  the recording was cut off: replayed up to its last complete chunk");
    }
    Ok(ExitCode::SUCCESS)
}
