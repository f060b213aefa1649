//! `road sched …`: the noise scheduler's plans, printed.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use road_sched::{PlannerSpec, PlannerTables, StageKind};

#[derive(Debug, Subcommand)]
pub enum SchedCommand {
    /// Print a planner's per-step noise levels σ per window slot for each stage it runs, and
    /// its NFE per simulated step.
    Plan(PlanArgs),
    /// List the planners of a planners file with their windows and NFE per simulated step.
    List(ListArgs),
}

#[derive(Debug, Args)]
pub struct ListArgs {
    /// Planners file (TOML: one table per planner).
    #[arg(long, default_value = "configs/planners.toml")]
    pub planners: PathBuf,
}

#[derive(Debug, Args)]
pub struct PlanArgs {
    /// Planner name in the planners file.
    pub name: String,
    #[arg(long, default_value = "configs/planners.toml")]
    pub planners: PathBuf,
    /// Simulated steps over which NFE per step is averaged.
    #[arg(long, default_value_t = 40)]
    pub ticks: u64,
}

/// Reads a planners file: `[name]` tables of [`PlannerSpec`], validated.
pub fn load_planners(path: &std::path::Path) -> Result<Vec<(String, PlannerSpec)>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read planners file {}", path.display()))?;
    let table: toml::Table =
        toml::from_str(&text).with_context(|| format!("bad planners file {}", path.display()))?;
    let mut out = Vec::new();
    for (name, value) in table {
        let spec: PlannerSpec = value
            .try_into()
            .with_context(|| format!("bad planner `{name}` in {}", path.display()))?;
        spec.validate(&name)
            .with_context(|| format!("in {}", path.display()))?;
        out.push((name, spec));
    }
    Ok(out)
}

pub fn run(cmd: SchedCommand) -> Result<ExitCode> {
    match cmd {
        SchedCommand::List(args) => {
            out!("| planner | kind | sampler | n | F | K | X | NFE per step (40 steps) |");
            out!("|---|---|---|---:|---:|---:|---:|---:|");
            for (name, spec) in load_planners(&args.planners)? {
                let ticks = if spec.kind == road_sched::PlannerKind::OneShot {
                    spec.future_slots as u64
                } else {
                    40
                };
                out!(
                    "| {name} | {:?} | {:?} | {} | {} | {} | {} | {:.2} |",
                    spec.kind,
                    spec.sampler,
                    spec.obs_slots,
                    spec.future_slots,
                    spec.steps_per_diffusion,
                    spec.replan_every.map_or("-".into(), |x| x.to_string()),
                    spec.expected_nfe_per_step(ticks)
                );
            }
        }
        SchedCommand::Plan(args) => {
            let planners = load_planners(&args.planners)?;
            let Some((name, spec)) = planners.into_iter().find(|(n, _)| *n == args.name) else {
                bail!("no planner `{}` in {}", args.name, args.planners.display());
            };
            let tables = PlannerTables::new(&name, spec.clone())?;
            let stages: &[StageKind] = match spec.kind {
                road_sched::PlannerKind::Rolling | road_sched::PlannerKind::Autoregressive => {
                    &[StageKind::Warmup, StageKind::Rolling]
                }
                _ => &[StageKind::Full],
            };
            for &stage in stages {
                let table = tables.stage(stage);
                out!(
                    "{stage:?} stage: {} steps, {} NFE ({:?}); σ per slot (observed slots first)",
                    table.steps(),
                    table.nfe(),
                    spec.sampler
                );
                for s in 0..table.steps() {
                    let p = table.step(s);
                    let row: Vec<String> = p.sigma_cur.iter().map(|v| format!("{v:8.3}")).collect();
                    out!("step {s:>3} nfe {} | {}", p.nfe, row.join(" "));
                }
                let last = table.step(table.steps() - 1);
                let row: Vec<String> = last.sigma_next.iter().map(|v| format!("{v:8.3}")).collect();
                out!("end          | {}", row.join(" "));
            }
            out!(
                "NFE per simulated step over {} steps: {:.2}",
                args.ticks,
                spec.expected_nfe_per_step(args.ticks)
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
