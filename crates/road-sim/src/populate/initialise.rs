//! The learned initialiser: new vehicles' whole observed histories drawn by a denoiser trained
//! with the initialisation task (`TrainConfig::initialisation_task_prob`), jointly, around the
//! agents the caller fixes and on the map. Unlike [`super::refine_histories`], which only
//! nudges placed histories within the conditioning augmentation's noise, the drawn agents here
//! start at any σ up to σ_max: from pure noise (where they are, how fast, which way: all the
//! model's), or, from a lower σ, around a placement (SDEdit: the placement's lane and place
//! roughly kept, the rest the model's). σ is per agent and slot: the fixed agents' observed
//! slots stay at σ_min, as the task trained them, while everything else descends together.

use candle_core::{Device, Tensor};
use rand::rngs::StdRng;
use road_data::{LaneletMap, SceneWindow};
use road_model::Denoiser;
use road_model::batch::{SceneInput, normal_vec};
use road_model::model::Mode;
use road_sched::edm::EdmSchedule;

use super::{Footprint, check_histories, padded_map, with_drawn_histories};
use crate::{Error, Result};

/// How [`initialise_histories`] samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Initialisation {
    /// σ (scene units) the drawn agents start at: the schedule's σ_max draws them from noise
    /// alone; a lower σ starts around their placed histories (extrapolated at constant
    /// velocity over the future slots).
    pub sigma_start: f64,
    /// Heun steps from `sigma_start` down to σ_min (ρ-spaced, as the EDM sampler's).
    pub steps: usize,
}

impl Initialisation {
    /// From pure noise in 32 steps.
    pub fn from_noise(edm: &EdmSchedule) -> Self {
        Self {
            sigma_start: edm.sigma_max,
            steps: 32,
        }
    }
}

/// `window` with its agents not `fixed` drawn anew by `model` (see the module's
/// documentation): their observed steps (all of the window's, fewer than the model's slots)
/// come from the model, their sizes and types stay. `edm` is the schedule to sample on (the
/// checkpoint's). The fixed agents' states are as given.
pub fn initialise_histories(
    model: &Denoiser,
    edm: &EdmSchedule,
    window: &SceneWindow,
    fixed: &[bool],
    init: Initialisation,
    rng: &mut StdRng,
) -> Result<SceneWindow> {
    let config = &model.config;
    let (a, n, w) = (window.agents, window.steps, config.window_slots);
    if config
        .agent_frame
        .as_ref()
        .is_some_and(|f| f.max_anchor_sigma.is_none())
    {
        return Err(Error::Config(
            "this checkpoint was not trained to draw whole agents (its agent_frame has no max_anchor_sigma; use one trained with train.initialisation_task_prob, e.g. models/road20-init)".into(),
        ));
    }
    check_histories(window, fixed, w)?;
    if !(init.sigma_start > edm.sigma_min && init.sigma_start <= edm.sigma_max) || init.steps == 0 {
        return Err(Error::Config(format!(
            "initialisation from σ = {} in {} steps: σ lies in (σ_min, σ_max] = ({}, {}], steps ≥ 1",
            init.sigma_start, init.steps, edm.sigma_min, edm.sigma_max
        )));
    }
    if a == 0 || fixed.iter().all(|&f| f) {
        return Ok(window.clone());
    }
    let input = SceneInput::from_window(window, 0, n, config);
    let x = sample(model, edm, &input, fixed, init, rng)?;
    with_drawn_histories(window, fixed, &x, w, config.heading_scale, "initialisation")
}

