//! `road router`: a zenoh router, zenoh's router mode in this binary, so that a deployment of
//! several `road serve` needs nothing beside `road` (a stock `zenohd` works the same). Servers
//! and ego clients in client mode connect to it; each server owns the keys under its own
//! prefix, and clients find servers through it (`docs/deploy.md`).

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use road_client::ZenohArgs;
use zenoh::Wait;

#[derive(Debug, Args)]
pub struct RouterArgs {
    #[command(flatten)]
    pub zenoh: ZenohArgs,
}

pub fn run(mut args: RouterArgs) -> Result<ExitCode> {
    match args.zenoh.mode.as_deref() {
        None | Some("router") => args.zenoh.mode = Some("router".into()),
        Some(other) => anyhow::bail!("--mode {other}: road router runs in router mode only"),
    }
    let config = args.zenoh.to_config()?;
    let stop = crate::signals::termination()?;
    let session = zenoh::open(config)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("cannot open the router's zenoh session")?;
    out!("road router: zenoh id {}", session.zid());
    for endpoint in &args.zenoh.listen {
        out!("road router: listening on {endpoint}");
    }
    let signal = stop.recv().context("the signal handler went away")?;
    tracing::info!("{signal}: closing the router");
    session
        .close()
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("closing the router's session")?;
    Ok(ExitCode::SUCCESS)
}
