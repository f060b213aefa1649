//! `road compare`: paired differences between models that `road eval --json` evaluated on the
//! same scenes (in one run or in several), against a baseline model, with 95 % bootstrap
//! intervals over scenes. Pairing removes the scene-to-scene spread that the separate
//! intervals of `road eval` carry, so two levers can be told apart on fewer scenes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use road_sim::metrics::{BOOTSTRAP_RESAMPLES, Estimate, bootstrap_ratio};
use serde_json::Value;

#[derive(Debug, Args)]
pub struct CompareArgs {
    /// `road eval --json` files of one suite (forecasting or reactivity) over the same scenes.
    #[arg(required = true, num_args = 1..)]
    pub files: Vec<PathBuf>,
    /// The model every other one is compared with (its name in the files); default: the first
    /// file's first model.
    #[arg(long)]
    pub baseline: Option<String>,
}

/// One model's per-scene figures: the validation window (absent in files written before
/// `road eval` recorded it) and the suite's values.
struct ModelRows {
    model: String,
    file: PathBuf,
    scenes: Vec<(Option<usize>, Vec<f64>)>,
}

/// Per-scene (weighted difference, weight) from the two models' fields.
type Difference = fn(&[f64], &[f64]) -> (f64, f64);

/// A suite's per-scene fields and the differences `road compare` reports.
struct Suite {
    fields: &'static [&'static str],
    /// Fields that files written by older builds lack: NaN where absent, after `fields`.
    optional_fields: &'static [&'static str],
    /// (column title, difference); a column whose difference is NaN for some scene (a field
    /// absent from one of the files) shows as such rather than a number.
    columns: &'static [(&'static str, Difference)],
}

/// A rate's per-scene value, 0 where the scene has nothing to count (no moving step, say);
/// NaN stays NaN (a field the file lacks).
fn rate(count: f64, of: f64) -> f64 {
    if of == 0.0 { 0.0 } else { count / of }
}

const FORECASTING: Suite = Suite {
    fields: &[
        "min_scene_ade_m",
        "min_scene_fde_m",
        "missed_agents",
        "agents",
    ],
    optional_fields: &[],
    columns: &[
        ("ΔminSceneADE (m)", |a, b| (a[0] - b[0], 1.0)),
        ("ΔminSceneFDE (m)", |a, b| (a[1] - b[1], 1.0)),
        // The same agents in both: the pooled miss-rate difference.
        ("Δmiss rate", |a, b| (a[2] - b[2], a[3])),
    ],
};

/// Models run `samples` simulations per scene, the baselines one: per-scene rates, their
/// difference weighted like the pooled rates (collisions per scene, off-road per driven agent
/// of one simulation).
const REACTIVITY: Suite = Suite {
    fields: &[
        "simulations",
        "adversary_collisions",
        "any_collisions",
        "driven_agents",
        "off_road_agents",
    ],
    // Since 2026-11-26: per driven step and per moving step (≥ 2 m/s); since its fifth
    // session, per pair of consecutive moving steps.
    optional_fields: &[
        "driven_steps",
        "reversing_steps",
        "moving_steps",
        "sliding_steps",
        "moving_pairs",
        "sharp_turns",
    ],
    columns: &[
        ("Δadversary collision rate", |a, b| {
            (a[1] / a[0] - b[1] / b[0], 1.0)
        }),
        ("Δany-collision rate", |a, b| {
            (a[2] / a[0] - b[2] / b[0], 1.0)
        }),
        ("Δoff-road rate", |a, b| {
            let drivers = b[3] / b[0];
            (drivers * (a[4] / a[3] - b[4] / b[3]), drivers)
        }),
        ("Δreversing steps", |a, b| {
            let steps = b[5] / b[0];
            (steps * (rate(a[6], a[5]) - rate(b[6], b[5])), steps)
        }),
        ("Δsliding steps", |a, b| {
            let steps = b[7] / b[0];
            (steps * (rate(a[8], a[7]) - rate(b[8], b[7])), steps)
        }),
        ("Δsharp turns", |a, b| {
            let pairs = b[9] / b[0];
            (pairs * (rate(a[10], a[9]) - rate(b[10], b[9])), pairs)
        }),
    ],
};