/// The sampler of [`initialise_histories`] past its checks: the scene's drawn states
/// `[A, W, 3]` (model units).
fn sample(
    model: &Denoiser,
    edm: &EdmSchedule,
    input: &SceneInput,
    fixed: &[bool],
    init: Initialisation,
    rng: &mut StdRng,
) -> road_model::Result<Vec<f32>> {
    let (a, n, w) = (input.agents, input.slots, model.config.window_slots);
    let device = Device::Cpu;
    let (polylines, map, map_valid) = padded_map(input);
    let map = Tensor::from_vec(map, (1, polylines, input.points, 2), &device)?;
    let map_valid = Tensor::from_vec(map_valid, (1, polylines), &device)?;
    let map_tokens = model.encode_map(&map, Mode::Infer)?;
    let features = Tensor::from_vec(
        input.agent_features.clone(),
        (1, a, input.agent_features.len() / a),
        &device,
    )?;
    let valid = Tensor::ones((1, a, w), candle_core::DType::F32, &device)?;

    // Start: the given histories, extrapolated at their last step over the future slots, plus
    // σ_start noise wherever a slot is drawn.
    let sigma_min = edm.sigma_min as f32;
    let start = init.sigma_start as f32;
    let observed = |agent: usize, slot: usize| fixed[agent] && slot < n;
    let noise = normal_vec(rng, a * w * 3);
    let mut x = vec![0.0f32; a * w * 3];
    for agent in 0..a {
        let state = |slot: usize| &input.states[3 * (agent * n + slot)..][..3];
        let last = state(n - 1);
        let step: Vec<f32> = if n >= 2 {
            (0..3).map(|d| last[d] - state(n - 2)[d]).collect()
        } else {
            vec![0.0; 3]
        };
        for slot in 0..w {
            let k = 3 * (agent * w + slot);
            for d in 0..3 {
                let base = if slot < n {
                    state(slot)[d]
                } else {
                    last[d] + step[d] * (slot + 1 - n) as f32
                };
                x[k + d] = if observed(agent, slot) {
                    base
                } else {
                    base + start * noise[k + d]
                };
            }
        }
    }
    // ρ-spaced levels from σ_start to σ_min.
    let rho = edm.rho;
    let (hi, lo) = (
        init.sigma_start.powf(1.0 / rho),
        edm.sigma_min.powf(1.0 / rho),
    );
    let levels: Vec<f32> = (0..=init.steps)
        .map(|i| (hi + (lo - hi) * i as f64 / init.steps as f64).powf(rho) as f32)
        .collect();
    let sigma_of = |level: f32| -> Vec<f32> {
        (0..a * w)
            .map(|k| {
                if observed(k / w, k % w) {
                    sigma_min
                } else {
                    level.max(sigma_min)
                }
            })
            .collect()
    };
    let denoise = |x: &[f32], sigma: &[f32]| -> road_model::Result<Vec<f32>> {
        let xt = Tensor::from_vec(x.to_vec(), (1, a, w, 3), &device)?;
        let st = Tensor::from_vec(sigma.to_vec(), (1, a, w), &device)?;
        let out = model.denoise(
            &xt,
            &st,
            &valid,
            &features,
            &map_tokens,
            &map_valid,
            Mode::Infer,
        )?;
        Ok(out.flatten_all()?.to_vec1::<f32>()?)
    };
    // Heun (EDM's second-order step) per token: a token whose σ does not change stays.
    for pair in levels.windows(2) {
        let (cur, next) = (sigma_of(pair[0]), sigma_of(pair[1]));
        let d_cur = denoise(&x, &cur)?;
        let slope = |x: &[f32], d: &[f32], sigma: &[f32], k: usize| (x[k] - d[k]) / sigma[k / 3];
        let euler: Vec<f32> = (0..x.len())
            .map(|k| x[k] + (next[k / 3] - cur[k / 3]) * slope(&x, &d_cur, &cur, k))
            .collect();
        let d_next = denoise(&euler, &next)?;
        for k in 0..x.len() {
            let dt = next[k / 3] - cur[k / 3];
            if dt != 0.0 {
                x[k] += dt * 0.5 * (slope(&x, &d_cur, &cur, k) + slope(&euler, &d_next, &next, k));
            }
        }
    }
    // The last level's denoised estimate: x itself still carries σ_min's noise (8 cm at
    // σ_min = 0.002 of 40 m), which a history's 0.1 s steps read as ±1 m/s.
    denoise(&x, &sigma_of(edm.sigma_min as f32))
}

/// The σ (scene units) a served scene's placement is redrawn from: about 4 m, road20-init's
/// anchor bound; of 0.05, 0.1 and 0.25 it came closest to the recordings with the fallback
/// (`road eval --suite initialisation --initialiser`, docs/results.md "Populating a map").
pub const REDRAW_SIGMA: f64 = 0.1;
/// Heun steps of the redraw down to σ_min.
pub const REDRAW_STEPS: usize = 32;

