//! SIGINT and SIGTERM as a message, so that long-running commands (`road serve`,
//! `road router`) close their sessions and finish their recordings when a terminal or a
//! container runtime stops them.

use std::sync::mpsc::{self, Receiver};

use anyhow::{Context, Result};

/// A channel that receives the name of the signal when SIGINT or SIGTERM arrives. Call once
/// per process.
pub fn termination() -> Result<Receiver<&'static str>> {
    let (tx, rx) = mpsc::channel();
    ctrlc::set_handler(move || {
        let _ = tx.send("SIGINT or SIGTERM");
    })
    .context("cannot install the SIGINT/SIGTERM handler")?;
    Ok(rx)
}
