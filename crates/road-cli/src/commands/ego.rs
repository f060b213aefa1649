//! `road ego`: the scripted ego of `road demo` as a stand-alone zenoh client of any
//! `road serve`: it creates scenes on a procedural map (on one server, or each on the
//! least-loaded server found under a root), drives ego 1 along its route at constant speed
//! (it does not yield) and prints every tick's round trip and infractions, then a summary per
//! server. Deployments use it as a smoke test (`docker/compose.yaml`, `docs/deploy.md`).

use std::collections::BTreeMap;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use road_client::protocol::{AgentState, CreateScene, DEFAULT_PREFIX};
use road_client::{Client, Scene, ZenohArgs};
use road_data::WindowConfig;
use road_serve::server::percentiles;
use road_sim::closed_loop::ExternalDriver;
use road_sim::procedural::{ProceduralMap, STEP_SECS, procedural};
use zenoh::Wait;

#[derive(Debug, Args)]
pub struct EgoArgs {
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// The server's key prefix (ignored with `--discover`).
    #[arg(long, default_value = DEFAULT_PREFIX)]
    pub prefix: String,
    /// Find the servers under this root (`road` finds `road` and `road/east`) and put each
    /// scene on the least-loaded one.
    #[arg(long, value_name = "ROOT")]
    pub discover: Option<String>,
    /// The procedural map.
    #[arg(long, default_value = "roundabout", value_parser = crate::commands::demo::parse_map)]
    pub map: ProceduralMap,
    /// Scenes to run side by side.
    #[arg(long, default_value_t = 1)]
    pub scenes: usize,
    /// Ticks per scene.
    #[arg(long, default_value_t = 60)]
    pub ticks: u64,
    /// Seed of the first scene (scene i gets seed + i).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Client id (scene i's client is `<id>-<i>`).
    #[arg(long, default_value = "road-ego")]
    pub client: String,
    /// Seconds a creation or a tick may take (a scene's first tick holds the warm-up).
    #[arg(long, default_value_t = 120.0)]
    pub timeout_s: f64,
    /// Seconds to wait for the servers to appear (with `--discover`).
    #[arg(long, default_value_t = 10.0)]
    pub wait_s: f64,
    /// Print the summary only.
    #[arg(long)]
    pub quiet: bool,
}

/// One scene of the run and the client that keeps it.
struct Driven {
    _client: Client,
    scene: Scene,
    server: String,
    rtt_ms: Vec<f64>,
    late: usize,
    infractions: usize,
}

