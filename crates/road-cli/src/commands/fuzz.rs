//! `road bench fuzz`: the server's protocol decoders and checks on generated inputs, the way
//! `road serve` runs them on what arrives (no network): `CreateScene` parsed and checked field
//! by field down to the map (a Lanelet2 `.osm` by value included) and the checkpoint,
//! `EgoTick` parsed and checked against a live scene, `CloseScene` parsed. Inputs come from
//! proptest strategies, in three families: arbitrary bytes, arbitrary JSON documents (keys
//! drawn from the protocol's field names, values of every JSON type and extreme numbers), and
//! valid messages with one part replaced, removed or added. A panic is a finding: its input is
//! written to `--findings` and the command fails; every finding becomes a bad-input test.
//! Each input's outcome (accepted or refused with a code) is counted, so a decoder that
//! accepts everything shows.

use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use road_protocol::{CloseScene, CreateScene, EgoTick, ErrorReply, parse};
use road_serve::ServeConfig;
use road_serve::models::{Checkpoints, find_models_dir, planners};
use road_serve::pool::{Pool, PoolKey};
use road_serve::scene::{LiveScene, SetupContext, setup};
use serde_json::{Value, json};

#[derive(Debug, Args)]
pub struct FuzzBenchArgs {
    /// Inputs per target and family.
    #[arg(long, default_value_t = 20_000)]
    pub execs: usize,
    /// Seed of the generators (the same seed gives the same inputs).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where the inputs that panicked are written.
    #[arg(long, default_value = "fuzz-findings")]
    pub findings: PathBuf,
}

/// The protocol's field names, so that generated objects hit real fields often.
const KEYS: &[&str] = &[
    "map",
    "procedural",
    "osm",
    "file",
    "agents",
    "id",
    "length_m",
    "width_m",
    "history",
    "x_m",
    "y_m",
    "heading_rad",
    "external",
    "planner",
    "checkpoint",
    "seed",
    "client",
    "max_ticks",
    "tick",
    "scene",
];

fn json_number() -> BoxedStrategy<Value> {
    prop_oneof![
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        any::<f64>()
            .prop_filter("JSON has no NaN or infinity", |f| f.is_finite())
            .prop_map(Value::from),
        prop::sample::select(vec![
            0.0, -0.0, 1e308, -1e308, 5e-324, 1e18, 4.5, -1.0, 30.0, 30.000001, 64.0, 1e6
        ])
        .prop_map(Value::from),
    ]
    .boxed()
}

fn json_value() -> BoxedStrategy<Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        json_number(),
        prop::sample::select(KEYS.to_vec()).prop_map(|s| Value::String(s.into())),
        prop::sample::select(vec![
            "roundabout",
            "intersection",
            "merge",
            "road20",
            "..",
            ""
        ])
        .prop_map(|s| Value::String(s.into())),
        ".{0,40}".prop_map(Value::String),
    ];
    leaf.prop_recursive(4, 64, 8, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..12).prop_map(Value::Array),
            prop::collection::btree_map(
                prop_oneof![
                    3 => prop::sample::select(KEYS.to_vec()).prop_map(str::to_owned),
                    1 => "[a-z_]{1,10}",
                ],
                inner,
                0..8
            )
            .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
    .boxed()
}

fn history(n: usize, x0: f64) -> Value {
    Value::Array(
        (0..n)
            .map(|i| json!({"x_m": x0 + i as f64, "y_m": 0.5, "heading_rad": 0.0}))
            .collect(),
    )
}

/// Valid messages of each kind, to be mutated; `ego` is the live scene's ego at step 0 (a
/// tick 1 there is accepted).
fn templates(kind: Target, ego: road_protocol::Pose) -> Vec<Value> {
    match kind {
        Target::Create => vec![
            json!({"map": {"procedural": "roundabout"}, "external": [1], "seed": 3,
                   "client": "ego-1", "max_ticks": 50}),
            json!({"map": {"osm": crate::commands::fuzz::small_osm()},
                   "agents": [
                     {"id": 1, "length_m": 4.5, "width_m": 1.8, "history": history(10, 0.0)},
                     {"id": 2, "length_m": 4.0, "width_m": 1.9, "history": history(12, 20.0)}],
                   "external": [1], "planner": "road20", "checkpoint": "road20",
                   "client": "ego-2"}),
        ],
        Target::Ego => vec![
            json!({"tick": 1, "agents": [{"id": 1, "x_m": ego.x_m, "y_m": ego.y_m,
                   "heading_rad": ego.heading_rad}], "client": "fuzz", "token": FUZZ_TOKEN}),
        ],
        Target::Close => vec![json!({"scene": 1, "client": "fuzz", "token": FUZZ_TOKEN})],
    }
}

