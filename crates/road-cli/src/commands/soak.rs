//! `road bench soak`: a `road serve` child process (this binary, TCP on loopback, recording on)
//! takes N scene cycles from one client session: a new client id, create a scene on the
//! procedural roundabout, tick it, close it. The server's resident memory, open file
//! descriptors and threads (read from `/proc/<pid>`) are sampled before the first scene,
//! after a warm-up (the pool, the checkpoint, zenoh's buffers are in place: the baseline) and
//! every few hundred cycles to the end: a leak shows as a slope against the baseline.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use road_client::protocol::{CreateScene, DEFAULT_PREFIX};
use road_client::{Client, ZenohArgs};
use zenoh::Wait;

#[derive(Debug, Args)]
pub struct SoakBenchArgs {
    /// Scene create/tick/close cycles after the warm-up.
    #[arg(long, default_value_t = 1000)]
    pub cycles: usize,
    /// Cycles before the baseline sample.
    #[arg(long, default_value_t = 20)]
    pub warmup: usize,
    /// Ticks per scene (the first holds the model's warm-up).
    #[arg(long, default_value_t = 1)]
    pub ticks: u64,
    /// Sample the server every this many cycles.
    #[arg(long, default_value_t = 250)]
    pub sample_every: usize,
    /// The server records nothing (tells recording's share of a growth).
    #[arg(long)]
    pub no_record: bool,
    /// One client id for every cycle (no liveliness token comes and goes).
    #[arg(long)]
    pub same_client: bool,
    /// A new zenoh session for every cycle (clients that come and go) instead of one session
    /// for the whole soak.
    #[arg(long)]
    pub session_per_cycle: bool,
    /// Run the server under this command (a heap profiler: `--wrapper valgrind
    /// --wrapper=--tool=massif`), one argument per flag; its process is the one sampled.
    #[arg(long, allow_hyphen_values = true)]
    pub wrapper: Vec<String>,
    #[arg(long)]
    pub json: bool,
}

/// The server process's footprint at one moment.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Footprint {
    pub cycles: usize,
    pub rss_mib: f64,
    pub open_fds: usize,
    pub threads: usize,
    pub recordings: usize,
}

/// Kills the server when the bench ends, however it ends.
pub(crate) struct ServerProcess(pub(crate) Child);

impl Drop for ServerProcess {
    /// SIGTERM first (the server closes its scenes; a profiler wrapping it writes its report),
    /// SIGKILL after 30 s.
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.0.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The server process's resident memory, descriptors and threads now (`/proc`, Linux).
/// `record`: the folder whose recordings are counted (none: 0).
pub(crate) fn footprint(
    pid: u32,
    cycles: usize,
    record: Option<&std::path::Path>,
) -> Result<Footprint> {
    let status_path = format!("/proc/{pid}/status");
    let status = std::fs::read_to_string(&status_path)
        .with_context(|| format!("cannot read {status_path} (Linux only)"))?;
    let field = |name: &str| -> Result<u64> {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("no {name} in {status_path}"))
    };
    let open_fds = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .with_context(|| format!("cannot list /proc/{pid}/fd"))?
        .count();
    let recordings = record
        .and_then(|r| std::fs::read_dir(r).ok())
        .map_or(0, |d| d.count());
    Ok(Footprint {
        cycles,
        rss_mib: field("VmRSS:")? as f64 / 1024.0,
        open_fds,
        threads: field("Threads:")? as usize,
        recordings,
    })
}

