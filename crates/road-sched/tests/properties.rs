//! Property tests of the math doc's invariants, for every planner kind.

use proptest::prelude::*;
use road_sched::{
    EdmSchedule, PlannerKind, PlannerSpec, PlannerTables, Sampler, SceneSpec, Scheduler, StageKind,
    TickOutcome, WindowUpdate,
};

fn spec(kind: PlannerKind, n: usize, f: usize, k: usize, x: Option<usize>) -> PlannerSpec {
    PlannerSpec {
        kind,
        obs_slots: n,
        future_slots: f,
        steps_per_diffusion: k,
        replan_every: x,
        obs_sigma: None,
        obs_noise: None,
        acceleration_smoothing: None,
        jerk_tracking: None,
        plan_smoothing: None,
        plan_smoothing_ahead: None,
        noise_temperature: None,
        collision_guard: None,
        lane_guard: None,
        stall_release: None,
        stuck_removal: None,
        give_way: None,
        sampler: Sampler::Heun,
        edm: EdmSchedule::default(),
    }
}

/// Any valid planner: (kind, n, F, K, X) under either sampler.
fn any_planner() -> impl Strategy<Value = PlannerSpec> {
    (any_heun_planner(), any::<bool>()).prop_map(|(mut spec, multistep)| {
        if multistep {
            spec.sampler = Sampler::Multistep;
        }
        spec
    })
}

/// Any valid planner under the Heun sampler.
fn any_heun_planner() -> impl Strategy<Value = PlannerSpec> {
    let rolling = (1usize..12, 1usize..24, 1usize..6)
        .prop_map(|(n, f, m)| spec(PlannerKind::Rolling, n, f, f * m, None));
    let ar = (1usize..12, 1usize..64)
        .prop_map(|(n, k)| spec(PlannerKind::Autoregressive, n, 1, k, None));
    let mpc = (
        1usize..12,
        1usize..24,
        1usize..64,
        any::<prop::sample::Index>(),
    )
        .prop_map(|(n, f, k, x)| spec(PlannerKind::Mpc, n, f, k, Some(x.index(f) + 1)));
    let one_shot = (1usize..12, 1usize..40, 1usize..64)
        .prop_map(|(n, f, k)| spec(PlannerKind::OneShot, n, f, k, None));
    prop_oneof![rolling, ar, mpc, one_shot]
}

/// Relative closeness for σ values that went through f32.
fn close(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-6 + 1e-5 * b.abs()
}

/// The σ profile after a window shift: drop future slot 0, append a pure-noise slot.
fn shifted(sigma: &[f32], obs: usize, sigma_max: f32) -> Vec<f32> {
    let mut out = sigma[..obs].to_vec();
    out.extend_from_slice(&sigma[obs + 1..]);
    out.push(sigma_max);
    out
}