/// The fuzz scene's secret.
const FUZZ_TOKEN: &str = "0123456789abcdef0123456789abcdef";

/// Finite numbers no field of the protocol can take: positions far off any map, headings of
/// millions of turns, boxes the size of continents (and not integers, for the id and count
/// fields). What a client that computes garbage sends, and what JSON's own checks let through.
const ABSURD: [f64; 8] = [1e300, -1e300, f64::MAX, -f64::MAX, 1e30, -1e30, 1e9, -1e9];

/// `template` with its `which`-th number (in document order) replaced by `value`.
fn with_absurd_number(template: &Value, which: usize, value: f64) -> Value {
    fn count(v: &Value) -> usize {
        match v {
            Value::Number(_) => 1,
            Value::Object(m) => m.values().map(count).sum(),
            Value::Array(a) => a.iter().map(count).sum(),
            _ => 0,
        }
    }
    let mut v = template.clone();
    let numbers = count(&v);
    if numbers > 0 {
        replace_nth_number(&mut v, which % numbers, &mut 0, value);
    }
    v
}

fn replace_nth_number(v: &mut Value, target: usize, index: &mut usize, value: f64) -> bool {
    match v {
        Value::Number(_) => {
            if *index == target {
                *v = json!(value);
                return true;
            }
            *index += 1;
            false
        }
        Value::Object(m) => m
            .values_mut()
            .any(|c| replace_nth_number(c, target, index, value)),
        Value::Array(a) => a
            .iter_mut()
            .any(|c| replace_nth_number(c, target, index, value)),
        _ => false,
    }
}

/// A two-lanelet Lanelet2 map (the bad-input tests' own).
pub fn small_osm() -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
    for (id, lat, lon) in [
        (1, 0.0, 0.0),
        (2, 0.0, 0.001),
        (3, 0.00004, 0.0),
        (4, 0.00004, 0.001),
    ] {
        s += &format!("  <node id=\"{id}\" lat=\"{lat}\" lon=\"{lon}\"/>\n");
    }
    s += "  <way id=\"10\"><nd ref=\"3\"/><nd ref=\"4\"/></way>\n";
    s += "  <way id=\"11\"><nd ref=\"1\"/><nd ref=\"2\"/></way>\n";
    s += "  <relation id=\"100\"><member type=\"way\" ref=\"10\" role=\"left\"/><member type=\"way\" ref=\"11\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/><tag k=\"subtype\" v=\"road\"/></relation>\n";
    s += "</osm>\n";
    s
}

/// Every path (object keys and array indices) inside `v`.
fn paths(v: &Value, prefix: &mut Vec<PathStep>, out: &mut Vec<Vec<PathStep>>) {
    match v {
        Value::Object(m) => {
            for (k, child) in m {
                prefix.push(PathStep::Key(k.clone()));
                out.push(prefix.clone());
                paths(child, prefix, out);
                prefix.pop();
            }
        }
        Value::Array(a) => {
            for (i, child) in a.iter().enumerate() {
                prefix.push(PathStep::Index(i));
                out.push(prefix.clone());
                paths(child, prefix, out);
                prefix.pop();
            }
        }
        _ => {}
    }
}

#[derive(Debug, Clone)]
enum PathStep {
    Key(String),
    Index(usize),
}

#[derive(Debug, Clone)]
enum Mutation {
    Replace(Value),
    Remove,
    AddKey(String, Value),
    /// The osm string cut or with bytes flipped (the XML parser's input).
    Garble(usize, u8),
}

