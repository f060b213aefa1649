//! `road bench serve --zenoh`: the whole front end on loopback. A `road serve` runs in this
//! process (TCP on 127.0.0.1, scouting off, recording on, no late-ego deadline); B client
//! threads each drive a roundabout scene with a constant-velocity ego, one tick at a time.
//! Per tick: the round trip at the client (put → NPCs received) beside the engine compute of
//! the same tick (the baseline: the engine time of the batched rounds the tick took part in)
//! and its queue wait (the engine time of other scenes' rounds that were running when its ego
//! came: continuous batching's cost, not the front end's), both from the reply; what is left
//! is the front end's overhead (zenoh both ways, JSON, checks, recording, the core's
//! bookkeeping between rounds).

use std::path::Path;
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use road_client::protocol::{AgentState, CreateScene, DEFAULT_PREFIX, SceneCreated};
use road_client::{Client, ZenohArgs};
use road_serve::models::find_models_dir;
use road_serve::server::percentiles;
use road_serve::{ServeConfig, Server};
use zenoh::Wait;

/// One row of the table.
#[derive(Debug, serde::Serialize)]
pub struct ZenohRow {
    /// The server's engine: `cpu` or `gpu`.
    pub engine: &'static str,
    pub scenes: usize,
    /// The clients' tick rate; `None`: each puts its next ego as soon as it has the NPCs.
    pub rate_hz: Option<f64>,
    pub timed_ticks: usize,
    pub rtt_p50_ms: f64,
    pub rtt_p99_ms: f64,
    pub compute_p50_ms: f64,
    pub compute_p99_ms: f64,
    pub queue_p50_ms: f64,
    pub queue_p99_ms: f64,
    /// Round trip − compute − queue wait.
    pub front_end_p50_ms: f64,
    pub front_end_p99_ms: f64,
    /// Of the front end, the server's own time: reply latency − compute − queue wait.
    pub server_own_p50_ms: f64,
    pub server_own_p99_ms: f64,
    /// Of the front end, the rest: round trip − reply latency (zenoh both ways, the
    /// publication, the client).
    pub transport_p50_ms: f64,
    pub transport_p99_ms: f64,
    pub scene_ticks_per_s: f64,
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// Runs the benchmark for each scene count; `checkpoint` is a folder under a models folder.
/// With `rate_hz`, client i puts tick t at `start + (t + i / B) / rate`, or at once when its
/// NPCs came later than that.
pub fn run(
    checkpoint: &Path,
    engine: road_serve::ServeEngine,
    scene_counts: &[usize],
    ticks: usize,
    rate_hz: Option<f64>,
) -> Result<Vec<ZenohRow>> {
    anyhow::ensure!(ticks > 0, "--ticks must be at least 1");
    if let Some(rate) = rate_hz {
        anyhow::ensure!(
            rate.is_finite() && rate > 0.0,
            "--rate-hz {rate} must be a positive number of ticks per second"
        );
    }
    let period = rate_hz.map(|rate| Duration::from_secs_f64(1.0 / rate));
    let name = checkpoint
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("checkpoint {} has no folder name", checkpoint.display()))?;
    let models = find_models_dir(checkpoint.parent())?;
    let record = std::env::temp_dir().join(format!("road-bench-zenoh-{}", std::process::id()));
    let mut rows = Vec::new();
    for &b in scene_counts {
        anyhow::ensure!(b > 0, "--scenes must be at least 1");
        let mut config = ServeConfig::new(models.clone());
        config.default_checkpoint = name.to_owned();
        config.record_dir = if std::env::var_os("NOREC").is_some() {
            None
        } else {
            Some(record.clone())
        };
        config.late_ego_deadline = Duration::ZERO;
        config.capacity = b.max(1);
        config.engine = engine;
        config.gpu_precision = crate::commands::gpu_options::context_options()?.precision;
        let endpoint = format!("tcp/127.0.0.1:{}", free_port()?);
        let server = Server::new(
            config,
            ZenohArgs::loopback(Some(&endpoint), None).to_config()?,
        )
        .start()?;
        let session = zenoh::open(ZenohArgs::loopback(None, Some(&endpoint)).to_config()?)
            .wait()
            .map_err(|e| anyhow::anyhow!("zenoh: {e}"))?;
        let ready = Arc::new(Barrier::new(b + 1));
        let go = Arc::new(Barrier::new(b + 1));
        let threads: Vec<_> = (0..b)
            .map(|i| -> Result<_> {
                let mut client =
                    Client::with_session(session.clone(), DEFAULT_PREFIX, &format!("bench-{i}"))?;
                client.set_timeout(Duration::from_secs(300));
                let (ready, go) = (Arc::clone(&ready), Arc::clone(&go));
                Ok(std::thread::spawn(move || -> Result<Vec<TickTimes>> {
                    let prepared = (|| -> Result<_> {
                        let mut scene = client.create(CreateScene::procedural(
                            "roundabout",
                            vec![1],
                            i as u64,
                        ))?;
                        let created = scene.created().clone();
                        // The first tick carries the warm-up: not timed.
                        scene.step(1, vec![ego_at(&created, 1)?])?;
                        Ok((scene, created))
                    })();
                    // Every thread meets the barriers, even one that failed to prepare.
                    ready.wait();
                    go.wait();
                    let (mut scene, created) = prepared?;
                    let mut out = Vec::with_capacity(ticks);
                    let clock = Instant::now();
                    for t in 2..=ticks as u64 + 1 {
                        if let Some(period) = period {
                            let slot = (t - 2) as f64 + i as f64 / b as f64;
                            let due = clock + period.mul_f64(slot);
                            std::thread::sleep(due.saturating_duration_since(Instant::now()));
                        }
                        let sent = Instant::now();
                        let npc = scene.step(t, vec![ego_at(&created, t)?])?;
                        out.push(TickTimes {
                            round_trip_ms: sent.elapsed().as_secs_f64() * 1e3,
                            latency_ms: npc.latency_ms,
                            compute_ms: npc.compute_ms,
                            queue_ms: npc.queue_ms,
                        });
                    }
                    scene.close()?;
                    Ok(out)
                }))
            })
            .collect::<Result<_>>()?;
        ready.wait();
        let started = Instant::now();
        go.wait();
        let mut samples = Vec::new();
        for t in threads {
            samples.extend(
                t.join()
                    .map_err(|_| anyhow::anyhow!("a client thread panicked"))??,
            );
        }
        let wall_s = started.elapsed().as_secs_f64();
        server.stop()?;
        let of = |f: fn(&TickTimes) -> f64| percentiles(&samples.iter().map(f).collect::<Vec<_>>());
        let (r, c, q, o) = (
            of(|t| t.round_trip_ms),
            of(|t| t.compute_ms),
            of(|t| t.queue_ms),
            of(|t| t.round_trip_ms - t.compute_ms - t.queue_ms),
        );
        let (own, transport) = (
            of(|t| t.latency_ms - t.compute_ms - t.queue_ms),
            of(|t| t.round_trip_ms - t.latency_ms),
        );
        rows.push(ZenohRow {
            engine: match engine {
                road_serve::ServeEngine::Cpu => "cpu",
                road_serve::ServeEngine::Gpu => "gpu",
            },
            scenes: b,
            rate_hz,
            timed_ticks: ticks,
            rtt_p50_ms: r.p50_ms,
            rtt_p99_ms: r.p99_ms,
            compute_p50_ms: c.p50_ms,
            compute_p99_ms: c.p99_ms,
            queue_p50_ms: q.p50_ms,
            queue_p99_ms: q.p99_ms,
            front_end_p50_ms: o.p50_ms,
            front_end_p99_ms: o.p99_ms,
            server_own_p50_ms: own.p50_ms,
            server_own_p99_ms: own.p99_ms,
            transport_p50_ms: transport.p50_ms,
            transport_p99_ms: transport.p99_ms,
            scene_ticks_per_s: samples.len() as f64 / wall_s,
        });
    }
    let _ = std::fs::remove_dir_all(&record);
    Ok(rows)
}