fn stages(t: &PlannerTables) -> Vec<StageKind> {
    match t.spec.kind {
        PlannerKind::Rolling | PlannerKind::Autoregressive => {
            vec![StageKind::Warmup, StageKind::Rolling]
        }
        PlannerKind::Mpc | PlannerKind::OneShot => vec![StageKind::Full],
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn snr_never_rises_along_the_window(spec in any_planner()) {
        let t = PlannerTables::new("p", spec.clone()).unwrap();
        let n = spec.obs_slots;
        for stage in stages(&t) {
            let table = t.stage(stage);
            for s in 0..table.steps() {
                let p = table.step(s);
                for sig in [p.sigma_cur, p.sigma_next] {
                    for w in n + 1..sig.len() {
                        prop_assert!(sig[w - 1] <= sig[w], "{stage:?} step {s}: σ[{}] = {} > σ[{w}] = {}", w - 1, sig[w - 1], sig[w]);
                    }
                }
            }
        }
    }

    #[test]
    fn slot_zero_is_clean_at_the_end_of_every_stage(spec in any_planner()) {
        let t = PlannerTables::new("p", spec.clone()).unwrap();
        for stage in stages(&t) {
            let table = t.stage(stage);
            let last = table.step(table.steps() - 1);
            prop_assert_eq!(last.sigma_next[spec.obs_slots], 0.0, "{:?}", stage);
            // And it was noisy at the start of the stage.
            prop_assert!(table.step(0).sigma_cur[spec.obs_slots] > 0.0);
        }
    }

    #[test]
    fn steps_per_stage_are_k_and_k_over_f(spec in any_planner()) {
        let t = PlannerTables::new("p", spec.clone()).unwrap();
        let k = spec.steps_per_diffusion;
        match spec.kind {
            PlannerKind::Rolling | PlannerKind::Autoregressive => {
                prop_assert_eq!(t.warmup.steps(), k);
                prop_assert_eq!(t.rolling.steps(), k / spec.future_slots);
            }
            PlannerKind::Mpc | PlannerKind::OneShot => prop_assert_eq!(t.full.steps(), k),
        }
    }

    #[test]
    fn steps_chain_within_and_across_stages(spec in any_planner()) {
        let t = PlannerTables::new("p", spec.clone()).unwrap();
        let n = spec.obs_slots;
        let obs_sigma = spec.obs_sigma() as f32;
        for stage in stages(&t) {
            let table = t.stage(stage);
            for s in 0..table.steps() {
                let p = table.step(s);
                prop_assert!(p.sigma_cur[..n].iter().chain(&p.sigma_next[..n]).all(|&x| x == obs_sigma));
                if s + 1 < table.steps() {
                    prop_assert_eq!(p.sigma_next, table.step(s + 1).sigma_cur);
                }
            }
        }
        if matches!(spec.kind, PlannerKind::Rolling | PlannerKind::Autoregressive) {
            let sigma_max = spec.edm.sigma_max as f32;
            let first_rolling = t.rolling.step(0).sigma_cur;
            for from in [&t.warmup, &t.rolling] {
                let end = shifted(from.step(from.steps() - 1).sigma_next, n, sigma_max);
                for (w, (&a, &b)) in end.iter().zip(first_rolling).enumerate() {
                    prop_assert!(close(a, b), "{:?} → rolling jumps at slot {w}: {a} vs {b}", from.kind);
                }
            }
        }
    }

    #[test]
    fn every_slot_moves_by_one_kth_of_u_per_step(spec in any_planner()) {
        let t = PlannerTables::new("p", spec.clone()).unwrap();
        let du = 1.0 / spec.steps_per_diffusion as f64;
        for stage in stages(&t) {
            let table = t.stage(stage);
            for s in 0..table.steps() {
                let p = table.step(s);
                for w in spec.obs_slots..p.sigma_cur.len() {
                    let moved = spec.edm.u_of_sigma(f64::from(p.sigma_cur[w])) - spec.edm.u_of_sigma(f64::from(p.sigma_next[w]));
                    prop_assert!(moved.abs() < 1e-4 || (moved - du).abs() < 1e-4, "{stage:?} step {s} slot {w}: Δu = {moved}");
                }
            }
        }
    }

    #[test]
    fn nfe_per_simulated_step_matches_the_math_doc(spec in any_planner(), ticks in 1u64..60) {
        let horizon = if spec.kind == PlannerKind::OneShot { ticks.min(spec.future_slots as u64) } else { ticks };
        let mut sched = Scheduler::new();
        let planner = sched.add_planner("p", spec.clone()).unwrap();
        let scene = sched.admit(SceneSpec { planner, external_agents: vec![] }).unwrap();
        let mut outcomes = Vec::new();
        let mut nfe = 0u64;
        for tick in 0..horizon {
            sched.request_tick(scene).unwrap();
            while sched.next_batch(8).unwrap() > 0 {
                sched.complete_batch();
            }
            sched.take_outcomes(&mut outcomes);
            let o: TickOutcome = outcomes.pop().unwrap();
            prop_assert_eq!(o.tick, tick);
            nfe += u64::from(o.nfe);
        }
        prop_assert_eq!(sched.stats(scene).unwrap().nfe, nfe);
        let expected = spec.expected_nfe_per_step(horizon) * horizon as f64;
        prop_assert!((nfe as f64 - expected).abs() < 1e-6, "counted {nfe} NFE, table says {expected}");
    }

    /// The multistep correction is DPM-Solver++(2M)'s update written as Euler plus a term:
    /// `(σn/σ)·x + (1 − σn/σ)·((1 + 1/2r)·D − D_prev/2r)` (k-diffusion's `sample_dpmpp_2m`).
    #[test]
    fn multistep_gamma_is_dpm_solver_2m(
        sigma_next in 0.001f64..50.0,
        up in 1.01f64..4.0,
        up_prev in 1.01f64..4.0,
        x in -3.0f64..3.0,
        d in -3.0f64..3.0,
        d_prev in -3.0f64..3.0,
    ) {
        let sigma = sigma_next * up;
        let sigma_prev = sigma * up_prev;
        let gamma = f64::from(Sampler::multistep_gamma(sigma_prev as f32, sigma as f32, sigma_next as f32));
        let euler = x + (sigma_next - sigma) * (x - d) / sigma;
        let ours = euler + gamma * (d - d_prev);
        let h = (sigma / sigma_next).ln();
        let r = (sigma_prev / sigma).ln() / h;
        let a = sigma_next / sigma;
        let theirs = a * x + (1.0 - a) * ((1.0 + 1.0 / (2.0 * r)) * d - d_prev / (2.0 * r));
        prop_assert!((ours - theirs).abs() < 1e-4 * (1.0 + theirs.abs()), "{ours} against {theirs}");
    }

    /// Many scenes of mixed planners, admitted and retired at random: every batch holds each
    /// scene at most once, every requested tick finishes, and no scene's work is lost.
    #[test]
    fn scheduler_serves_every_scene(ops in prop::collection::vec((0u8..4, 0usize..16), 1..200), max_batch in 1usize..9) {
        let mut sched = Scheduler::with_capacity(16);
        let planners = [
            sched.add_planner("road", spec(PlannerKind::Rolling, 3, 4, 8, None)).unwrap(),
            sched.add_planner("ar", spec(PlannerKind::Autoregressive, 3, 1, 5, None)).unwrap(),
            sched.add_planner("mpc", spec(PlannerKind::Mpc, 3, 4, 6, Some(2))).unwrap(),
            sched.add_planner("one", spec(PlannerKind::OneShot, 3, 30, 6, None)).unwrap(),
        ];
        let mut live = Vec::new();
        let mut requested = std::collections::HashMap::new();
        let mut outcomes = Vec::new();
        for (op, arg) in ops {
            match op {
                0 => live.push(sched.admit(SceneSpec { planner: planners[arg % 4], external_agents: vec![0] }).unwrap()),
                1 if !live.is_empty() => {
                    let id = live[arg % live.len()];
                    if sched.request_tick(id).is_ok() {
                        *requested.entry(id).or_insert(0u64) += 1;
                    }
                }
                2 if !live.is_empty() => {
                    sched.next_batch(max_batch).unwrap();
                    let batch = sched.batch().to_vec();
                    let mut seen = std::collections::HashSet::new();
                    for item in &batch {
                        prop_assert!(seen.insert(item.scene), "scene twice in a batch");
                        let plan = sched.step_plan(item);
                        prop_assert_eq!(plan.sigma_cur.len(), sched.planner(item.planner).unwrap().spec.window_slots());
                    }
                    sched.complete_batch();
                }
                3 if !live.is_empty() => {
                    let id = live.swap_remove(arg % live.len());
                    sched.retire(id).unwrap();
                    requested.remove(&id);
                    prop_assert!(sched.stats(id).is_err());
                }
                _ => {}
            }
        }
        // Drain: every requested tick of a live scene completes.
        while sched.next_batch(max_batch).unwrap() > 0 {
            sched.complete_batch();
        }
        sched.take_outcomes(&mut outcomes);
        for id in &live {
            let done = outcomes.iter().filter(|o| o.scene == *id).count() as u64;
            prop_assert_eq!(done, requested.get(id).copied().unwrap_or(0));
            prop_assert_eq!(sched.stats(*id).unwrap().ticks, done);
        }
        prop_assert_eq!(sched.live_scenes(), live.len());
        prop_assert_eq!(sched.pending_scenes(), 0);
    }
}

/// The math doc's table with the shipped step counts: RoAD-W ≈ 2K/F, AR ≈ 2K, MPC-X ≈ 2K/X,
/// one-shot 2K once.
#[test]
fn nfe_table_of_the_math_doc() {
    let k = 40;
    let road20 = spec(PlannerKind::Rolling, 10, 10, k, None);
    let road15 = spec(PlannerKind::Rolling, 10, 5, k, None);
    let ar = spec(PlannerKind::Autoregressive, 10, 1, k, None);
    let mpc1 = spec(PlannerKind::Mpc, 10, 10, k, Some(1));
    let mpc5 = spec(PlannerKind::Mpc, 10, 10, k, Some(5));
    let one_shot = spec(PlannerKind::OneShot, 10, 30, k, None);
    let long = 100_000;
    assert!((road20.expected_nfe_per_step(long) - 8.0).abs() < 1e-3);
    assert!((road15.expected_nfe_per_step(long) - 16.0).abs() < 1e-3);
    assert!((ar.expected_nfe_per_step(long) - 79.0).abs() < 1e-3);
    assert!((mpc1.expected_nfe_per_step(long) - 79.0).abs() < 1e-3);
    assert!((mpc5.expected_nfe_per_step(long) - 79.0 / 5.0).abs() < 1e-3);
    assert!((one_shot.expected_nfe_per_step(30) * 30.0 - 79.0).abs() < 1e-9);
}

/// The multistep sampler: one evaluation per step, so RoAD-20 at K = 20 costs 2 per tick (Heun:
/// 4); a slot without a previous estimate, or landing on 0, takes the Euler step (γ = 0).
#[test]
fn multistep_halves_the_evaluations() {
    let mut road20 = spec(PlannerKind::Rolling, 10, 10, 20, None);
    let long = 100_000;
    assert!((road20.expected_nfe_per_step(long) - 4.0).abs() < 1e-3);
    road20.sampler = Sampler::Multistep;
    assert!((road20.expected_nfe_per_step(long) - 2.0).abs() < 1e-3);
    let tables = PlannerTables::new("road20-2m", road20).unwrap();
    for stage in [StageKind::Warmup, StageKind::Rolling] {
        let table = tables.stage(stage);
        assert_eq!(table.nfe() as usize, table.steps(), "{stage:?}");
    }
    assert_eq!(Sampler::multistep_gamma(0.0, 2.0, 1.0), 0.0);
    assert_eq!(Sampler::multistep_gamma(4.0, 2.0, 0.0), 0.0);
    assert_eq!(Sampler::multistep_gamma(2.0, 2.0, 2.0), 0.0);
    // Equal log-steps (r = 1): γ = (1 − σn/σ)/2.
    assert!((Sampler::multistep_gamma(4.0, 2.0, 1.0) - 0.25).abs() < 1e-6);
}

#[test]
fn window_updates_follow_each_planner() {
    let k = 8;
    let mpc = spec(PlannerKind::Mpc, 2, 4, k, Some(3));
    let updates: Vec<_> = (0..6).map(|t| mpc.tick_program(t).unwrap()).collect();
    assert_eq!(
        updates
            .iter()
            .map(|p| p.stage.is_some())
            .collect::<Vec<_>>(),
        [true, false, false, true, false, false]
    );
    assert_eq!(
        updates
            .iter()
            .map(|p| p.emit_future_slot)
            .collect::<Vec<_>>(),
        [0, 1, 2, 0, 1, 2]
    );
    assert_eq!(updates[2].then, WindowUpdate::Rebuild);
    let one = spec(PlannerKind::OneShot, 2, 3, k, None);
    assert_eq!(one.tick_program(2).unwrap().then, WindowUpdate::Exhausted);
    assert!(one.tick_program(3).is_none());
    let road = spec(PlannerKind::Rolling, 2, 4, k, None);
    assert_eq!(road.tick_program(0).unwrap().stage, Some(StageKind::Warmup));
    assert_eq!(
        road.tick_program(7).unwrap().stage,
        Some(StageKind::Rolling)
    );
}

#[test]
fn invalid_planners_are_named_errors() {
    let bad = spec(PlannerKind::Rolling, 10, 10, 45, None);
    let err = PlannerTables::new("road20", bad).unwrap_err().to_string();
    assert!(err.contains("road20") && err.contains("multiple"), "{err}");
    let err = PlannerTables::new("ar", spec(PlannerKind::Autoregressive, 10, 2, 4, None))
        .unwrap_err()
        .to_string();
    assert!(err.contains("future_slots = 1"), "{err}");
    let err = PlannerTables::new("mpc", spec(PlannerKind::Mpc, 10, 10, 40, None))
        .unwrap_err()
        .to_string();
    assert!(err.contains("replan_every"), "{err}");
    let err = PlannerTables::new("mpc", spec(PlannerKind::Mpc, 10, 10, 40, Some(11)))
        .unwrap_err()
        .to_string();
    assert!(err.contains("1..=10"), "{err}");
}

#[test]
fn scheduler_refuses_misuse() {
    let mut sched = Scheduler::new();
    let p = sched
        .add_planner("road", spec(PlannerKind::Rolling, 2, 2, 4, None))
        .unwrap();
    assert!(sched.add_planner("road", PlannerSpec::default()).is_err());
    let s = sched
        .admit(SceneSpec {
            planner: p,
            external_agents: vec![],
        })
        .unwrap();
    sched.request_tick(s).unwrap();
    assert!(
        sched
            .request_tick(s)
            .unwrap_err()
            .to_string()
            .contains("in progress")
    );
    assert_eq!(sched.next_batch(4).unwrap(), 1);
    assert!(matches!(
        sched.next_batch(4),
        Err(road_sched::Error::BatchInFlight)
    ));
    assert!(
        sched.retire(s).is_err(),
        "a scene in the batch cannot retire"
    );
    sched.complete_batch();
    sched.retire(s).unwrap();
    assert!(
        sched
            .request_tick(s)
            .unwrap_err()
            .to_string()
            .contains("no live scene")
    );
    let s2 = sched
        .admit(SceneSpec {
            planner: p,
            external_agents: vec![],
        })
        .unwrap();
    assert_eq!(s2.index(), s.index(), "slots are reused");
    assert_ne!(s2, s, "ids are not");
}

#[test]
fn plan_smoothing_options_are_checked_together() {
    let with = |h: Option<usize>, ahead: Option<usize>| PlannerSpec {
        plan_smoothing: h,
        plan_smoothing_ahead: ahead,
        ..spec(PlannerKind::Rolling, 10, 10, 40, None)
    };
    assert_eq!(with(Some(4), None).plan_smoothing_fit(), Some((4, 4)));
    assert_eq!(with(Some(4), Some(0)).plan_smoothing_fit(), Some((4, 0)));
    assert_eq!(with(None, None).plan_smoothing_fit(), None);
    assert!(with(Some(4), Some(2)).validate("p").is_ok());
    let error = |h, ahead| with(h, ahead).validate("p").unwrap_err().to_string();
    assert!(
        error(Some(4), Some(5))
            .contains("plan_smoothing_ahead must be 0 to plan_smoothing (4), got 5")
    );
    assert!(error(None, Some(2)).contains("plan_smoothing_ahead needs plan_smoothing"));
    assert!(error(Some(0), None).contains("plan_smoothing must be 1 to"));
}

#[test]
fn noise_temperature_is_checked() {
    let with = |tau: f64| PlannerSpec {
        noise_temperature: Some(tau),
        ..spec(PlannerKind::Rolling, 10, 10, 20, None)
    };
    for tau in [0.5, 1.0, 1.5, 2.0] {
        assert!(with(tau).validate("p").is_ok(), "τ = {tau}");
        assert_eq!(with(tau).noise_temperature(), tau);
    }
    for tau in [0.0, -1.0, 2.5, f64::NAN, f64::INFINITY] {
        let message = with(tau).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("noise_temperature must be in (0, 2]"),
            "τ = {tau}: {message}"
        );
    }
}