fn mutate(template: &Value, which: usize, mutation: &Mutation) -> Value {
    let mut v = template.clone();
    let mut all = Vec::new();
    paths(&v, &mut Vec::new(), &mut all);
    if all.is_empty() {
        return v;
    }
    let path = &all[which % all.len()];
    let (last, parent_path) = path.split_last().expect("paths are not empty");
    let mut parent = &mut v;
    for step in parent_path {
        parent = match step {
            PathStep::Key(k) => &mut parent[k.as_str()],
            PathStep::Index(i) => &mut parent[*i],
        };
    }
    match (mutation, last, parent) {
        (Mutation::Replace(new), PathStep::Key(k), Value::Object(m)) => {
            m.insert(k.clone(), new.clone());
        }
        (Mutation::Replace(new), PathStep::Index(i), Value::Array(a)) => a[*i] = new.clone(),
        (Mutation::Remove, PathStep::Key(k), Value::Object(m)) => {
            m.remove(k);
        }
        (Mutation::Remove, PathStep::Index(i), Value::Array(a)) => {
            a.remove(*i);
        }
        (Mutation::AddKey(k, new), _, Value::Object(m)) => {
            m.insert(k.clone(), new.clone());
        }
        (Mutation::Garble(at, byte), PathStep::Key(k), Value::Object(m)) => {
            if let Some(Value::String(s)) = m.get_mut(k) {
                let mut bytes = std::mem::take(s).into_bytes();
                if !bytes.is_empty() {
                    let i = at % bytes.len();
                    if byte % 2 == 0 {
                        bytes.truncate(i);
                    } else {
                        bytes[i] = *byte;
                    }
                }
                *s = String::from_utf8_lossy(&bytes).into_owned();
            }
        }
        _ => {}
    }
    v
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        4 => json_value().prop_map(Mutation::Replace),
        2 => Just(Mutation::Remove),
        1 => ("[a-z_]{1,10}", json_value()).prop_map(|(k, v)| Mutation::AddKey(k, v)),
        2 => (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Mutation::Garble(i, b)),
    ]
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Target {
    Create,
    Ego,
    Close,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Family {
    Bytes,
    Json,
    Mutated,
    /// A valid message with one number replaced by a finite but absurd one ([`ABSURD`]).
    Absurd,
}

/// Counts of one target and family.
#[derive(Debug, Default)]
struct Tally {
    execs: usize,
    accepted: usize,
    refused: BTreeMap<String, usize>,
    panics: usize,
    slowest: Duration,
}

/// What the server runs on one input of `target`; `Ok(())` accepted, `Err` refused.
struct Harness {
    config: ServeConfig,
    checkpoints: Checkpoints,
    planners: BTreeMap<String, road_sched::PlannerSpec>,
    map_files: BTreeMap<String, std::sync::Arc<road_data::LaneletMap>>,
    live: LiveScene,
}

impl Harness {
    fn new() -> Result<Self> {
        let config = ServeConfig::new(find_models_dir(None)?);
        let mut checkpoints = Checkpoints::new(config.models_dir.clone());
        let planners = planners()?;
        let map_files = BTreeMap::new();
        let request: CreateScene = serde_json::from_value(json!({
            "map": {"procedural": "roundabout"}, "external": [1], "client": "fuzz"
        }))?;
        let scene_setup = setup(
            &request,
            &mut SetupContext {
                config: &config,
                checkpoints: &mut checkpoints,
                planners: &planners,
                map_files: &map_files,
            },
        )
        .map_err(|e| anyhow::anyhow!("the fuzz scene: {e}"))?;
        let key = PoolKey {
            checkpoint: scene_setup.checkpoint_name.clone(),
            planner: scene_setup.planner_name.clone(),
        };
        // Leaked: the live scene refers to its pool's slot for the whole run.
        let pool: &'static mut Pool = Box::leak(Box::new(Pool::new(
            scene_setup.model,
            road_serve::pool::PoolEngine::Cpu,
            &scene_setup.planner,
            1,
            config.max_agents,
        )?));
        let live = LiveScene::new(1, scene_setup, key, pool, FUZZ_TOKEN.into(), Instant::now())?;
        Ok(Self {
            config,
            checkpoints,
            planners,
            map_files,
            live,
        })
    }

    fn run(&mut self, target: Target, input: &[u8]) -> Result<(), ErrorReply> {
        match target {
            Target::Create => {
                let request: CreateScene = parse(input)?;
                setup(
                    &request,
                    &mut SetupContext {
                        config: &self.config,
                        checkpoints: &mut self.checkpoints,
                        planners: &self.planners,
                        map_files: &self.map_files,
                    },
                )
                .map(|_| ())
            }
            Target::Ego => {
                let msg: EgoTick = parse(input)?;
                self.live
                    .check_ego(
                        "fuzz",
                        &msg,
                        self.config.max_external_speed_mps,
                        Instant::now(),
                    )
                    .map(|_| ())
            }
            Target::Close => parse::<CloseScene>(input).map(|_| ()),
        }
    }
}

