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
        &["sched", "plan", "--help"],
        &["sched", "list", "--help"],
        &["gpu", "info", "--help"],
        &["gpu", "selftest", "--help"],
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
        stdout(&o).contains("Rolling stage: 4 steps, 8 NFE"),
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
        "layer_norm",
        "attention",
        "pair_attention",
        "pick_agent_maps",
        "edm.precondition",
    ] {
        assert!(text.contains(&format!("{kernel}: ok")), "{kernel}: {text}");
    }
    for checkpoint in ["models/road20-cvmap", "models/road20"] {
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
    let o = road(&[
        "bench",
        "serve",
        "--scenes",
        "2",
        "--ticks",
        "2",
        "--join-every",
        "2",
        "--cache",
        dir_arg,
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
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
    std::fs::remove_dir_all(&dir).ok();
}

/// `road demo --map`: the intersection and the merge run too; an unknown map is refused with
/// the known ones named.
#[test]
fn demo_runs_every_procedural_map() {
    let dir = std::env::temp_dir().join(format!("road-cli-demo-maps-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for map in ["intersection", "merge"] {
        let png = dir.join(format!("demo-{map}.png"));
        let o = road(&[
            "demo",
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
    let o = road(&["demo", "--map", "atlantis", "--steps", "1"]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("roundabout, intersection, merge"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `road demo`, the README's main job: the procedural scene closed loop on both engines.
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
        // RoAD-20: the K = 40 warm-up (80 NFE) then rolling stages of K/F = 4 steps (8 NFE).
        assert_eq!(v["nfe"], 80 + 3 * 8);
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
    for name in ["log-replay", "constant-velocity", "road20"] {
        let png = dir.join(format!("reactivity-{name}-00.png"));
        assert!(
            std::fs::read(&png).unwrap().starts_with(b"\x89PNG"),
            "{name}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
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
    let file = |name: &str, model: &str, per_scene: Vec<serde_json::Value>| {
        let path = dir.join(name);
        let json = serde_json::json!({ "suite": "forecasting", "results": [
            { "model": model, "per_scene": per_scene } ] });
        std::fs::write(&path, json.to_string()).unwrap();
        path.to_str().unwrap().to_owned()
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