#[test]
fn jerk_tracking_options_are_checked() {
    let with = |jerk_cost_m: f64, ahead: usize| PlannerSpec {
        jerk_tracking: Some(road_sched::JerkTracking {
            jerk_cost_m,
            ahead,
            max_acceleration_mps2: Some(6.0),
            max_slip_deg: Some(5.0),
            max_course_offset_deg: None,
            min_turn_radius_m: None,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    assert!(with(0.01, 3).validate("p").is_ok());
    assert!(with(0.01, 0).validate("p").is_ok());
    let error = |cost, ahead| with(cost, ahead).validate("p").unwrap_err().to_string();
    for cost in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(
            error(cost, 3).contains("jerk_tracking.jerk_cost_m must be positive and finite"),
            "{cost}"
        );
    }
    // Five future slots: at most five to look at.
    assert!(error(0.01, 6).contains("jerk_tracking.ahead must be 0 to 5 slots, got 6"));
    let unbounded = PlannerSpec {
        jerk_tracking: Some(road_sched::JerkTracking {
            jerk_cost_m: 0.01,
            ahead: 2,
            max_acceleration_mps2: Some(0.0),
            max_slip_deg: None,
            max_course_offset_deg: None,
            min_turn_radius_m: None,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    assert!(
        unbounded
            .validate("p")
            .unwrap_err()
            .to_string()
            .contains("jerk_tracking.max_acceleration_mps2 must be positive and finite, got 0")
    );
    for slip in [-1.0, 90.0, f64::NAN] {
        let sliding = PlannerSpec {
            jerk_tracking: Some(road_sched::JerkTracking {
                jerk_cost_m: 0.01,
                ahead: 2,
                max_acceleration_mps2: None,
                max_slip_deg: Some(slip),
                max_course_offset_deg: None,
                min_turn_radius_m: None,
            }),
            ..spec(PlannerKind::Rolling, 10, 5, 40, None)
        };
        let message = sliding.validate("p").unwrap_err().to_string();
        assert!(
            message.contains("jerk_tracking.max_slip_deg must be 0 to below 90 degrees"),
            "{slip}: {message}"
        );
    }
}

/// The turning circle and the deadlock release take physical values at their bounds and refuse
/// the rest by name.
#[test]
fn turning_circle_and_deadlock_release_are_checked() {
    let turning = |radius: f64| PlannerSpec {
        jerk_tracking: Some(road_sched::JerkTracking {
            jerk_cost_m: 0.01,
            ahead: 2,
            max_acceleration_mps2: None,
            max_slip_deg: None,
            max_course_offset_deg: None,
            min_turn_radius_m: Some(radius),
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    for radius in [0.1, 4.0, 50.0] {
        assert!(turning(radius).validate("p").is_ok(), "{radius}");
    }
    for radius in [0.0, -1.0, 50.1, f64::NAN, f64::INFINITY] {
        let message = turning(radius).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("jerk_tracking.min_turn_radius_m must be above 0 and at most 50"),
            "{radius}: {message}"
        );
    }
    let deadlock = |secs: f64| PlannerSpec {
        collision_guard: Some(road_sched::CollisionGuard {
            horizon_steps: 10,
            brake_mps2: 6.0,
            yield_to_unreactive: true,
            release_deadlock_after_secs: Some(secs),
            regrow_cut_steps: false,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    for secs in [0.1, 5.0, 600.0] {
        assert!(deadlock(secs).validate("p").is_ok(), "{secs}");
    }
    for secs in [0.0, -5.0, 600.5, f64::NAN] {
        let message = deadlock(secs).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("collision_guard.release_deadlock_after_secs must be above 0"),
            "{secs}: {message}"
        );
    }
}

/// The lane guard's nudges take 1 to 50 steps of look-ahead and a turn in (0, 1] rad per metre;
/// anything else is refused by name.
#[test]
fn lane_guard_anticipation_outside_its_bounds_is_refused() {
    let with = |steps, max_turn_rad_per_m| PlannerSpec {
        lane_guard: Some(road_sched::LaneGuard {
            lookahead_m: 6.0,
            turn_plan: true,
            anticipation: Some(road_sched::LaneAnticipation {
                steps,
                max_turn_rad_per_m,
            }),
            keep_off_opposing_lanes: false,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    assert!(with(3, 0.1).validate("p").is_ok());
    for (steps, turn) in [(0, 0.1), (51, 0.1), (3, 0.0), (3, 1.5), (3, f64::NAN)] {
        let message = with(steps, turn).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("lane_guard.anticipation: steps must be in 1..=50"),
            "{steps}, {turn}: {message}"
        );
    }
}

/// The stall release and the stuck removal take their documented ranges; anything else is
/// refused by name.
#[test]
fn stall_release_and_stuck_removal_outside_their_bounds_are_refused() {
    let gridlock = |gridlock_after_secs| PlannerSpec {
        stall_release: Some(road_sched::StallRelease {
            after_secs: 3.0,
            acceleration_mps2: 1.5,
            release_speed_mps: 5.0,
            gridlock_after_secs,
            hand_back_speed_mps: None,
            make_room_again: false,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    let release = |after_secs, acceleration_mps2, release_speed_mps| PlannerSpec {
        stall_release: Some(road_sched::StallRelease {
            after_secs,
            acceleration_mps2,
            release_speed_mps,
            gridlock_after_secs: None,
            hand_back_speed_mps: None,
            make_room_again: false,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    let hand_back = |hand_back_speed_mps| PlannerSpec {
        stall_release: Some(road_sched::StallRelease {
            after_secs: 3.0,
            acceleration_mps2: 1.5,
            release_speed_mps: 5.0,
            gridlock_after_secs: None,
            hand_back_speed_mps,
            make_room_again: false,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    for mps in [None, Some(0.5), Some(5.0)] {
        assert!(hand_back(mps).validate("p").is_ok(), "{mps:?}");
    }
    for mps in [Some(0.0), Some(-1.0), Some(5.5), Some(f64::NAN)] {
        let message = hand_back(mps).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("hand_back_speed_mps, when set, in (0, release_speed_mps]"),
            "{mps:?}: {message}"
        );
    }
    assert!(release(3.0, 1.5, 5.0).validate("p").is_ok());
    for secs in [None, Some(1.0), Some(600.0)] {
        assert!(gridlock(secs).validate("p").is_ok(), "{secs:?}");
    }
    for secs in [Some(0.0), Some(-1.0), Some(600.5), Some(f64::NAN)] {
        let message = gridlock(secs).validate("p").unwrap_err().to_string();
        assert!(
            message.contains("gridlock_after_secs, when set, in (0, 600]"),
            "{secs:?}: {message}"
        );
    }
    for (secs, acc, speed) in [
        (0.0, 1.5, 5.0),
        (600.5, 1.5, 5.0),
        (3.0, 0.0, 5.0),
        (3.0, 5.5, 5.0),
        (3.0, 1.5, 0.0),
        (3.0, 1.5, 20.5),
        (f64::NAN, 1.5, 5.0),
    ] {
        let message = release(secs, acc, speed)
            .validate("p")
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("stall_release: after_secs must be in (0, 600]"),
            "{secs} {acc} {speed}: {message}"
        );
    }
    let removal_disoriented =
        |after_secs, clear_of_external_m, disoriented_after_secs| PlannerSpec {
            stuck_removal: Some(road_sched::StuckRemoval {
                after_secs,
                clear_of_external_m,
                disoriented_after_secs,
            }),
            ..spec(PlannerKind::Rolling, 10, 5, 40, None)
        };
    let removal = |after_secs, clear_of_external_m| {
        removal_disoriented(after_secs, clear_of_external_m, None)
    };
    for (secs, clear) in [(30.0, 50.0), (0.1, 0.0), (600.0, 10_000.0)] {
        assert!(removal(secs, clear).validate("p").is_ok(), "{secs} {clear}");
    }
    for disoriented in [0.1, 5.0, 600.0] {
        assert!(
            removal_disoriented(30.0, 50.0, Some(disoriented))
                .validate("p")
                .is_ok(),
            "{disoriented}"
        );
    }
    for disoriented in [0.0, -1.0, 600.5, f64::NAN, f64::INFINITY] {
        let message = removal_disoriented(30.0, 50.0, Some(disoriented))
            .validate("p")
            .unwrap_err()
            .to_string();
        assert!(
            message.contains(
                "stuck_removal: after_secs and disoriented_after_secs must be in (0, 600]"
            ),
            "{disoriented}: {message}"
        );
    }
    for (secs, clear) in [
        (0.0, 50.0),
        (-1.0, 50.0),
        (600.5, 50.0),
        (f64::NAN, 50.0),
        (30.0, -1.0),
        (30.0, 10_000.5),
        (30.0, f64::NAN),
    ] {
        let message = removal(secs, clear).validate("p").unwrap_err().to_string();
        assert!(
            message.contains(
                "stuck_removal: after_secs and disoriented_after_secs must be in (0, 600]"
            ),
            "{secs} {clear}: {message}"
        );
    }
}

/// The give-way rule takes its documented ranges; anything else is refused by name.
#[test]
fn give_way_outside_its_bounds_is_refused() {
    let rule = |approach_m, gap_secs, brake_mps2, stop_secs| PlannerSpec {
        give_way: Some(road_sched::GiveWay {
            approach_m,
            gap_secs,
            brake_mps2,
            stop_secs,
        }),
        ..spec(PlannerKind::Rolling, 10, 5, 40, None)
    };
    for ok in [
        (30.0, 3.0, 3.0, 1.0),
        (100.0, 30.0, 10.0, 0.0),
        (0.1, 0.1, 0.1, 30.0),
    ] {
        assert!(rule(ok.0, ok.1, ok.2, ok.3).validate("p").is_ok(), "{ok:?}");
    }
    for bad in [
        (0.0, 3.0, 3.0, 1.0),
        (100.5, 3.0, 3.0, 1.0),
        (f64::NAN, 3.0, 3.0, 1.0),
        (30.0, 0.0, 3.0, 1.0),
        (30.0, 30.5, 3.0, 1.0),
        (30.0, 3.0, 0.0, 1.0),
        (30.0, 3.0, 10.5, 1.0),
        (30.0, 3.0, 3.0, -0.1),
        (30.0, 3.0, 3.0, 30.5),
        (30.0, 3.0, 3.0, f64::NAN),
    ] {
        let message = rule(bad.0, bad.1, bad.2, bad.3)
            .validate("p")
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("give_way: approach_m must be in (0, 100]"),
            "{bad:?}: {message}"
        );
    }
}