pub fn run(args: &FuzzBenchArgs) -> Result<ExitCode> {
    anyhow::ensure!(args.execs >= 1, "--execs must be at least 1");
    let mut harness = Harness::new()?;
    let mut runner = TestRunner::new_with_rng(
        Config::default(),
        TestRng::from_seed(RngAlgorithm::ChaCha, &seed_bytes(args.seed)),
    );
    let bytes = prop::collection::vec(any::<u8>(), 0..512);
    let documents = json_value();
    let mutations = (any::<usize>(), any::<usize>(), mutation());
    let absurd_picks = (any::<usize>(), any::<usize>(), any::<usize>());
    let mut tallies: BTreeMap<(Target, Family), Tally> = BTreeMap::new();
    let mut findings = Vec::new();
    let started = Instant::now();
    // Panics are counted and their inputs kept; the default hook would print each one.
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    for target in [Target::Create, Target::Ego, Target::Close] {
        let ego = *harness.live.agents[0]
            .history
            .last()
            .context("the fuzz scene's ego has no history")?;
        let templates = templates(target, ego);
        for family in [Family::Bytes, Family::Json, Family::Mutated, Family::Absurd] {
            let tally = tallies.entry((target, family)).or_default();
            for _ in 0..args.execs {
                let input: Vec<u8> = match family {
                    Family::Bytes => current(&bytes, &mut runner)?,
                    Family::Json => serde_json::to_vec(&current(&documents, &mut runner)?)?,
                    Family::Mutated => {
                        let (t, which, m) = current(&mutations, &mut runner)?;
                        serde_json::to_vec(&mutate(&templates[t % templates.len()], which, &m))?
                    }
                    Family::Absurd => {
                        let (t, which, k) = current(&absurd_picks, &mut runner)?;
                        let template = &templates[t % templates.len()];
                        let value = ABSURD[k % ABSURD.len()];
                        serde_json::to_vec(&with_absurd_number(template, which, value))?
                    }
                };
                let t0 = Instant::now();
                let outcome = catch_unwind(AssertUnwindSafe(|| harness.run(target, &input)));
                tally.slowest = tally.slowest.max(t0.elapsed());
                tally.execs += 1;
                match outcome {
                    Ok(Ok(())) => tally.accepted += 1,
                    Ok(Err(e)) => {
                        let code = serde_json::to_value(e.code)?
                            .as_str()
                            .unwrap_or("?")
                            .to_owned();
                        *tally.refused.entry(code).or_default() += 1;
                    }
                    Err(panic) => {
                        tally.panics += 1;
                        let message = panic
                            .downcast_ref::<String>()
                            .cloned()
                            .or_else(|| panic.downcast_ref::<&str>().map(|s| (*s).to_owned()))
                            .unwrap_or_default();
                        findings.push((target, family, input.clone(), message));
                    }
                }
            }
        }
    }
    std::panic::set_hook(hook);
    let secs = started.elapsed().as_secs_f64();
    let total: usize = tallies.values().map(|t| t.execs).sum();
    out!(
        "road bench fuzz: {total} inputs in {secs:.1} s ({:.0}/s), seed {}",
        total as f64 / secs,
        args.seed
    );
    out!(
        "| target | family of inputs | executions | accepted | refused (by code) | panics | slowest ms |"
    );
    out!("|---|---|---:|---:|---|---:|---:|");
    for ((target, family), t) in &tallies {
        let refused: Vec<String> = t.refused.iter().map(|(c, n)| format!("{c} {n}")).collect();
        out!(
            "| {target:?} | {family:?} | {} | {} | {} | {} | {:.2} |",
            t.execs,
            t.accepted,
            refused.join(", "),
            t.panics,
            t.slowest.as_secs_f64() * 1e3
        );
    }
    if findings.is_empty() {
        out!("findings: none");
        return Ok(ExitCode::SUCCESS);
    }
    std::fs::create_dir_all(&args.findings)
        .with_context(|| format!("cannot create {}", args.findings.display()))?;
    for (i, (target, family, input, message)) in findings.iter().enumerate() {
        let path = args
            .findings
            .join(format!("{target:?}-{family:?}-{i}.bin").to_lowercase());
        std::fs::write(&path, input).with_context(|| format!("cannot write {}", path.display()))?;
        out!(
            "finding: {target:?} ({family:?}) panicked: {message}; input in {}",
            path.display()
        );
    }
    Ok(ExitCode::FAILURE)
}

fn current<S: Strategy>(strategy: &S, runner: &mut TestRunner) -> Result<S::Value> {
    Ok(strategy
        .new_tree(runner)
        .map_err(|e| anyhow::anyhow!("generator: {e}"))?
        .current())
}

fn seed_bytes(seed: u64) -> [u8; 32] {
    let mut out = [0u8; 32];
    for (i, chunk) in out.chunks_mut(8).enumerate() {
        chunk.copy_from_slice(&(seed.wrapping_add(i as u64)).to_le_bytes());
    }
    out
}
