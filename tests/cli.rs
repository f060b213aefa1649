//! End-to-end tests of the `road` program on the shared INTERACTION data.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .unwrap()
}

/// The INTERACTION folder: `ROAD_DATA`, else `../shared/data/interaction` beside the clone.
/// Missing data fails the test: these tests must run in CI, not be skipped.
fn data_dir() -> PathBuf {
    let dir = std::env::var_os("ROAD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("../shared/data/interaction"));
    assert!(
        dir.join("maps").is_dir(),
        "INTERACTION data not found at {} (set ROAD_DATA)",
        dir.display()
    );
    dir
}

fn road(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_road"))
        .args(args)
        .current_dir(workspace())
        .env("RUST_LOG", "warn")
        .output()
        .expect("road runs")
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn every_subcommand_explains_itself() {
    let top = road(&["--help"]);
    assert!(top.status.success());
    for cmd in ["data", "sched", "gpu"] {
        assert!(stdout(&top).contains(cmd), "road --help lacks {cmd}");
    }
    for args in [
        &["data", "stats", "--help"][..],
        &["data", "build", "--help"],
        &["data", "export-torch", "--help"],
        &["sched", "plan", "--help"],
        &["sched", "list", "--help"],
        &["gpu", "info", "--help"],
        &["gpu", "selftest", "--help"],
        &["router", "--help"],
        &["ego", "--help"],
        &["bench", "soak", "--help"],
        &["bench", "fuzz", "--help"],
    ] {
        let o = road(args);
        assert!(
            o.status.success() && stdout(&o).contains("Usage"),
            "{args:?}: {}",
            stderr(&o)
        );
    }
}

#[test]
fn the_protocol_fuzzer_runs_every_target_and_finds_nothing() {
    let findings = std::env::temp_dir().join(format!("road-fuzz-{}", std::process::id()));
    let o = road(&[
        "bench",
        "fuzz",
        "--execs",
        "400",
        "--seed",
        "7",
        "--findings",
        findings.to_str().unwrap(),
    ]);
    let out = stdout(&o);
    assert!(o.status.success(), "{out}{}", stderr(&o));
    assert!(out.contains("4800 inputs"), "{out}");
    for row in [
        "| Create | Mutated |",
        "| Ego | Json |",
        "| Close | Bytes |",
    ] {
        assert!(out.contains(row), "{row} missing: {out}");
    }
    // Mutated valid messages are accepted sometimes: the checks are not refusing everything.
    let ego_mutated = out
        .lines()
        .find(|l| l.starts_with("| Ego | Mutated |"))
        .unwrap();
    let accepted: usize = ego_mutated
        .split('|')
        .nth(4)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(accepted > 0, "{ego_mutated}");
    // A finite but absurd number anywhere in a valid creation or tick is refused (issue 41:
    // `1e300` as a position or heading used to poison the scene).
    for row in ["| Create | Absurd |", "| Ego | Absurd |"] {
        let line = out.lines().find(|l| l.starts_with(row)).unwrap();
        let accepted: usize = line.split('|').nth(4).unwrap().trim().parse().unwrap();
        assert_eq!(accepted, 0, "{line}");
    }
    assert!(out.contains("findings: none"), "{out}");
    assert!(!findings.exists());
}

#[test]
fn build_writes_a_cache_that_stats_reads() {
    let data = data_dir();
    let out = std::env::temp_dir().join(format!("road-cli-cache-{}", std::process::id()));
    let data_arg = data.to_str().unwrap();
    let o = road(&[
        "data",
        "build",
        "--data",
        data_arg,
        "--split",
        "validation",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.join("validation.roadds").is_file());
    assert!(
        stdout(&o).contains("validation list names"),
        "missing files are reported: {}",
        stdout(&o)
    );

    let o = road(&[
        "data",
        "stats",
        "--data",
        data_arg,
        "--split",
        "validation",
        "--cache",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    assert_eq!(json["projection_check_passed"], true);
    assert_eq!(json["splits"][0]["files"], 24);

    // The PyTorch export of it, with road20-wide4's fixed validation batches.
    let export = out.join("torch");
    let o = road(&[
        "data",
        "export-torch",
        "--cache",
        out.to_str().unwrap(),
        "--out",
        export.to_str().unwrap(),
        "--split",
        "validation",
        "--config",
        "configs/road20-wide4.toml",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("6162 windows") && stdout(&o).contains("8 batches of 16 scenes"),
        "{}",
        stdout(&o)
    );
    for file in ["validation.safetensors", "validation_batches.safetensors"] {
        let bytes = std::fs::metadata(export.join(file)).unwrap().len();
        assert!(bytes > 100_000, "{file}: {bytes} bytes");
    }
    // Without a train cache the error names the file.
    let o = road(&[
        "data",
        "export-torch",
        "--cache",
        out.to_str().unwrap(),
        "--out",
        export.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("train.roadds"), "{}", stderr(&o));

    // A cache built with other settings is stale, and says so.
    let o = road(&[
        "data",
        "stats",
        "--data",
        data_arg,
        "--split",
        "validation",
        "--cache",
        out.to_str().unwrap(),
        "--set",
        "stride_steps=5",
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("stale dataset cache") && stderr(&o).contains("validation.roadds"),
        "{}",
        stderr(&o)
    );

    // A corrupt one too.
    let path = out.join("validation.roadds");
    let mut bytes = std::fs::read(&path).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(&path, bytes).unwrap();
    let o = road(&[
        "data",
        "stats",
        "--data",
        data_arg,
        "--split",
        "validation",
        "--cache",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("corrupt dataset cache: checksum mismatch"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn bad_inputs_are_named() {
    let o = road(&["data", "stats", "--data", "/nonexistent/interaction"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("/nonexistent/interaction/maps"),
        "{}",
        stderr(&o)
    );

    let o = road(&["data", "stats", "--set", "max_agents=0"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("min_agents"), "{}", stderr(&o));

    let o = road(&["sched", "plan", "nonesuch"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("no planner `nonesuch`") && stderr(&o).contains("planners.toml"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn shipped_configs_match_the_defaults_and_validate() {
    let text = std::fs::read_to_string(workspace().join("configs/data.toml")).unwrap();
    let shipped: road_data::WindowConfig = toml::from_str(&text).unwrap();
    assert_eq!(shipped, road_data::WindowConfig::default());

    let o = road(&["sched", "list"]);
    assert!(o.status.success(), "{}", stderr(&o));
    for name in ["road20", "road15", "ar", "djinn10-mpc1", "djinn30"] {
        assert!(
            stdout(&o).contains(&format!("| {name} |")),
            "{name} missing: {}",
            stdout(&o)
        );
    }
    // road20: 2K/F NFE per simulated step in the long run; 40 steps include the warm-up.
    let o = road(&["sched", "plan", "road20", "--ticks", "40"]);
    assert!(
        stdout(&o).contains("Rolling stage: 4 steps, 8 NFE (Heun)"),
        "{}",
        stdout(&o)
    );
    // The multistep sampler: one evaluation per step.
    let o = road(&["sched", "plan", "road20-nearfit-lanes-guarded-k20-2m"]);
    assert!(
        stdout(&o).contains("Rolling stage: 2 steps, 2 NFE (Multistep)"),
        "{}",
        stdout(&o)
    );
}

#[test]
fn gpu_selftest_passes_on_the_adapter_present() {
    let o = road(&["gpu", "selftest"]);
    assert!(o.status.success(), "{}\n{}", stdout(&o), stderr(&o));
    let text = stdout(&o);
    for kernel in [
        "linear",
        "linear_tiled",
        "linear (norm, residual)",
        "linear_tiled (norm, residual)",
        "encode_polylines",
        "attention",
        "pair_attention",
        "pick_agent_maps",
        "edm.precondition",
    ] {
        assert!(text.contains(&format!("{kernel}: ok")), "{kernel}: {text}");
    }
    for checkpoint in ["models/road20-wide4", "models/road20"] {
        assert!(
            text.contains(&format!("denoiser {checkpoint}: ok")),
            "{checkpoint}: {text}"
        );
    }
}

/// The shipped road20 checkpoint through `road sample` (both engines) and `road eval` on one
/// validation scene.
#[test]
fn sample_and_eval_run_with_the_shipped_checkpoint() {
    let data = data_dir();
    let dir = std::env::temp_dir().join(format!("road-cli-eval-{}", std::process::id()));
    let (data_arg, dir_arg) = (data.to_str().unwrap(), dir.to_str().unwrap());
    let o = road(&[
        "data",
        "build",
        "--data",
        data_arg,
        "--split",
        "validation",
        "--out",
        dir_arg,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut pngs = Vec::new();
    for engine in ["cpu", "gpu"] {
        let png = dir.join(format!("sample-{engine}.png"));
        let o = road(&[
            "sample",
            "--checkpoint",
            "models/road20",
            "--scene",
            "val:5",
            "--samples",
            "2",
            "--steps",
            "3",
            "--engine",
            engine,
            "--cache",
            dir_arg,
            "--out",
            png.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{engine}: {}", stderr(&o));
        assert!(stdout(&o).contains("NFE per sample"), "{}", stdout(&o));
        pngs.push(std::fs::read(&png).unwrap());
    }
    assert!(pngs[0].starts_with(b"\x89PNG"));
    assert_eq!(
        pngs[0], pngs[1],
        "both engines draw the same samples for a seed"
    );

    let json = dir.join("eval.json");
    let o = road(&[
        "eval",
        "--checkpoints",
        "models/road20",
        "--limit",
        "1",
        "--samples",
        "2",
        "--cache",
        dir_arg,
        "--json",
        json.to_str().unwrap(),
        "--figure-scenes",
        "1",
        "--figures",
        dir_arg,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        std::fs::read(dir.join("forecasting-road20-00.png"))
            .unwrap()
            .starts_with(b"\x89PNG")
    );
    assert!(
        stdout(&o).contains("| constant velocity |") && stdout(&o).contains("| road20 |"),
        "{}",
        stdout(&o)
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let road20 = &v["results"][1];
    assert_eq!(road20["model"], "road20");
    assert!(
        road20["ade_sum"].as_f64().unwrap().is_finite() && road20["agents"].as_u64().unwrap() >= 4
    );
    // RoAD-20 over 30 steps: 80 warm-up NFE + 29 rolling stages of 8.
    assert!((road20["nfe_per_step"].as_f64().unwrap() - 312.0 / 30.0).abs() < 1e-9);

    // Serving through the scheduler on every engine (candle, fast CPU, WGSL), lockstep and
    // with a scene joining.
    // `road bench serve` of 2 scenes for 2 ticks with `extra` flags, its JSON report.
    let bench_serve = |extra: &[&str]| {
        let mut args = vec![
            "bench",
            "serve",
            "--checkpoint",
            "models/road20",
            "--scenes",
            "2",
            "--ticks",
            "2",
        ];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--cache", dir_arg, "--json"]);
        let o = road(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_str::<serde_json::Value>(&stdout(&o)).unwrap()
    };
    let v = bench_serve(&["--join-every", "2"]);
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 6, "{v}");
    let engines: Vec<&str> = rows.iter().map(|r| r["engine"].as_str().unwrap()).collect();
    assert!(
        engines[0].contains("candle") && engines[2].contains("fast") && engines[4].contains("WGSL"),
        "{engines:?}"
    );
    // Lockstep RoAD-20 rolling ticks: K/F = 4 steps, 8 NFE; a joining scene adds its warm-up;
    // every engine runs the same schedule.
    assert_eq!(rows[0]["nfe_per_scene_tick"], 8.0);
    assert!(rows[1]["nfe_per_scene_tick"].as_f64().unwrap() > 8.0);
    for pair in rows.chunks(2).skip(1) {
        assert_eq!(rows[0]["nfe_per_scene_tick"], pair[0]["nfe_per_scene_tick"]);
        assert_eq!(rows[1]["nfe_per_scene_tick"], pair[1]["nfe_per_scene_tick"]);
    }

    // Another planner on the same checkpoint: K = 10 sampler steps make a rolling stage one Heun
    // step (2 NFE); a planner that does not exist is refused by name.
    let v = bench_serve(&[
        "--engines",
        "cpu",
        "--planner",
        "road20-nearfit-lanes-guarded-k10",
    ]);
    assert_eq!(v["planner"], "road20-nearfit-lanes-guarded-k10");
    assert_eq!(v["rows"][0]["nfe_per_scene_tick"], 2.0, "{v}");
    let gflop_per_sec = v["rows"][0]["gflop_per_sec"].as_f64().unwrap();
    assert!(gflop_per_sec.is_finite() && gflop_per_sec > 0.0, "{v}");
    // The multistep sampler: one evaluation per step, so K = 20 costs 2 NFE per tick.
    let v = bench_serve(&[
        "--engines",
        "cpu",
        "--planner",
        "road20-nearfit-lanes-guarded-k20-2m",
    ]);
    assert_eq!(v["rows"][0]["nfe_per_scene_tick"], 2.0, "{v}");
    let o = road(&[
        "bench",
        "serve",
        "--engines",
        "cpu",
        "--planner",
        "no-such",
        "--cache",
        dir_arg,
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("unknown planner `no-such`"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Issues 39 and 41: around an ego that stops where its history ends, the default's vehicles
/// stay on the roundabout. On seed 2 one used to creep off its lane onto the median, a few
/// centimetres a tick, which the lane guard left alone as a standing vehicle's jitter.
#[test]
fn vehicles_held_up_by_a_stopped_ego_stay_on_the_road() {
    let dir = std::env::temp_dir().join(format!("road-cli-held-up-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("held-up.json");
    let o = road(&[
        "demo",
        "--in-process",
        "--seed",
        "2",
        "--steps",
        "60",
        "--ego-speed-scale",
        "0",
        "--engine",
        "cpu",
        "--json",
        json.to_str().unwrap(),
        "--out",
        dir.join("held-up.png").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let ticks = run["ticks"].as_array().unwrap();
    assert_eq!(ticks.len(), 60);
    for (t, tick) in ticks.iter().enumerate() {
        assert_eq!(tick["off_road"], serde_json::json!([]), "tick {}", t + 1);
        assert_eq!(tick["collisions"], serde_json::json!([]), "tick {}", t + 1);
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `road demo --in-process --map`: the intersection and the merge run too; an unknown map is
/// refused with the known ones named; the in-process flags are refused without `--in-process`.
#[test]
fn demo_runs_every_procedural_map() {
    let dir = std::env::temp_dir().join(format!("road-cli-demo-maps-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for map in ["intersection", "merge"] {
        let png = dir.join(format!("demo-{map}.png"));
        let o = road(&[
            "demo",
            "--in-process",
            "--map",
            map,
            "--steps",
            "2",
            "--engine",
            "cpu",
            "--out",
            png.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{map}: {}", stderr(&o));
        assert!(
            stdout(&o).contains(&format!("procedural {map}, 6 vehicles")),
            "{}",
            stdout(&o)
        );
        assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    }
    // Another planner of configs/planners.toml on the same checkpoint, by name.
    let png = dir.join("demo-paper.png");
    let o = road(&[
        "demo",
        "--in-process",
        "--steps",
        "2",
        "--engine",
        "cpu",
        "--planner",
        "road20",
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("road20-wide4 [road20]"),
        "{}",
        stdout(&o)
    );
    let o = road(&["demo", "--in-process", "--steps", "1", "--planner", "nope"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("unknown planner `nope`")
            && stderr(&o).contains("road20-fitted-guarded"),
        "{}",
        stderr(&o)
    );
    let o = road(&[
        "demo",
        "--in-process",
        "--steps",
        "1",
        "--planner",
        "djinn30",
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("planner `djinn30` does not fit checkpoint road20-wide4"),
        "{}",
        stderr(&o)
    );
    let o = road(&["demo", "--map", "atlantis", "--steps", "1"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("roundabout, intersection, merge"),
        "{}",
        stderr(&o)
    );
    let o = road(&["demo", "--out", "x.png"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--in-process"), "{}", stderr(&o));
    // `--scripted` is the served demo's: the in-process one runs the script by default, and a
    // scripted scene places no vehicles.
    for args in [
        &["demo", "--scripted", "--in-process", "--steps", "1"][..],
        &["demo", "--scripted", "--populate", "3", "--steps", "1"][..],
    ] {
        let o = road(args);
        assert!(!o.status.success(), "{args:?}");
        assert!(stderr(&o).contains("--scripted"), "{}", stderr(&o));
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 39: `road demo --in-process --populate` redraws the placed vehicles with the
/// initialiser as a served scene does (road20-init, embedded, unless `--initialiser` names
/// another or `none`); bad initialisers are refused by name.
#[test]
fn the_in_process_demo_redraws_populated_vehicles_with_the_initialiser() {
    let dir = temp_dir("demo-initialiser");
    let first_tick = |extra: &[&str], name: &str| {
        let json = dir.join(format!("{name}.json"));
        let mut args = vec![
            "demo",
            "--in-process",
            "--populate",
            "4",
            "--steps",
            "2",
            "--engine",
            "cpu",
            "--json",
            json.to_str().unwrap(),
        ];
        let png = dir.join(format!("{name}.png"));
        args.extend(["--out", png.to_str().unwrap()]);
        args.extend(extra);
        let o = road(&args);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let run: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        run["ticks"][0]["poses"].clone()
    };
    let redrawn = first_tick(&[], "default");
    let named = first_tick(&["--initialiser", "road20-init"], "named");
    let refined = first_tick(&["--initialiser", "none"], "none");
    assert_eq!(redrawn, named, "the default is road20-init");
    assert_ne!(redrawn, refined, "at least one vehicle redrawn");
    let populated = |initialiser: &'static str| {
        vec![
            "demo",
            "--in-process",
            "--populate",
            "2",
            "--steps",
            "1",
            "--initialiser",
            initialiser,
        ]
    };
    for (args, says) in [
        (
            vec![
                "demo",
                "--in-process",
                "--steps",
                "1",
                "--initialiser",
                "none",
            ],
            "needs --populate",
        ),
        (
            populated("atlantis"),
            "--initialiser \"atlantis\": no checkpoint folder",
        ),
        (
            populated("models/road20-wide4"),
            "not trained to draw whole vehicles",
        ),
    ] {
        let o = road(&args);
        assert!(!o.status.success(), "{args:?}");
        assert!(stderr(&o).contains(says), "{args:?}: {}", stderr(&o));
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 39: `road demo` populates the roundabout by the model around the ego and keeps
/// vehicles entering; `--scripted` runs the map's seven scripted vehicles as before.
#[test]
fn the_served_demo_is_populated_by_default_and_scripted_on_request() {
    let dir = temp_dir("demo-populated");
    let checkpoint = workspace().join("models/road20-wide4");
    let header = |extra: &[&str]| {
        let o = Command::new(env!("CARGO_BIN_EXE_road"))
            .args(["demo", "--steps", "3", "--checkpoint"])
            .arg(&checkpoint)
            .args(extra)
            .current_dir(&dir)
            .env("RUST_LOG", "warn")
            .output()
            .expect("road runs");
        assert!(o.status.success(), "{}", stderr(&o));
        stdout(&o).lines().next().unwrap_or_default().to_owned()
    };
    let populated = header(&[]);
    assert!(
        populated.contains("8 vehicles") && populated.contains("7 by road20-wide4"),
        "{populated}"
    );
    let scripted = header(&["--scripted"]);
    assert!(
        scripted.contains("7 vehicles") && scripted.contains("6 by road20-wide4"),
        "{scripted}"
    );
    let drawn = header(&["--initialiser", "road20-init"]);
    assert!(
        drawn.contains("8 vehicles") && drawn.contains("7 by road20-wide4, drawn by road20-init"),
        "{drawn}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `road eval --suite procedural`: the demo's closed loop over maps, seeds and rotations, one
/// row per map with every run counted (the JSON holds every run); bad angles and maps are
/// refused by name. `road demo --rotate-deg` turns the scene.
#[test]
fn procedural_suite_counts_every_run() {
    let dir = std::env::temp_dir().join(format!("road-cli-procedural-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("procedural.json");
    let o = road(&[
        "eval",
        "--suite",
        "procedural",
        "--checkpoints",
        "models/road20-wide4",
        "--maps",
        "merge",
        "roundabout",
        "--seeds",
        "2",
        "--rotations-deg",
        "0",
        "-90",
        "--procedural-steps",
        "2",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("| road20-wide4 | merge | 4 |"), "{out}");
    assert!(out.contains("| road20-wide4 | roundabout | 4 |"), "{out}");
    assert!(out.contains("0°: ") && out.contains("-90°: "), "{out}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(report["suite"], "procedural");
    assert_eq!(report["runs"].as_array().unwrap().len(), 8);
    assert_eq!(report["results"][1]["model_vehicles"], 4 * 6);
    // Two ticks: one step per vehicle between them, each checked for reversing.
    assert_eq!(report["results"][1]["model_vehicle_steps"], 4 * 6);
    assert!(report["results"][1]["reversing_steps"].as_u64().unwrap() <= 4 * 6);
    let moving = report["results"][1]["moving_steps"].as_u64().unwrap();
    assert!(moving <= 4 * 6 && report["results"][1]["sliding_steps"].as_u64().unwrap() <= moving);
    let o = road(&["eval", "--suite", "procedural", "--maps", "atlantis"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("unknown procedural map \"atlantis\""),
        "{}",
        stderr(&o)
    );
    let o = road(&["eval", "--suite", "procedural", "--seeds", "0"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--seeds"), "{}", stderr(&o));

    let png = dir.join("turned.png");
    let o = road(&[
        "demo",
        "--in-process",
        "--engine",
        "cpu",
        "--steps",
        "2",
        "--rotate-deg",
        "-135",
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    let o = road(&[
        "demo",
        "--in-process",
        "--steps",
        "1",
        "--rotate-deg",
        "NaN",
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--rotate-deg"), "{}", stderr(&o));
    std::fs::remove_dir_all(&dir).ok();
}

/// `road demo --in-process`: the procedural scene closed loop on both engines.
#[test]
fn demo_runs_closed_loop_on_both_engines() {
    let dir = std::env::temp_dir().join(format!("road-cli-demo-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut runs = Vec::new();
    for engine in ["cpu", "gpu"] {
        let (png, json) = (
            dir.join(format!("demo-{engine}.png")),
            dir.join(format!("demo-{engine}.json")),
        );
        let o = road(&[
            "demo",
            "--in-process",
            "--steps",
            "4",
            "--engine",
            engine,
            "--out",
            png.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{engine}: {}", stderr(&o));
        let text = stdout(&o);
        assert!(
            text.contains("time per tick") && text.contains("infractions"),
            "{text}"
        );
        assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        assert_eq!(v["ticks"].as_array().unwrap().len(), 4);
        // The default's RoAD-20 at K = 20 under the multistep sampler (one evaluation per
        // step): the warm-up (20 NFE) then rolling stages of K/F = 2 steps (2 NFE).
        assert_eq!(v["nfe"], 20 + 3 * 2);
        runs.push(v);
    }
    // The same seed: the same closed loop on both engines, to the rollout tolerance.
    for (t, (a, b)) in runs[0]["ticks"]
        .as_array()
        .unwrap()
        .iter()
        .zip(runs[1]["ticks"].as_array().unwrap())
        .enumerate()
    {
        for (p, q) in a["poses"]
            .as_array()
            .unwrap()
            .iter()
            .zip(b["poses"].as_array().unwrap())
        {
            for key in ["x_m", "y_m"] {
                let (x, y) = (p[key].as_f64().unwrap(), q[key].as_f64().unwrap());
                assert!((x - y).abs() < 0.02, "tick {t} {key}: cpu {x} vs gpu {y}");
            }
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The reactivity suite end to end on one validation scene, with figures and JSON.
#[test]
fn reactivity_suite_runs_with_the_shipped_checkpoint() {
    let data = data_dir();
    let dir = std::env::temp_dir().join(format!("road-cli-react-{}", std::process::id()));
    let json = dir.join("reactivity.json");
    let o = road(&[
        "eval",
        "--suite",
        "reactivity",
        "--data",
        data.to_str().unwrap(),
        "--checkpoints",
        "models/road20",
        "--limit",
        "1",
        "--samples",
        "2",
        "--sim-steps",
        "6",
        "--figure-scenes",
        "1",
        "--figures",
        dir.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = stdout(&o);
    for row in ["| log replay |", "| constant velocity |", "| road20 |"] {
        assert!(text.contains(row), "{text}");
    }
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let road20 = &v["results"][2];
    assert_eq!(road20["model"], "road20");
    assert_eq!(road20["simulations"], 2);
    // NFE per simulated step as the math doc predicts: (80 + 5 · 8) / 6.
    let nfe = road20["nfe_per_step"].as_f64().unwrap();
    assert!((nfe - 120.0 / 6.0).abs() < 1e-9, "{nfe}");
    assert!((road20["expected_nfe_per_step"].as_f64().unwrap() - nfe).abs() < 1e-9);
    // Reversing is counted over the driven agents' steps between the 6 simulated ticks.
    let scene = &road20["per_scene"][0];
    let driven = scene["driven_agents"].as_u64().unwrap();
    assert_eq!(scene["driven_steps"].as_u64().unwrap(), driven * 5);
    let reversing = road20["reversing_rate"]["value"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&reversing), "{reversing}");
    // Sliding is counted over the steps at 2 m/s or more.
    let moving = scene["moving_steps"].as_u64().unwrap();
    assert!(moving <= driven * 5 && scene["sliding_steps"].as_u64().unwrap() <= moving);
    for name in ["log-replay", "constant-velocity", "road20"] {
        let png = dir.join(format!("reactivity-{name}-00.png"));
        assert!(
            std::fs::read(&png).unwrap().starts_with(b"\x89PNG"),
            "{name}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Writes a `road eval --json` file of one suite with one model's per-scene figures; returns
/// its path.
fn eval_json(path: &Path, suite: &str, model: &str, per_scene: Vec<serde_json::Value>) -> String {
    let json = serde_json::json!({ "suite": suite, "results": [
        { "model": model, "per_scene": per_scene } ] });
    std::fs::write(path, json.to_string()).unwrap();
    path.to_str().unwrap().to_owned()
}

/// `road compare` pairs scenes by validation window across files: a model 0.5 m worse on every
/// shared scene shows +0.5 with a zero-width interval, whatever the order of the scenes; mixed
/// suites and files without per-scene figures are refused, naming the file.
#[test]
fn compare_pairs_scenes_across_eval_files() {
    let dir = std::env::temp_dir().join(format!("road-compare-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = |window: usize, ade: f64, missed: usize| {
        serde_json::json!({ "window": window, "agents": 4, "min_scene_ade_m": ade,
            "min_scene_fde_m": 2.0 * ade, "missed_agents": missed })
    };
    let file = |name: &str, model: &str, per_scene| {
        eval_json(&dir.join(name), "forecasting", model, per_scene)
    };
    let base = file(
        "base.json",
        "cv",
        vec![scene(3, 1.0, 1), scene(7, 2.0, 2), scene(9, 1.5, 0)],
    );
    // Scene 9 missing, the other two in another order: two pairs.
    let worse = file(
        "worse.json",
        "lever",
        vec![scene(7, 2.5, 2), scene(3, 1.5, 3)],
    );
    let o = road(&["compare", &base, &worse]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(
        out.contains("| lever | 2 | +0.500 [+0.500, +0.500] | +1.000 [+1.000, +1.000] | +0.250"),
        "{out}"
    );

    let reactivity = dir.join("reactivity.json");
    std::fs::write(&reactivity, r#"{"suite": "reactivity", "results": []}"#).unwrap();
    let o = road(&["compare", &base, reactivity.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("reactivity.json"), "{}", stderr(&o));

    let old = dir.join("old.json");
    std::fs::write(
        &old,
        r#"{"suite": "forecasting", "results": [{"model": "x"}]}"#,
    )
    .unwrap();
    let o = road(&["compare", &base, old.to_str().unwrap()]);
    assert!(
        stderr(&o).contains("old.json") && stderr(&o).contains("per_scene"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `road compare` on the reactivity suite pairs the reversing and sliding shares (per driven
/// and per moving step) where both files count them, and says so where one file does not.
#[test]
fn compare_pairs_sliding_steps_where_both_files_count_them() {
    let dir = temp_dir("compare-sliding");
    let scene = |window: usize, sliding: Option<u64>| {
        let mut s = serde_json::json!({ "window": window, "simulations": 3,
            "adversary_collisions": 0, "any_collisions": 1, "driven_agents": 30,
            "off_road_agents": 3 });
        if let Some(sliding) = sliding {
            s["driven_steps"] = 1170.into();
            s["reversing_steps"] = 0.into();
            s["moving_steps"] = 600.into();
            s["sliding_steps"] = sliding.into();
        }
        s
    };
    let file = |name: &str, model: &str, per_scene| {
        eval_json(&dir.join(name), "reactivity", model, per_scene)
    };
    // 60 of 600 moving steps slide in the baseline, 30 under the lever: −0.05 on each scene.
    let base = file(
        "base.json",
        "default",
        vec![scene(3, Some(60)), scene(7, Some(60))],
    );
    let lever = file(
        "lever.json",
        "lever",
        vec![scene(7, Some(30)), scene(3, Some(30))],
    );
    let old = file("old.json", "old", vec![scene(3, None), scene(7, None)]);
    let o = road(&["compare", &base, &lever, &old]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("Δsliding steps"), "{out}");
    assert!(
        out.contains("| +0.000 [+0.000, +0.000] | -0.050 [-0.050, -0.050] |"),
        "{out}"
    );
    assert!(
        out.lines()
            .any(|l| l.starts_with("| old |") && l.contains("(not in every file)")),
        "{out}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A fresh folder under the system's temporary one.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("road-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A decoded GIF: its size and each frame's delay (hundredths of a second) and RGBA pixels.
struct Gif {
    width: u16,
    height: u16,
    frames: Vec<(u16, Vec<u8>)>,
}

fn read_gif(path: &Path) -> Gif {
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut decoder = options.read_info(file).unwrap();
    let (width, height) = (decoder.width(), decoder.height());
    let mut frames = Vec::new();
    while let Some(frame) = decoder.read_next_frame().unwrap() {
        assert_eq!((frame.width, frame.height), (width, height), "full frames");
        frames.push((frame.delay, frame.buffer.to_vec()));
    }
    Gif {
        width,
        height,
        frames,
    }
}

/// Pixels of exactly this colour in an RGBA frame.
fn pixels_of(rgba: &[u8], rgb: [u8; 3]) -> usize {
    rgba.chunks_exact(4).filter(|p| p[..3] == rgb).count()
}

/// `road demo` with no flags is the product: `road serve` in the process, the scripted ego a
/// zenoh client, a line per tick, the recording `demo.mcap` and its animation `demo.gif` (the
/// scene at creation and every tick); `road render` redraws the recording at another size
/// and pace.
/// The README's main command works from anywhere: a copy of the binary in a folder with no
/// `models/` (nor any above it) runs the demo on the embedded default checkpoint.
#[test]
fn demo_runs_outside_the_repository_on_the_embedded_checkpoint() {
    let dir = temp_dir("demo-embedded");
    let bin = dir.join("road");
    // A hard link where the file system allows it (the debug binary is large), else a copy.
    std::fs::hard_link(env!("CARGO_BIN_EXE_road"), &bin)
        .or_else(|_| std::fs::copy(env!("CARGO_BIN_EXE_road"), &bin).map(|_| ()))
        .unwrap();
    // Served, then the in-process closed loop (its engines load the embedded bytes too).
    let runs: [&[&str]; 2] = [
        &["demo", "--steps", "3"],
        &["demo", "--in-process", "--engine", "cpu", "--steps", "3"],
    ];
    for args in runs {
        let o = Command::new(&bin)
            .args(args)
            .current_dir(&dir)
            .env("RUST_LOG", "info")
            .env_remove("ROAD_MODELS")
            .output()
            .expect("road runs");
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(stderr(&o).contains("embedded"), "{}", stderr(&o));
    }
    assert!(dir.join("demo.mcap").is_file() && dir.join("demo.gif").is_file());
    assert!(dir.join("demo.png").is_file());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn demo_serves_the_scene_and_writes_its_recording_and_animation() {
    let dir = temp_dir("demo-served");
    // The checkpoint by absolute path: the files land in `dir`, the models are here.
    let checkpoint = workspace().join("models/road20-wide4");
    let steps = 20;
    let o = Command::new(env!("CARGO_BIN_EXE_road"))
        .args(["demo", "--steps", &steps.to_string(), "--checkpoint"])
        .arg(&checkpoint)
        .current_dir(&dir)
        .env("RUST_LOG", "warn")
        .output()
        .expect("road runs");
    assert!(o.status.success(), "{}", stderr(&o));
    let text = stdout(&o);
    let tick_lines: Vec<&str> = text.lines().filter(|l| l.starts_with("tick ")).collect();
    assert_eq!(tick_lines.len(), steps, "{text}");
    assert!(
        tick_lines
            .iter()
            .all(|l| l.contains("round trip") && l.contains("engine")),
        "{text}"
    );
    assert!(
        text.contains("round trip p50") && text.contains("infractions:"),
        "{text}"
    );
    let mcap = dir.join("demo.mcap");
    assert!(std::fs::read(&mcap).unwrap().starts_with(mcap::MAGIC));
    let gif = read_gif(&dir.join("demo.gif"));
    assert_eq!(gif.frames.len(), steps + 1);
    assert_eq!((gif.width, gif.height), (800, 800));
    assert!(gif.frames.iter().all(|f| f.0 == 10), "10 frames a second");
    // The model's vehicles orange, the ego green.
    let first = &gif.frames[0].1;
    assert!(pixels_of(first, [240, 140, 20]) > 0 && pixels_of(first, [30, 150, 70]) > 0);

    let small = dir.join("small.gif");
    let o = road(&[
        "render",
        mcap.to_str().unwrap(),
        "--out",
        small.to_str().unwrap(),
        "--size",
        "200",
        "--fps",
        "5",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains(&format!("{} frames", steps + 1)),
        "{}",
        stdout(&o)
    );
    let gif = read_gif(&small);
    assert_eq!(gif.frames.len(), steps + 1);
    assert_eq!((gif.width, gif.height), (200, 200));
    assert!(gif.frames.iter().all(|f| f.0 == 20));
    std::fs::remove_dir_all(&dir).ok();
}

/// The recorder of `road serve` writing a scene in `dir`: the roundabout's lanes, agent 1
/// external and 2, 3 the model's, `ticks` ticks 100 ms apart (with 2 and 3 colliding at tick
/// 3 and 3 off road at tick 4), a chunk written out after every tick. Returns the finished
/// file and its length when tick `flushed` had been written out.
fn record_scene(dir: &Path, ticks: u64, flushed: u64) -> (PathBuf, u64) {
    record_scene_with(dir, ticks, flushed, false)
}

/// As [`record_scene`]; `with_plans`: agent 2 reports a 30 m plan every tick.
fn record_scene_with(dir: &Path, ticks: u64, flushed: u64, with_plans: bool) -> (PathBuf, u64) {
    use road_serve::record::{Recorder, topics};
    use std::time::{Duration, SystemTime};
    let map = road_sim::procedural::procedural(
        road_sim::procedural::ProceduralMap::Roundabout,
        &road_data::WindowConfig::default(),
        2,
    )
    .unwrap()
    .map;
    let agents: Vec<road_protocol::AgentInfo> = [(1, true), (2, false), (3, false)]
        .into_iter()
        .map(|(id, external)| road_protocol::AgentInfo {
            id,
            length_m: 4.5,
            width_m: 1.8,
            external,
            history: vec![],
        })
        .collect();
    let created = serde_json::json!({ "scene": 7, "agents": agents });
    let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
    let mut rec = Recorder::start(
        dir,
        7,
        br#"{"client":"ego-7"}"#,
        created.to_string().as_bytes(),
        Some(&map),
        t0,
    )
    .unwrap();
    let poses = |t: u64| -> Vec<road_sim::Pose> {
        let x = t as f64;
        [(-20.0 + x, -3.0), (5.0, 10.0 - x), (5.0 + 0.5 * x, 10.0)]
            .into_iter()
            .map(|(x_m, y_m)| road_sim::Pose {
                x_m,
                y_m,
                heading_rad: 0.0,
            })
            .collect()
    };
    rec.agents(&agents, &poses(0), &[], false, t0).unwrap();
    let mut flushed_len = 0;
    for t in 1..=ticks {
        let at = t0 + Duration::from_millis(100 * t);
        let ego = serde_json::json!({ "tick": t, "agents": [
            { "id": 1, "x_m": -20.0 + t as f64, "y_m": -3.0, "heading_rad": 0.0 } ] });
        rec.write(topics::EGO, ego.to_string().as_bytes(), at)
            .unwrap();
        let npc = serde_json::json!({
            "scene": 7, "tick": t, "time_s": 0.1 * t as f64, "npcs": [],
            "collisions": if t == 3 { vec![[2, 3]] } else { vec![] },
            "off_road": if t == 4 { vec![3] } else { vec![] },
            "latency_ms": 1.0, "compute_ms": 0.5,
        });
        rec.write(topics::NPC, npc.to_string().as_bytes(), at)
            .unwrap();
        let plans: Vec<road_protocol::AgentPlan> = if with_plans {
            let from = poses(t)[1];
            vec![road_protocol::AgentPlan {
                id: 2,
                poses: (1..=10)
                    .map(|k| road_protocol::Pose {
                        x_m: from.x_m - 3.0 * k as f64,
                        y_m: from.y_m,
                        heading_rad: std::f64::consts::PI,
                    })
                    .collect(),
            }]
        } else {
            Vec::new()
        };
        rec.agents(&agents, &poses(t), &plans, false, at).unwrap();
        rec.flush().unwrap();
        if t == flushed {
            flushed_len = std::fs::metadata(rec.path()).unwrap().len();
        }
    }
    (rec.finish().unwrap(), flushed_len)
}

/// `road render` on a recording: a frame per tick with the tick's collision and off-road
/// agent outlined red; a recording cut off mid-chunk (a killed server) renders up to its last
/// complete chunk; a missing file, a file that is not MCAP and an MCAP file without a scene
/// are refused, naming the file.
#[test]
fn render_draws_a_frame_per_tick_and_names_bad_files() {
    let dir = temp_dir("render");
    let (mcap, flushed_len) = record_scene(&dir, 6, 3);
    let gif_path = dir.join("scene.gif");
    let o = road(&["render", mcap.to_str().unwrap(), "--size", "300"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("1 collision pair(s) and 1 off-road agent(s)"),
        "{}",
        stdout(&o)
    );
    let gif = read_gif(&mcap.with_extension("gif"));
    assert_eq!(gif.frames.len(), 7, "the scene at creation and 6 ticks");
    assert_eq!((gif.width, gif.height), (300, 300));
    let red = |k: usize| pixels_of(&gif.frames[k].1, [210, 30, 30]);
    assert_eq!((red(0), red(2)), (0, 0), "no infraction, nothing red");
    // The same scene with a planned path: more of the model's orange in every tick's frame.
    let planned_dir = temp_dir("render-plans");
    let (planned, _) = record_scene_with(&planned_dir, 6, 3, true);
    let o = road(&["render", planned.to_str().unwrap(), "--size", "300"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let with_plans = read_gif(&planned.with_extension("gif"));
    let orange = |frames: &[(u16, Vec<u8>)], k: usize| pixels_of(&frames[k].1, [240, 140, 20]);
    assert!(
        orange(&with_plans.frames, 5) > orange(&gif.frames, 5) + 20,
        "the plan is drawn: {} against {} orange pixels",
        orange(&with_plans.frames, 5),
        orange(&gif.frames, 5)
    );
    assert!(red(3) > 0, "the collision at tick 3 is highlighted");
    assert!(red(4) > 0, "the off-road agent at tick 4 is highlighted");

    // SIGKILL mid-write: the file ends a few bytes into tick 4's chunk.
    let cut = dir.join("cut.mcap");
    let bytes = std::fs::read(&mcap).unwrap();
    std::fs::write(&cut, &bytes[..flushed_len as usize + 20]).unwrap();
    let o = road(&[
        "render",
        cut.to_str().unwrap(),
        "--out",
        gif_path.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("cut off"), "{}", stdout(&o));
    assert_eq!(read_gif(&gif_path).frames.len(), 4);

    let o = road(&["render", "/nonexistent/scene.mcap"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("/nonexistent/scene.mcap") && stderr(&o).contains("cannot read"),
        "{}",
        stderr(&o)
    );
    let garbage = dir.join("garbage.mcap");
    std::fs::write(&garbage, b"these bytes are not a recording").unwrap();
    let o = road(&["render", garbage.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("not an MCAP file") && stderr(&o).contains("garbage.mcap"),
        "{}",
        stderr(&o)
    );
    // MCAP, but no scene in it: the creation messages only.
    let empty_dir = dir.join("empty");
    let rec = road_serve::record::Recorder::start(
        &empty_dir,
        1,
        b"{}",
        b"{}",
        None,
        std::time::SystemTime::now(),
    )
    .unwrap();
    let empty = rec.finish().unwrap();
    let o = road(&["render", empty.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("no /map messages") && stderr(&o).contains("scene-1.mcap"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&planned_dir).ok();
}

/// `road replay` publishes a recording's NPC ticks again on the live keys under `--prefix`,
/// in order, to a subscriber on loopback (scouting off).
#[test]
fn replay_republishes_the_npc_ticks_over_zenoh() {
    use std::time::{Duration, Instant};
    use zenoh::Wait;
    let dir = temp_dir("replay");
    let (mcap, _) = record_scene(&dir, 5, 0);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let config = road_client::ZenohArgs::loopback(Some(&endpoint), None)
        .to_config()
        .unwrap();
    let session = zenoh::open(config).wait().unwrap();
    let npc = session
        .declare_subscriber("replay-test/client/ego-7/scene/*/npc")
        .wait()
        .unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_road"))
        .args(["replay", mcap.to_str().unwrap(), "--prefix", "replay-test"])
        .args(["--speed", "5", "--wait-s", "30", "--mode", "peer"])
        .args(["--connect", &endpoint, "--no-multicast-scouting"])
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("road runs");
    let deadline = Instant::now() + Duration::from_secs(90);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            child.kill().ok();
            panic!("road replay did not finish");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("/road/npc -> replay-test/client/ego-7/scene/7/npc: 5 published"),
        "{}",
        stdout(&o)
    );
    let mut ticks = Vec::new();
    while ticks.len() < 5 {
        let Some(sample) = npc.recv_timeout(Duration::from_secs(10)).unwrap() else {
            break;
        };
        assert_eq!(
            sample.key_expr().as_str(),
            "replay-test/client/ego-7/scene/7/npc"
        );
        let v: serde_json::Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        ticks.push(v["tick"].as_u64().unwrap());
    }
    assert_eq!(ticks, [1, 2, 3, 4, 5]);
    session.close().wait().unwrap();
    std::fs::remove_dir_all(&dir).ok();
}