/// What a served scene starts from (`CreateScene.populate`): `placement`'s agents not `fixed`
/// drawn by the initialiser `model` from [`REDRAW_SIGMA`] (on its schedule `edm`), each draw
/// that lands off `map`'s lanes or on another agent taking its history in `refined` (the same
/// placement refined: [`sound_or`]); which agents kept the draw.
pub fn redraw_placement(
    model: &Denoiser,
    edm: &EdmSchedule,
    map: &LaneletMap,
    placement: &SceneWindow,
    refined: &SceneWindow,
    fixed: &[bool],
    rng: &mut StdRng,
) -> Result<(SceneWindow, Vec<bool>)> {
    let init = Initialisation {
        sigma_start: REDRAW_SIGMA,
        steps: REDRAW_STEPS,
    };
    let drawn = initialise_histories(model, edm, placement, fixed, init, rng)?;
    sound_or(map, &drawn, refined, fixed)
}

/// `drawn` (a window of [`initialise_histories`]) with every drawn vehicle that ends off the
/// lanes of `map`, or overlapping an agent decided before it or the fallback of one after it,
/// replaced by its history in `fallback` (the same agents, mutually clear: the refined
/// placement), in agent order; the fixed agents as in `drawn`. Returns the window and which agents kept the model's draw: what a served
/// scene starts from, so that a draw that missed the road never becomes an NPC off it.
pub fn sound_or(
    map: &LaneletMap,
    drawn: &SceneWindow,
    fallback: &SceneWindow,
    fixed: &[bool],
) -> Result<(SceneWindow, Vec<bool>)> {
    let (a, n) = (drawn.agents, drawn.steps);
    if fallback.agents != a || fallback.steps != n || fixed.len() != a {
        return Err(Error::Config(format!(
            "drawn window {a} × {n}, fallback {} × {}, {} fixed flags",
            fallback.agents,
            fallback.steps,
            fixed.len()
        )));
    }
    let last = |w: &SceneWindow, agent: usize| crate::window_pose(w, agent, n - 1);
    let footprint = |w: &SceneWindow, agent: usize| {
        last(w, agent).map(|pose| Footprint {
            pose,
            length_m: f64::from(w.length_m[agent]),
            width_m: f64::from(w.width_m[agent]),
        })
    };
    let mut out = drawn.clone();
    let mut kept = vec![false; a];
    let mut occupied: Vec<Footprint> = (0..a)
        .filter(|&agent| fixed[agent])
        .filter_map(|agent| footprint(drawn, agent))
        .collect();
    for agent in (0..a).filter(|&agent| !fixed[agent]) {
        // Clear of the agents decided, and of the fallbacks of those still to decide (any of
        // them may fall back), so that the result is clear whatever they become.
        let mut others = occupied.clone();
        others.extend(
            (agent + 1..a)
                .filter(|&later| !fixed[later])
                .filter_map(|later| footprint(fallback, later)),
        );
        let sound = footprint(drawn, agent).filter(|f| {
            map.lanelet_at([f.pose.x_m, f.pose.y_m]).is_some()
                && super::has_room(f.pose, f.length_m, f.width_m, &others, 0.0)
        });
        let chosen = match sound {
            Some(f) => {
                kept[agent] = true;
                Some(f)
            }
            None => {
                let k = 3 * agent * n;
                out.states[k..k + 3 * n].copy_from_slice(&fallback.states[k..k + 3 * n]);
                out.valid[agent * n..(agent + 1) * n]
                    .copy_from_slice(&fallback.valid[agent * n..(agent + 1) * n]);
                footprint(fallback, agent)
            }
        };
        occupied.extend(chosen);
    }
    Ok((out, kept))
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use road_data::WindowConfig;
    use road_model::{AgentFrame, AgentMap, ModelConfig};

    use super::*;
    use crate::populate::{
        PlacementOptions, footprints, keep_agents, place_vehicles, with_vehicles,
    };
    use crate::procedural::{ProceduralMap, procedural};

    /// A small untrained model with an agent frame, agent maps and the anchor bound.
    fn model(max_anchor_sigma: Option<f64>) -> Denoiser {
        let config = ModelConfig {
            hidden: 16,
            heads: 2,
            blocks: 1,
            agent_frame: Some(AgentFrame {
                anchor_slot: 9,
                relative_scale: 1.0,
                residual_scale: Some(40.0),
                max_anchor_sigma,
            }),
            agent_map: Some(AgentMap { polylines: 4 }),
            ..ModelConfig::default()
        };
        road_model::model::init_seeded(&config, &Device::Cpu, 3)
            .unwrap()
            .1
    }

    /// The roundabout's ego and four placed vehicles, the ego fixed.
    fn scene() -> (SceneWindow, Vec<bool>) {
        let scene = procedural(ProceduralMap::Roundabout, &WindowConfig::default(), 10).unwrap();
        let ego = keep_agents(&scene.window, &[scene.ego.agent]);
        let mut rng = StdRng::seed_from_u64(4);
        let placed = place_vehicles(
            &scene.map,
            &footprints(&ego),
            4,
            10,
            &PlacementOptions::default(),
            &mut rng,
        );
        let window = with_vehicles(&ego, &placed).unwrap();
        let mut fixed = vec![false; window.agents];
        fixed[0] = true;
        (window, fixed)
    }

    #[test]
    fn drawn_agents_change_and_fixed_ones_stay() {
        let (window, fixed) = scene();
        let edm = EdmSchedule::default();
        let mut rng = StdRng::seed_from_u64(5);
        for sigma_start in [edm.sigma_max, 0.25] {
            let init = Initialisation {
                sigma_start,
                steps: 4,
            };
            let out =
                initialise_histories(&model(Some(0.1)), &edm, &window, &fixed, init, &mut rng)
                    .unwrap();
            assert_eq!(out.agents, window.agents);
            assert_eq!(out.states[..30], window.states[..30], "the ego moved");
            assert!(out.states.iter().all(|v| v.is_finite()));
            assert!(
                out.states[30..] != window.states[30..],
                "nothing drawn from σ = {sigma_start}"
            );
            assert_eq!(out.length_m, window.length_m);
        }
    }

    #[test]
    fn a_model_not_trained_to_draw_agents_or_a_bad_start_is_refused() {
        let (window, fixed) = scene();
        let edm = EdmSchedule::default();
        let mut rng = StdRng::seed_from_u64(5);
        let init = Initialisation::from_noise(&edm);
        let err = initialise_histories(&model(None), &edm, &window, &fixed, init, &mut rng)
            .unwrap_err()
            .to_string();
        assert!(err.contains("max_anchor_sigma"), "{err}");
        for (sigma_start, steps) in [(0.0, 4), (100.0, 4), (f64::NAN, 4), (1.0, 0)] {
            let init = Initialisation { sigma_start, steps };
            let err =
                initialise_histories(&model(Some(0.1)), &edm, &window, &fixed, init, &mut rng)
                    .unwrap_err()
                    .to_string();
            assert!(err.contains("initialisation from σ"), "{err}");
        }
        let err = initialise_histories(
            &model(Some(0.1)),
            &edm,
            &window,
            &fixed[..2],
            init,
            &mut rng,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("fixed flags"), "{err}");
    }

    #[test]
    fn draws_off_the_lanes_or_onto_another_fall_back() {
        let scene = procedural(ProceduralMap::Roundabout, &WindowConfig::default(), 10).unwrap();
        let (placed, fixed) = self::scene();
        let mut drawn = placed.clone();
        let n = placed.steps;
        // Vehicle 1 drawn 500 m away (off the map), vehicle 2 onto the ego, vehicle 3 moved
        // 0.1 m along: only vehicle 3 keeps its draw.
        let shift = |w: &mut SceneWindow, agent: usize, to: Option<[f32; 2]>, by: [f32; 2]| {
            for t in 0..n {
                let k = 3 * (agent * n + t);
                let (x, y) = match to {
                    Some(p) => (p[0], p[1]),
                    None => (w.states[k] + by[0], w.states[k + 1] + by[1]),
                };
                w.states[k] = x;
                w.states[k + 1] = y;
            }
        };
        let ego_now = [placed.states[3 * (n - 1)], placed.states[3 * (n - 1) + 1]];
        shift(&mut drawn, 1, None, [500.0 / 40.0, 0.0]);
        shift(&mut drawn, 2, Some(ego_now), [0.0, 0.0]);
        shift(&mut drawn, 3, None, [0.1 / 40.0, 0.0]);
        let (out, kept) = sound_or(&scene.map, &drawn, &placed, &fixed).unwrap();
        assert_eq!(kept, vec![false, false, false, true, true]);
        let rows =
            |w: &SceneWindow, agent: usize| w.states[3 * agent * n..3 * (agent + 1) * n].to_vec();
        assert_eq!(rows(&out, 1), rows(&placed, 1));
        assert_eq!(rows(&out, 2), rows(&placed, 2));
        assert_eq!(rows(&out, 3), rows(&drawn, 3));
        assert!(sound_or(&scene.map, &drawn, &placed, &fixed[..2]).is_err());
    }
}
