//! `road eval`: the paper's evaluation suites on validation scenes (forecasting, reactivity)
//! and `road demo`'s closed loop counted over procedural maps (procedural, and long sessions
//! with inflow: long). Each suite is a
//! module of its own; what they share is in `common`.

mod common;
mod forecasting;
mod initialisation;
mod long;
mod procedural;
mod reactivity;

use std::process::ExitCode;

use anyhow::{Result, bail};

pub use common::EvalArgs;

pub fn run(args: EvalArgs) -> Result<ExitCode> {
    match args.suite.as_str() {
        "forecasting" => forecasting::run(args),
        "reactivity" => reactivity::run(args),
        "procedural" => procedural::run(args),
        "long" => long::run(args),
        "initialisation" => initialisation::run(args),
        other => {
            bail!(
                "unknown suite `{other}`; available: forecasting, reactivity, procedural, long, \
             initialisation"
            )
        }
    }
}