pub fn run(args: EgoArgs) -> Result<ExitCode> {
    anyhow::ensure!(args.scenes >= 1, "--scenes must be at least 1");
    anyhow::ensure!(args.ticks >= 1, "--ticks must be at least 1");
    anyhow::ensure!(
        args.timeout_s.is_finite() && args.timeout_s > 0.0,
        "--timeout-s must be positive, got {}",
        args.timeout_s
    );
    let timeout = Duration::from_secs_f64(args.timeout_s);
    let session = zenoh::open(args.zenoh.to_config()?)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("cannot open the zenoh session")?;
    let script = procedural(args.map, &WindowConfig::default(), 2)?;
    let mut driven = Vec::with_capacity(args.scenes);
    for i in 0..args.scenes {
        let id = format!("{}-{i}", args.client);
        let request = CreateScene {
            // The server stops there and waits for the close (no late-ego tick after the last).
            max_ticks: Some(args.ticks),
            ..CreateScene::procedural(args.map.name(), vec![1], args.seed + i as u64)
        };
        let (client, scene) = match &args.discover {
            Some(root) => place(&session, root, &id, request, timeout, args.wait_s)
                .with_context(|| format!("scene {i}: no server under {root} took it"))?,
            None => {
                let mut client = Client::with_session(session.clone(), &args.prefix, &id)?;
                client.set_timeout(timeout);
                let scene = client
                    .create(request)
                    .with_context(|| format!("scene {i} on {}", args.prefix))?;
                (client, scene)
            }
        };
        let server = client.keys().prefix().to_owned();
        out!(
            "scene {i}: id {} on {server} ({} agents, ego 1 scripted)",
            scene.id(),
            scene.created().agents.len()
        );
        driven.push(Driven {
            _client: client,
            scene,
            server,
            rtt_ms: Vec::new(),
            late: 0,
            infractions: 0,
        });
    }

    let mut ego = script.ego;
    let mut failures = Vec::new();
    for t in 1..=args.ticks {
        let p = ego.pose(0, 0, (t - 1) as usize, &[])?;
        let pose = AgentState {
            id: 1,
            x_m: p.x_m,
            y_m: p.y_m,
            heading_rad: p.heading_rad,
        };
        let sent = Instant::now();
        for d in &driven {
            d.scene.put(t, vec![pose])?;
        }
        for (i, d) in driven.iter_mut().enumerate() {
            match d.scene.wait_tick(t) {
                Ok(npc) => {
                    d.rtt_ms.push(sent.elapsed().as_secs_f64() * 1e3);
                    d.late += usize::from(!npc.late_external.is_empty());
                    d.infractions += npc.collisions.len() + npc.off_road.len();
                    if !args.quiet {
                        out!(
                            "tick {t:>4} ({:5.1} s) scene {i} on {}: round trip {:7.1} ms, engine {:6.1} ms, {} collision(s), {} off road",
                            t as f64 * STEP_SECS,
                            d.server,
                            d.rtt_ms[d.rtt_ms.len() - 1],
                            npc.compute_ms,
                            npc.collisions.len(),
                            npc.off_road.len()
                        );
                    }
                }
                Err(e) => failures.push(format!(
                    "tick {t}: scene {i} (id {}) on {}: {e}",
                    d.scene.id(),
                    d.server
                )),
            }
        }
        if !failures.is_empty() {
            break;
        }
    }

    let mut by_server: BTreeMap<&str, (usize, Vec<f64>, usize)> = BTreeMap::new();
    for d in &driven {
        let entry = by_server.entry(&d.server).or_default();
        entry.0 += 1;
        entry
            .1
            .extend_from_slice(d.rtt_ms.get(1..).unwrap_or_default());
        entry.2 += d.late;
    }
    for (server, (scenes, rtt, late)) in &by_server {
        let p = percentiles(rtt);
        out!(
            "{server}: {scenes} scene(s), {} tick(s) after the first, round trip p50 {:.1} ms, p99 {:.1} ms; late {late}",
            rtt.len(),
            p.p50_ms,
            p.p99_ms
        );
    }
    let infractions: usize = driven.iter().map(|d| d.infractions).sum();
    out!("infractions (collisions and off-road agents, summed over ticks): {infractions}");
    if !failures.is_empty() {
        for f in &failures {
            eprintln!("error: {f}");
        }
        return Ok(ExitCode::FAILURE);
    }
    for (i, d) in driven.into_iter().enumerate() {
        let server = d.server.clone();
        let closed = d
            .scene
            .close()
            .with_context(|| format!("closing scene {i} on {server}"))?;
        if let Some(recording) = closed.recording {
            out!("scene {i}: recorded by {server} at {recording}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Places a scene on the least-loaded server under `root`, waiting up to `wait_s` for one to
/// appear (servers announce themselves when they start).
fn place(
    session: &zenoh::Session,
    root: &str,
    id: &str,
    request: CreateScene,
    timeout: Duration,
    wait_s: f64,
) -> Result<(Client, Scene)> {
    let until = Instant::now() + Duration::from_secs_f64(wait_s.max(0.0));
    loop {
        match Client::create_on_least_loaded(session.clone(), root, id, request.clone(), timeout) {
            Ok(placed) => return Ok(placed),
            Err(road_client::Error::NoServer { .. }) if Instant::now() < until => {
                std::thread::sleep(Duration::from_millis(250));
            }
            Err(e) => return Err(e.into()),
        }
    }
}
