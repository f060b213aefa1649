//! `road bench serve --zenoh`: the whole front end on loopback. A `road serve` runs in this
//! process (TCP on 127.0.0.1, scouting off, recording on, no late-ego deadline); B client
//! threads each drive a roundabout scene with a constant-velocity ego, one tick at a time.
//! Per tick: the round trip at the client (put → NPCs received) beside the engine compute of
//! the same tick (the baseline: the engine time of the batched rounds the tick took part in),
//! and their difference, the front end's overhead (zenoh both ways, JSON, checks, recording,
//! the core's bookkeeping between rounds).

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
    pub scenes: usize,
    pub timed_ticks: usize,
    pub rtt_p50_ms: f64,
    pub rtt_p99_ms: f64,
    pub compute_p50_ms: f64,
    pub compute_p99_ms: f64,
    pub overhead_p50_ms: f64,
    pub overhead_p99_ms: f64,
    pub scene_ticks_per_s: f64,
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// Runs the benchmark for each scene count; `checkpoint` is a folder under a models folder.
pub fn run(checkpoint: &Path, scene_counts: &[usize], ticks: usize) -> Result<Vec<ZenohRow>> {
    anyhow::ensure!(ticks > 0, "--ticks must be at least 1");
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
        config.record_dir = Some(record.clone());
        config.late_ego_deadline = Duration::ZERO;
        config.capacity = b.max(1);
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
                Ok(std::thread::spawn(move || -> Result<Vec<(f64, f64)>> {
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
                    for t in 2..=ticks as u64 + 1 {
                        let sent = Instant::now();
                        let npc = scene.step(t, vec![ego_at(&created, t)?])?;
                        out.push((sent.elapsed().as_secs_f64() * 1e3, npc.compute_ms));
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
        let rtt: Vec<f64> = samples.iter().map(|s| s.0).collect();
        let compute: Vec<f64> = samples.iter().map(|s| s.1).collect();
        let overhead: Vec<f64> = samples.iter().map(|s| s.0 - s.1).collect();
        let (r, c, o) = (
            percentiles(&rtt),
            percentiles(&compute),
            percentiles(&overhead),
        );
        rows.push(ZenohRow {
            scenes: b,
            timed_ticks: ticks,
            rtt_p50_ms: r.p50_ms,
            rtt_p99_ms: r.p99_ms,
            compute_p50_ms: c.p50_ms,
            compute_p99_ms: c.p99_ms,
            overhead_p50_ms: o.p50_ms,
            overhead_p99_ms: o.p99_ms,
            scene_ticks_per_s: samples.len() as f64 / wall_s,
        });
    }
    let _ = std::fs::remove_dir_all(&record);
    Ok(rows)
}

/// The roundabout's agent 1 at `tick`, at constant velocity from its history.
fn ego_at(created: &SceneCreated, tick: u64) -> Result<AgentState> {
    created
        .constant_velocity(1, tick)
        .context("the roundabout's agent 1 has a history")
}

/// Prints the table and the real-time estimate.
pub fn print(rows: &[ZenohRow]) {
    out!(
        "| scenes | timed ticks | round trip p50 / p99 ms | engine compute p50 / p99 ms | front-end overhead p50 / p99 ms | scene-ticks/s |"
    );
    out!("|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        out!(
            "| {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} |",
            r.scenes,
            r.timed_ticks,
            r.rtt_p50_ms,
            r.rtt_p99_ms,
            r.compute_p50_ms,
            r.compute_p99_ms,
            r.overhead_p50_ms,
            r.overhead_p99_ms,
            r.scene_ticks_per_s
        );
    }
    if let Some(best) = rows
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
