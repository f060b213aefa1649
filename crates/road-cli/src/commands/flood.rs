//! `road bench flood`: what refused input costs everyone else. A `road serve` child process
//! (this binary, TCP on loopback) serves one scene ticking at an ego stack's pace (the victim)
//! while a second session floods the server with oversized creations. Reported per phase
//! (without the flood: the baseline; with it): the victim's round trips, the server's resident
//! memory, and what became of the floods (refused with `payload_too_large`, or dropped by
//! zenoh's message-size limit before the server saw them).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use road_client::Client;
use road_client::protocol::{CreateScene, DEFAULT_PREFIX, ErrorCode};
use zenoh::Wait;

use crate::commands::soak::{footprint, start_server};

#[derive(Debug, Args)]
pub struct FloodBenchArgs {
    /// Bytes of each oversized creation (the server's limit is 8 MiB).
    #[arg(long, default_value_t = 50_000_000)]
    pub flood_bytes: usize,
    /// Victim ticks per phase.
    #[arg(long, default_value_t = 100)]
    pub ticks: u64,
    /// The victim's ego rate.
    #[arg(long, default_value_t = 10.0)]
    pub rate_hz: f64,
    #[arg(long)]
    pub json: bool,
}

/// One phase's figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FloodPhase {
    pub phase: &'static str,
    pub victim_ticks: usize,
    pub round_trip: road_client::protocol::Percentiles,
    pub rss_before_mib: f64,
    pub rss_peak_mib: f64,
    pub rss_after_mib: f64,
    pub floods_sent: usize,
    pub floods_refused: usize,
    pub floods_unanswered: usize,
}

pub fn run(args: &FloodBenchArgs) -> Result<()> {
    anyhow::ensure!(args.ticks >= 1, "--ticks must be at least 1");
    anyhow::ensure!(
        args.rate_hz.is_finite() && args.rate_hz > 0.0,
        "--rate-hz must be positive"
    );
    let (server, endpoint, session) = start_server(&[], None, &[])?;
    let pid = server.0.id();
    let mut victim = Client::with_session(session.clone(), DEFAULT_PREFIX, "victim")?;
    victim.set_timeout(Duration::from_secs(60));
    let mut scene = victim.create(CreateScene::procedural("roundabout", vec![1], 0))?;
    let mut tick = 0u64;
    let mut step = |scene: &mut road_client::Scene| -> Result<f64> {
        tick += 1;
        let ego = scene
            .created()
            .constant_velocity(1, tick)
            .context("the roundabout's agent 1 has a history")?;
        let sent = Instant::now();
        scene.step(tick, vec![ego])?;
        Ok(sent.elapsed().as_secs_f64() * 1e3)
    };
    // The first tick carries the model's warm-up: not part of either phase.
    step(&mut scene)?;
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let mut phases = Vec::new();
    for flooding in [false, true] {
        let stop = Arc::new(AtomicBool::new(false));
        let (sent, refused, unanswered) = (
            Arc::new(AtomicUsize::new(0)),
            Arc::new(AtomicUsize::new(0)),
            Arc::new(AtomicUsize::new(0)),
        );
        let flooder = flooding.then(|| {
            let (stop, sent, refused, unanswered) = (
                stop.clone(),
                sent.clone(),
                refused.clone(),
                unanswered.clone(),
            );
            let endpoint = endpoint.clone();
            let bytes = args.flood_bytes;
            std::thread::spawn(move || -> Result<()> {
                let own = zenoh::open(
                    road_client::ZenohArgs::loopback(None, Some(&endpoint)).to_config()?,
                )
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
                let mut flooder = Client::with_session(own, DEFAULT_PREFIX, "flooder")?;
                flooder.set_timeout(Duration::from_secs(2));
                let payload = vec![b' '; bytes];
                while !stop.load(Ordering::Relaxed) {
                    sent.fetch_add(1, Ordering::Relaxed);
                    match flooder.query_raw(&flooder.keys().create(), payload.clone()) {
                        Ok(Err(e)) if e.code == ErrorCode::PayloadTooLarge => {
                            refused.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {
                            unanswered.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                Ok(())
            })
        });
        let before = footprint(pid, 0, None)?.rss_mib;
        let mut peak = before;
        let mut round_trips = Vec::new();
        let started = Instant::now();
        for i in 0..args.ticks {
            round_trips.push(step(&mut scene)?);
            peak = peak.max(footprint(pid, 0, None)?.rss_mib);
            let next = started + period.mul_f64((i + 1) as f64);
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
        }
        stop.store(true, Ordering::Relaxed);
        if let Some(flooder) = flooder {
            flooder
                .join()
                .map_err(|_| anyhow::anyhow!("the flooding thread panicked"))??;
        }
        phases.push(FloodPhase {
            phase: if flooding { "flood" } else { "baseline" },
            victim_ticks: round_trips.len(),
            round_trip: road_serve::server::percentiles(&round_trips),
            rss_before_mib: before,
            rss_peak_mib: peak,
            rss_after_mib: footprint(pid, 0, None)?.rss_mib,
            floods_sent: sent.load(Ordering::Relaxed),
            floods_refused: refused.load(Ordering::Relaxed),
            floods_unanswered: unanswered.load(Ordering::Relaxed),
        });
    }
    scene.close()?;
    drop(server);
    if args.json {
        out!("{}", serde_json::to_string_pretty(&phases)?);
        return Ok(());
    }
    out!(
        "road bench flood: one scene at {} Hz for {} ticks a phase, then the same while another session sends {} MB creations back to back",
        args.rate_hz,
        args.ticks,
        args.flood_bytes as f64 / 1e6
    );
    out!(
        "| phase | victim round trip p50 / p99 / max ms | server resident MiB before / peak / after | floods sent / refused / unanswered |"
    );
    out!("|---|---:|---:|---:|");
    for p in &phases {
        out!(
            "| {} | {:.2} / {:.2} / {:.2} | {:.1} / {:.1} / {:.1} | {} / {} / {} |",
            p.phase,
            p.round_trip.p50_ms,
            p.round_trip.p99_ms,
            p.round_trip.max_ms,
            p.rss_before_mib,
            p.rss_peak_mib,
            p.rss_after_mib,
            p.floods_sent,
            p.floods_refused,
            p.floods_unanswered
        );
    }
    Ok(())
}