/// One timed tick as its client saw it.
struct TickTimes {
    round_trip_ms: f64,
    /// From the reply: ego arrival to the reply's making (before its publication).
    latency_ms: f64,
    /// From the reply: engine time of the rounds the tick took part in.
    compute_ms: f64,
    /// From the reply: engine time of other scenes' rounds it waited for.
    queue_ms: f64,
}

/// The roundabout's agent 1 at `tick`, at constant velocity from its history.
fn ego_at(created: &SceneCreated, tick: u64) -> Result<AgentState> {
    created
        .constant_velocity(1, tick)
        .context("the roundabout's agent 1 has a history")
}

/// Prints the table and the real-time estimate.
pub fn print(rows: &[ZenohRow]) {
    if let Some(first) = rows.first() {
        out!("server engine: {}", first.engine);
    }
    if let Some(rate) = rows.first().and_then(|r| r.rate_hz) {
        out!("clients paced at {rate} Hz (phases spread over the period)");
    }
    out!(
        "| scenes | timed ticks | round trip p50 / p99 ms | engine compute p50 / p99 ms | queue wait p50 / p99 ms | front end p50 / p99 ms | of which server p50 / p99 ms | of which zenoh & client p50 / p99 ms | scene-ticks/s |"
    );
    out!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        out!(
            "| {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} |",
            r.scenes,
            r.timed_ticks,
            r.rtt_p50_ms,
            r.rtt_p99_ms,
            r.compute_p50_ms,
            r.compute_p99_ms,
            r.queue_p50_ms,
            r.queue_p99_ms,
            r.front_end_p50_ms,
            r.front_end_p99_ms,
            r.server_own_p50_ms,
            r.server_own_p99_ms,
            r.transport_p50_ms,
            r.transport_p99_ms,
            r.scene_ticks_per_s
        );
    }
    if let Some(rate) = rows.first().and_then(|r| r.rate_hz) {
        for r in rows {
            out!(
                "{} scenes at {rate} Hz: round trip p99 {:.1} ms against a period of {:.1} ms ({})",
                r.scenes,
                r.rtt_p99_ms,
                1e3 / rate,
                if r.rtt_p99_ms <= 1e3 / rate {
                    "kept"
                } else {
                    "not kept"
                }
            );
        }
    } else if let Some(best) = rows
        .iter()
        .map(|r| r.scene_ticks_per_s)
        .max_by(f64::total_cmp)
    {
        out!(
            "real time at 10 Hz: about {:.0} scenes on this engine (best measured {:.1} scene-ticks/s ÷ 10)",
            (best / 10.0).floor(),
            best
        );
    }
}