pub fn run(args: &SoakBenchArgs) -> Result<()> {
    anyhow::ensure!(args.cycles >= 1, "--cycles must be at least 1");
    anyhow::ensure!(args.sample_every >= 1, "--sample-every must be at least 1");
    let record: PathBuf = std::env::temp_dir().join(format!("road-soak-{}", std::process::id()));
    let recording = (!args.no_record).then_some(record.as_path());
    let (server, endpoint, session) = start_server(&args.wrapper, recording, &[])?;
    let pid = server.0.id();
    let mut samples = vec![footprint(pid, 0, Some(&record))?];
    let total = args.warmup + args.cycles;
    let started = Instant::now();
    let mut timed_from = Instant::now();
    for i in 1..=total {
        let client = if args.same_client {
            "soak".to_owned()
        } else {
            format!("soak-{i}")
        };
        if args.session_per_cycle {
            let own = zenoh::open(ZenohArgs::loopback(None, Some(&endpoint)).to_config()?)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            cycle(&own, &client, i, args.ticks).with_context(|| format!("cycle {i}"))?;
            own.close().wait().map_err(|e| anyhow::anyhow!("{e}"))?;
        } else {
            cycle(&session, &client, i, args.ticks).with_context(|| format!("cycle {i}"))?;
        }
        if i == args.warmup {
            samples.push(footprint(pid, i, Some(&record))?);
            timed_from = Instant::now();
        } else if i > args.warmup
            && ((i - args.warmup).is_multiple_of(args.sample_every) || i == total)
        {
            samples.push(footprint(pid, i, Some(&record))?);
        }
    }
    let timed_secs = timed_from.elapsed().as_secs_f64();
    drop(server);
    let _ = std::fs::remove_dir_all(&record);
    if args.json {
        out!("{}", serde_json::to_string_pretty(&samples)?);
        return Ok(());
    }
    out!(
        "road bench soak: {total} cycles ({} warm-up) of create, {} tick(s), close against one `road serve` (recording {}, {}, {}), {:.1} s in all, {:.1} cycles/s after the warm-up",
        args.warmup,
        args.ticks,
        if args.no_record { "off" } else { "on" },
        if args.same_client {
            "one client id"
        } else {
            "a client id per cycle"
        },
        if args.session_per_cycle {
            "a zenoh session per cycle"
        } else {
            "one zenoh session"
        },
        started.elapsed().as_secs_f64(),
        args.cycles as f64 / timed_secs
    );
    out!("| cycles | resident MiB | open fds | threads | recordings |");
    out!("|---:|---:|---:|---:|---:|");
    for s in &samples {
        out!(
            "| {} | {:.1} | {} | {} | {} |",
            s.cycles,
            s.rss_mib,
            s.open_fds,
            s.threads,
            s.recordings
        );
    }
    let (base, end) = (
        &samples[1.min(samples.len() - 1)],
        &samples[samples.len() - 1],
    );
    out!(
        "after the warm-up to the end: resident {:+.1} MiB, open fds {:+}, threads {:+}",
        end.rss_mib - base.rss_mib,
        end.open_fds as i64 - base.open_fds as i64,
        end.threads as i64 - base.threads as i64
    );
    Ok(())
}

/// One cycle: a fresh client id (its liveliness token comes and goes), a scene, its ticks, its
/// close.
fn cycle(session: &zenoh::Session, client: &str, i: usize, ticks: u64) -> Result<()> {
    let mut client = Client::with_session(session.clone(), DEFAULT_PREFIX, client)?;
    client.set_timeout(Duration::from_secs(120));
    let mut scene = client.create(CreateScene::procedural("roundabout", vec![1], i as u64))?;
    for t in 1..=ticks {
        let ego = scene
            .created()
            .constant_velocity(1, t)
            .context("the roundabout's agent 1 has a history")?;
        scene.step(t, vec![ego])?;
    }
    let closed = scene.close()?;
    anyhow::ensure!(
        closed.ticks == ticks,
        "scene {} closed after {} ticks, not {ticks}",
        closed.scene,
        closed.ticks
    );
    Ok(())
}

/// A `road serve` child of this binary on a free loopback port (under `wrapper`, when given),
/// recording into `record` (a fresh folder) or not, with `extra` flags; returns once its status
/// answers: the process, its endpoint and a session connected to it.
pub(crate) fn start_server(
    wrapper: &[String],
    record: Option<&std::path::Path>,
    extra: &[&str],
) -> Result<(ServerProcess, String, zenoh::Session)> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    if let Some(record) = record {
        let _ = std::fs::remove_dir_all(record);
    }
    let exe = std::env::current_exe().context("cannot find this binary")?;
    let mut command = match wrapper.split_first() {
        Some((program, rest)) => {
            let mut c = Command::new(program);
            c.args(rest).arg(&exe);
            c
        }
        None => Command::new(&exe),
    };
    let mut server = ServerProcess(
        command
            .args(["serve", "--listen", &endpoint, "--no-multicast-scouting"])
            .args(["--late-ego-ms", "0"])
            .args(match record {
                None => vec!["--no-record".into()],
                Some(dir) => vec!["--record".into(), dir.as_os_str().to_owned()],
            })
            .args(extra)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("cannot start {} serve", exe.display()))?,
    );
    let session = zenoh::open(ZenohArgs::loopback(None, Some(&endpoint)).to_config()?)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if let Some(status) = server.0.try_wait()? {
            bail!("road serve exited early: {status}");
        }
        let mut probe = Client::with_session(session.clone(), DEFAULT_PREFIX, "bench-probe")?;
        probe.set_timeout(Duration::from_secs(2));
        if probe.status().is_ok() {
            break;
        }
        anyhow::ensure!(Instant::now() < deadline, "road serve did not come up");
        std::thread::sleep(Duration::from_millis(200));
    }
    Ok((server, endpoint, session))
}
