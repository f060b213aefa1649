//! An example ego stack: creates a scene on the procedural roundabout, drives its ego (agent 1)
//! at the speed of its history along its last heading (a log-replay-style ego that does not
//! react), prints each tick's latency and infractions, and closes the scene.
//!
//! ```sh
//! road serve --listen tcp/127.0.0.1:7447 --no-multicast-scouting &
//! cargo run -p road-client --example ego -- --connect tcp/127.0.0.1:7447 --no-multicast-scouting
//! ```

use std::process::ExitCode;

use clap::Parser;
use road_client::protocol::{AgentState, CreateScene, DEFAULT_PREFIX};
use road_client::{Client, ZenohArgs};

#[derive(Debug, Parser)]
struct Args {
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// The server's key prefix.
    #[arg(long, default_value = DEFAULT_PREFIX)]
    prefix: String,
    #[arg(long, default_value = "example-ego")]
    client: String,
    #[arg(long, default_value_t = 50)]
    ticks: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

fn main() -> ExitCode {
    match run(Args::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> Result<(), road_client::Error> {
    let client = Client::open(&args.zenoh, &args.prefix, &args.client)?;
    let mut scene = client.create(CreateScene::procedural("roundabout", vec![1], args.seed))?;
    let created = scene.created().clone();
    println!(
        "scene {} on {} ({} agents), planner {}",
        created.scene,
        created.checkpoint,
        created.agents.len(),
        created.planner
    );
    let ego = created
        .agents
        .iter()
        .find(|a| a.external)
        .expect("agent 1 is external");
    let h = &ego.history;
    let (last, previous) = (h[h.len() - 1], h[h.len() - 2]);
    let (vx, vy) = (last.x_m - previous.x_m, last.y_m - previous.y_m);
    for t in 1..=args.ticks {
        let k = t as f64;
        let npc = scene.step(
            t,
            vec![AgentState {
                id: ego.id,
                x_m: last.x_m + vx * k,
                y_m: last.y_m + vy * k,
                heading_rad: last.heading_rad,
            }],
        )?;
        println!(
            "tick {:>3}: {:>6.1} ms, {} NPCs, collisions {:?}, off road {:?}{}",
            npc.tick,
            npc.latency_ms,
            npc.npcs.len(),
            npc.collisions,
            npc.off_road,
            if npc.late_external.is_empty() {
                ""
            } else {
                " (late: the model drove the ego)"
            }
        );
    }
    let closed = scene.close()?;
    println!(
        "closed after {} ticks; recording {}",
        closed.ticks,
        closed.recording.as_deref().unwrap_or("none")
    );
    Ok(())
}