pub fn run(args: CompareArgs) -> Result<ExitCode> {
    let mut suite_name: Option<String> = None;
    let mut models: Vec<ModelRows> = Vec::new();
    for path in &args.files {
        let (name, rows) = read(path)?;
        match &suite_name {
            None => suite_name = Some(name),
            Some(first) if *first != name => bail!(
                "{} is a {name} evaluation, {} a {first} one: compare one suite at a time",
                path.display(),
                args.files[0].display()
            ),
            Some(_) => {}
        }
        for rows in rows {
            match models.iter().find(|m| m.model == rows.model) {
                // The same model (a baseline every run adds) from a later file: the first wins.
                Some(first) => tracing::info!(
                    model = %rows.model,
                    kept = %first.file.display(),
                    skipped = %rows.file.display(),
                    "model in several files"
                ),
                None => models.push(rows),
            }
        }
    }
    let suite_name = suite_name.expect("at least one file (clap requires it)");
    let suite = suite(&suite_name);
    let baseline = match &args.baseline {
        Some(name) => models.iter().find(|m| &m.model == name).with_context(|| {
            format!(
                "no model `{name}` in the files; they hold: {}",
                models
                    .iter()
                    .map(|m| m.model.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?,
        None => &models[0],
    };
    out!(
        "{suite_name}: paired per-scene differences against {} ({}), 95 % percentile bootstrap over scenes, {BOOTSTRAP_RESAMPLES} resamples",
        baseline.model,
        baseline.file.display()
    );
    let titles: Vec<&str> = suite.columns.iter().map(|c| c.0).collect();
    out!(
        "| model | scenes paired | {} |",
        titles
            .iter()
            .map(|t| format!("{t} [95 % CI]"))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    out!("|---|---:|{}", "---:|".repeat(titles.len()));
    for model in models.iter().filter(|m| m.model != baseline.model) {
        let (pairs, by_position) = pair(model, baseline)?;
        let cells: Vec<String> = suite
            .columns
            .iter()
            .map(|(_, diff)| {
                let values: Vec<(f64, f64)> = pairs.iter().map(|(a, b)| diff(a, b)).collect();
                if values.iter().any(|(d, w)| d.is_nan() || w.is_nan()) {
                    "(not in every file)".to_owned()
                } else {
                    show(bootstrap_ratio(&values, 0x5eed))
                }
            })
            .collect();
        out!(
            "| {} | {}{} | {} |",
            model.model,
            pairs.len(),
            if by_position { " (by position)" } else { "" },
            cells.join(" | ")
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn show(e: Estimate) -> String {
    format!("{:+.3} [{:+.3}, {:+.3}]", e.value, e.ci_low, e.ci_high)
}

fn suite(name: &str) -> &'static Suite {
    match name {
        "reactivity" => &REACTIVITY,
        _ => &FORECASTING,
    }
}

/// The suite's name and every model's per-scene rows of one `road eval --json` file.
fn read(path: &Path) -> Result<(String, Vec<ModelRows>)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let json: Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not JSON (a `road eval --json` file)", path.display()))?;
    let at = |what: &str| format!("{}: {what}", path.display());
    let suite_name = json["suite"]
        .as_str()
        .with_context(|| at("no `suite` (not a `road eval --json` file)"))?
        .to_owned();
    if !matches!(suite_name.as_str(), "forecasting" | "reactivity") {
        bail!(at(&format!(
            "suite `{suite_name}`; road compare knows forecasting and reactivity"
        )));
    }
    let suite = suite(&suite_name);
    let results = json["results"]
        .as_array()
        .with_context(|| at("no `results` list"))?;
    let mut models = Vec::new();
    for (i, result) in results.iter().enumerate() {
        let model = result["model"]
            .as_str()
            .with_context(|| at(&format!("results[{i}] has no `model`")))?
            .to_owned();
        let Some(per_scene) = result["per_scene"].as_array() else {
            bail!(at(&format!(
                "model `{model}` has no `per_scene` figures (written before road eval kept them): \
                 evaluate it again"
            )));
        };
        let mut scenes = Vec::with_capacity(per_scene.len());
        for (k, scene) in per_scene.iter().enumerate() {
            let window = scene["window"].as_u64().map(|w| w as usize);
            let values = suite
                .fields
                .iter()
                .map(|field| {
                    scene[*field].as_f64().with_context(|| {
                        at(&format!(
                            "model `{model}`, per_scene[{k}]: no number `{field}`"
                        ))
                    })
                })
                .chain(
                    suite
                        .optional_fields
                        .iter()
                        .map(|field| Ok(scene[*field].as_f64().unwrap_or(f64::NAN))),
                )
                .collect::<Result<Vec<f64>>>()?;
            scenes.push((window, values));
        }
        models.push(ModelRows {
            model,
            file: path.to_owned(),
            scenes,
        });
    }
    Ok((suite_name, models))
}

/// The two models' figures scene by scene: by validation window where both files name them,
/// else by position (the same `road eval` settings select the same scenes in the same order),
/// which the caller reports.
#[allow(clippy::type_complexity)]
fn pair<'a>(
    model: &'a ModelRows,
    baseline: &'a ModelRows,
) -> Result<(Vec<(&'a [f64], &'a [f64])>, bool)> {
    let ids = |m: &ModelRows| m.scenes.iter().all(|s| s.0.is_some());
    if ids(model) && ids(baseline) {
        let of_baseline: BTreeMap<usize, &[f64]> = baseline
            .scenes
            .iter()
            .map(|(w, v)| (w.expect("checked"), v.as_slice()))
            .collect();
        let pairs: Vec<_> = model
            .scenes
            .iter()
            .filter_map(|(w, v)| {
                of_baseline
                    .get(&w.expect("checked"))
                    .map(|b| (v.as_slice(), *b))
            })
            .collect();
        if pairs.is_empty() {
            bail!(
                "`{}` ({}) and `{}` ({}) share no scene",
                model.model,
                model.file.display(),
                baseline.model,
                baseline.file.display()
            );
        }
        return Ok((pairs, false));
    }
    if model.scenes.len() != baseline.scenes.len() {
        bail!(
            "`{}` ({}, {} scenes) and `{}` ({}, {} scenes) cannot be paired: one file has no \
             scene ids and the counts differ",
            model.model,
            model.file.display(),
            model.scenes.len(),
            baseline.model,
            baseline.file.display(),
            baseline.scenes.len()
        );
    }
    let pairs = model
        .scenes
        .iter()
        .zip(&baseline.scenes)
        .map(|(a, b)| (a.1.as_slice(), b.1.as_slice()))
        .collect();
    Ok((pairs, true))
}
