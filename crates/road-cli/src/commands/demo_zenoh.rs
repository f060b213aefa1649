//! `road demo` (the default path): the whole product in one command. A `road serve` runs in
//! this process on loopback (TCP 127.0.0.1, scouting off), a scripted ego client (the demo's
//! ego, which does not yield) drives a procedural map (`--map`) over zenoh, the server
//! populates the map around it and keeps vehicles entering (or, `--scripted`, runs the map's
//! script), the server's
//! recording of the scene is kept as `demo.mcap` (Foxglove shows `/map` and `/agents`) and
//! drawn as `demo.gif` (`road render`). Prints every tick's round trip, server latency, engine
//! time and infractions, then their summary.

use std::collections::BTreeSet;
use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use road_client::protocol::{AgentState, CreateScene, DEFAULT_PREFIX};
use road_client::{Client, ZenohArgs};
use road_data::WindowConfig;
use road_serve::models::{embedded, find_models_dir};
use road_serve::server::percentiles;
use road_serve::{ServeConfig, Server};
use road_sim::closed_loop::ExternalDriver;
use road_sim::procedural::{ProceduralMap, STEP_SECS, procedural};

use crate::commands::render::render_gif;
use crate::recording::Recording;

#[allow(clippy::too_many_arguments)] // the demo's checkpoint, engine, scene, traffic and outputs
pub fn run(
    checkpoint: &Path,
    engine: road_serve::ServeEngine,
    map: ProceduralMap,
    steps: usize,
    seed: u64,
    mcap_out: &Path,
    gif_out: &Path,
    populate: Option<usize>,
    initialiser: Option<String>,
    inflow_per_minute: Option<f64>,
) -> Result<ExitCode> {
    let name = checkpoint
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("checkpoint {} has no folder name", checkpoint.display()))?;
    // The shipped default runs anywhere: from its folder when there is one, else embedded.
    let models = if checkpoint.is_dir() {
        find_models_dir(checkpoint.parent())?
    } else if name == embedded::NAME {
        find_models_dir(None)?
    } else {
        anyhow::bail!("no checkpoint folder {}", checkpoint.display());
    };
    let record = std::env::temp_dir().join(format!("road-demo-{}", std::process::id()));
    let mut config = ServeConfig::new(models);
    config.default_checkpoint = name.to_owned();
    config.record_dir = Some(record.clone());
    config.engine = engine;
    config.gpu_precision = crate::commands::gpu_options::context_options()?.precision;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let server = Server::new(
        config,
        ZenohArgs::loopback(Some(&endpoint), None).to_config()?,
    )
    .start()
    .with_context(|| {
        format!(
            "cannot start the demo server with checkpoint {}",
            checkpoint.display()
        )
    })?;
    let mut client = Client::open(
        &ZenohArgs::loopback(None, Some(&endpoint)),
        DEFAULT_PREFIX,
        "demo-ego",
    )?;
    client.set_timeout(Duration::from_secs(120));
    // The same scripted ego as `road demo`: its route through the map at constant speed.
    let procedural_scene = procedural(map, &WindowConfig::default(), 2)?;
    let mut request = CreateScene::procedural(map.name(), vec![1], seed);
    request.populate = populate.map(|n| road_client::protocol::Populate {
        vehicles: Some(u32::try_from(n).unwrap_or(u32::MAX)),
        vehicles_per_100m: None,
        refine: true,
        initialiser: initialiser.clone(),
    });
    // Inflow keeps the scene at its vehicles at the start (the ego and the placed or scripted
    // ones).
    let start = populate.map_or(procedural_scene.routes.len(), |n| n + 1);
    request.inflow = inflow_per_minute.map(|rate| road_client::protocol::Inflow {
        vehicles_per_minute: rate,
        max_vehicles: Some(u32::try_from(start).unwrap_or(u32::MAX)),
    });
    let mut scene = client.create(request)?;
    let vehicles = scene.created().agents.len();
    let mut ego = procedural_scene.ego;
    let mut rtt_ms = Vec::with_capacity(steps);
    let mut compute_ms = Vec::with_capacity(steps);
    let mut events = Vec::new();
    let (mut seen_pairs, mut seen_off) = (BTreeSet::new(), BTreeSet::new());
    let mut late = 0;
    let drawn_by = initialiser.map_or_else(String::new, |i| format!(", drawn by {i}"));
    out!(
        "road demo over zenoh: procedural {}, {vehicles} vehicles (ego 1 scripted by the client, {} by {name}{drawn_by}), {steps} ticks of {STEP_SECS:.1} s on loopback",
        map.name(),
        vehicles - 1
    );
    for t in 1..=steps as u64 {
        let p = ego.pose(0, 0, (t - 1) as usize, &[])?;
        let sent = Instant::now();
        let npc = scene.step(
            t,
            vec![AgentState {
                id: 1,
                x_m: p.x_m,
                y_m: p.y_m,
                heading_rad: p.heading_rad,
            }],
        )?;
        rtt_ms.push(sent.elapsed().as_secs_f64() * 1e3);
        compute_ms.push(npc.compute_ms);
        late += usize::from(!npc.late_external.is_empty());
        let secs = t as f64 * STEP_SECS;
        for pair in &npc.collisions {
            if seen_pairs.insert(*pair) {
                events.push(format!(
                    "tick {t:>3} ({secs:4.1} s): collision of agents {} and {}",
                    pair[0], pair[1]
                ));
            }
        }
        for a in &npc.off_road {
            if seen_off.insert(*a) {
                events.push(format!("tick {t:>3} ({secs:4.1} s): agent {a} off road"));
            }
        }
        for a in &npc.entered {
            events.push(format!(
                "tick {t:>3} ({secs:4.1} s): agent {} entered the map",
                a.id
            ));
        }
        for a in &npc.left {
            events.push(format!(
                "tick {t:>3} ({secs:4.1} s): agent {a} drove off the map and left the scene"
            ));
        }
        let mut infractions: Vec<String> = npc
            .collisions
            .iter()
            .map(|p| format!("collision {}-{}", p[0], p[1]))
            .chain(npc.off_road.iter().map(|a| format!("{a} off road")))
            .collect();
        if !npc.late_external.is_empty() {
            infractions.push("ego late: the model drove it".into());
        }
        out!(
            "tick {t:>3} ({secs:4.1} s): round trip {:7.1} ms, server {:7.1} ms, engine {:7.1} ms; {}",
            rtt_ms[rtt_ms.len() - 1],
            npc.latency_ms,
            npc.compute_ms,
            if infractions.is_empty() {
                "no infraction".to_owned()
            } else {
                infractions.join(", ")
            }
        );
    }
    let closed = scene.close()?;
    server.stop()?;
    let recording = closed
        .recording
        .context("the demo server recorded nothing")?;
    std::fs::copy(&recording, mcap_out)
        .with_context(|| format!("cannot write {}", mcap_out.display()))?;
    let _ = std::fs::remove_dir_all(&record);

    let (r, c) = (percentiles(&rtt_ms[1..]), percentiles(&compute_ms[1..]));
    out!(
        "first tick (with the warm-up): {:.1} ms round trip; then round trip p50 {:.2} ms, p99 {:.2} ms; engine p50 {:.2} ms, p99 {:.2} ms; late ticks {late}",
        rtt_ms[0],
        r.p50_ms,
        r.p99_ms,
        c.p50_ms,
        c.p99_ms
    );
    if events.is_empty() {
        out!("infractions: none (no collision, nobody off road)");
    } else {
        out!(
            "infractions: {} collision pair(s), {} vehicle(s) off road",
            seen_pairs.len(),
            seen_off.len()
        );
        for e in &events {
            out!("  {e}");
        }
    }
    out!("recording: {}", mcap_out.display());
    let recording = Recording::read(mcap_out)?;
    let rendered = render_gif(&recording, gif_out, 1.0 / STEP_SECS, 800)?;
    out!(
        "animation: {} ({} frames: the scene at creation and every tick)",
        gif_out.display(),
        rendered.frames
    );
    Ok(ExitCode::SUCCESS)
}
