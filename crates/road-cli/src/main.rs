//! `road`: the traffic NPC server's command-line program.

/// `println!` for results: a closed stdout (`road … | head`) ends the program quietly, as
/// SIGPIPE would, instead of panicking.
macro_rules! out {
    ($($arg:tt)*) => { $crate::write_stdout_line(format_args!($($arg)*)) };
}

mod commands;
mod config;
mod plot;
mod recording;
mod signals;

pub(crate) fn write_stdout_line(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
    if let Err(e) = writeln!(std::io::stdout().lock(), "{args}") {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("error: cannot write to stdout: {e}");
        std::process::exit(1);
    }
}

use clap::{Parser, Subcommand};

/// Rolling-ahead diffusion traffic simulation: data, scheduling and GPU tools.
#[derive(Debug, Parser)]
#[command(name = "road", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// The main job on its embedded default: a procedural roundabout served by `road serve`
    /// in this process to a scripted ego over zenoh on loopback; prints every tick's latency and
    /// infractions, writes the recording (`demo.mcap`) and its animation (`demo.gif`).
    Demo(commands::demo::DemoArgs),
    /// The networked NPC server over Eclipse Zenoh: ego stacks create scenes, put their ego
    /// every tick and get the NPCs back; every scene recorded to MCAP (`docs/protocol.md`).
    Serve(commands::serve::ServeArgs),
    /// A zenoh router (zenoh's router mode in this binary): several `road serve` and their
    /// clients meet through it (`docs/deploy.md`).
    Router(commands::router::RouterArgs),
    /// A scripted ego client of `road serve` (the demo's ego): creates scenes on one server or
    /// on the least-loaded ones found under a root, drives them, prints round trips.
    Ego(commands::ego::EgoArgs),
    /// A scene recording of `road serve` (MCAP) as an animated GIF, one frame per tick.
    Render(commands::render::RenderArgs),
    /// A scene recording's protocol messages published again over zenoh at the recorded pace.
    Replay(commands::replay::ReplayArgs),
    /// Recordings cut off by a killed server rewritten whole (with their summary), so that the
    /// default MCAP readers open them; a complete file is left as it is.
    Recover(commands::recover::RecoverArgs),
    /// INTERACTION data: statistics and binary caches for training.
    #[command(subcommand)]
    Data(commands::data::DataCommand),
    /// The noise scheduler: inspect a planner's per-step noise levels and NFE.
    #[command(subcommand)]
    Sched(commands::sched::SchedCommand),
    /// Train a denoiser (RoAD, AR, DJINN) on the INTERACTION caches.
    Train(commands::train::TrainArgs),
    /// Sample futures of a validation scene with a checkpoint and draw them as a PNG.
    Sample(commands::sample::SampleArgs),
    /// The paper's evaluation on validation scenes: forecasting and reactivity suites.
    Eval(commands::eval::EvalArgs),
    /// Paired per-scene differences between models of `road eval --json` files (same scenes),
    /// against a baseline, with bootstrap intervals.
    Compare(commands::compare::CompareArgs),
    /// Throughput benchmarks (training, scheduler), each against a baseline from the same run.
    #[command(subcommand)]
    Bench(commands::bench::BenchCommand),
    /// The GPU: which adapter wgpu picks here, and a self-test of the kernels.
    #[command(subcommand)]
    Gpu(commands::gpu::GpuCommand),
}

/// Training runs `train.workers` threads of its own; candle's matrix products must then stay on
/// their caller's thread (it reads `RAYON_NUM_THREADS` on every product). A value the user set
/// is kept.
#[allow(unsafe_code)]
fn single_threaded_matmuls() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        // SAFETY: called from `main` before this program starts any thread, so nothing reads
        // the environment concurrently.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    }
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
                tracing_subscriber::EnvFilter::new("info,wgpu_core=warn,wgpu_hal=warn,naga=warn")
            }),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    if matches!(
        cli.command,
        Command::Train(_) | Command::Bench(commands::bench::BenchCommand::Train(_))
    ) {
        single_threaded_matmuls();
    }
    let result = match cli.command {
        Command::Demo(args) => commands::demo::run(args),
        Command::Serve(args) => commands::serve::run(args),
        Command::Router(args) => commands::router::run(args),
        Command::Ego(args) => commands::ego::run(args),
        Command::Render(args) => commands::render::run(args),
        Command::Replay(args) => commands::replay::run(args),
        Command::Recover(args) => commands::recover::run(args),
        Command::Data(cmd) => commands::data::run(cmd),
        Command::Sched(cmd) => commands::sched::run(cmd),
        Command::Gpu(cmd) => commands::gpu::run(cmd),
        Command::Train(args) => commands::train::run(args),
        Command::Sample(args) => commands::sample::run(args),
        Command::Bench(cmd) => commands::bench::run(cmd),
        Command::Eval(args) => commands::eval::run(args),
        Command::Compare(args) => commands::compare::run(args),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
