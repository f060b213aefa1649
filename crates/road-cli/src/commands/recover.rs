//! `road recover FILE…`: recordings cut off by a killed `road serve` (no summary, often a
//! partial chunk at the end) rewritten whole, so that the default readers open them (Python's
//! `mcap.reader.make_reader`, the `mcap` CLI, Foxglove): every complete message before the cut
//! is kept, in order, and the summary follows. A file that already has its summary is left as
//! it is. A server does the same at start for its own folder's files (`road_serve::recover`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;
use road_serve::recover::{Recovery, recover};

#[derive(Debug, Args)]
pub struct RecoverArgs {
    /// Recordings (`road serve --record DIR`'s `scene-<id>.mcap`, or any MCAP file).
    #[arg(required = true, value_name = "FILE")]
    pub files: Vec<PathBuf>,
}

/// One line per file on stdout (an error on stderr); fails if any file could not be recovered.
pub fn run(args: RecoverArgs) -> Result<ExitCode> {
    let mut failed = 0usize;
    for file in &args.files {
        match recover(file) {
            Ok(Recovery::Recovered(r)) => out!(
                "{}: recovered {} messages; {} trailing bytes dropped (the record cut off)",
                file.display(),
                r.messages,
                r.dropped_bytes
            ),
            Ok(Recovery::Complete) => out!(
                "{}: already complete (it has its summary); left as is",
                file.display()
            ),
            Err(e) => {
                failed += 1;
                eprintln!("error: {:#}", anyhow::Error::new(e));
            }
        }
    }
    anyhow::ensure!(
        failed == 0,
        "{failed} of {} file(s) not recovered",
        args.files.len()
    );
    Ok(ExitCode::SUCCESS)
}
