//! The two CPU engines behind [`StepEngine`]: [`CpuEngine`], candle's [`Denoiser`] (the
//! reference every other engine is held to), and [`FastCpuEngine`], the same denoiser on the
//! fast path of [`crate::fast`]. Both keep the windows on the host ([`HostWindows`]) and
//! evaluate only the scenes whose σ row changes: in a batch of scenes at different phases the
//! others hold still, and on the CPU skipping them is free.

use std::borrow::Cow;

use candle_core::{Device, Tensor};

use road_model::batch::AGENT_FEATURES;
use road_model::model::{Denoiser, MapTokens, Mode};
use road_model::{Error, Result};
use road_rollout::heun::{
    changing_scenes, gather_rows, heun_update, multistep_correct, scatter_rows,
};
use road_rollout::{
    ShiftEdit, ShiftShape, StepEngine, estimate_shift, window_emitted, window_shift,
};

use crate::fast::{FastDenoiser, FastInputs, SceneCache, SceneMap};

/// Every scene's window `[B, A, W, 3]` and validity `[B, A, W]` on the host.
#[derive(Debug, Default)]
struct HostWindows {
    scenes: usize,
    agents: usize,
    slots: usize,
    windows: Vec<f32>,
    valid: Vec<f32>,
    /// The last denoiser estimate D(x; σ) of each scene's window `[B, A, W, 3]` (zeros until
    /// a step moves it): what [`StepEngine::read_denoised`] reads.
    denoised: Vec<f32>,
}

impl HostWindows {
    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()> {
        let (x, v) = (self.agents * self.slots * 3, self.agents * self.slots);
        if windows.len() != self.scenes * x || valid.len() != self.scenes * v {
            return Err(Error::data(format!(
                "load: {} state and {} validity values for {} scenes × {} agents × {} slots",
                windows.len(),
                valid.len(),
                self.scenes,
                self.agents,
                self.slots
            )));
        }
        self.windows = windows.to_vec();
        self.valid = valid.to_vec();
        self.denoised = vec![0.0; windows.len()];
        Ok(())
    }

    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()> {
        let (x, v) = (window.len(), valid.len());
        if (scene + 1) * x > self.windows.len() || (scene + 1) * v > self.valid.len() {
            return Err(Error::data(format!(
                "load_scene {scene}: outside the loaded batch"
            )));
        }
        self.windows[scene * x..(scene + 1) * x].copy_from_slice(window);
        self.valid[scene * v..(scene + 1) * v].copy_from_slice(valid);
        // A rebuilt window has no estimate yet.
        self.denoised[scene * x..(scene + 1) * x].fill(0.0);
        Ok(())
    }

    fn read_denoised(&self, scenes: &[usize], out: &mut [f32]) -> Result<()> {
        let x = self.agents * self.slots * 3;
        if out.len() != scenes.len() * x {
            return Err(Error::data(format!(
                "read_denoised of {} scenes: {} outputs; scenes of {x} each",
                scenes.len(),
                out.len()
            )));
        }
        for (&scene, out) in scenes.iter().zip(out.chunks_exact_mut(x.max(1))) {
            if scene >= self.scenes || self.denoised.len() < (scene + 1) * x {
                return Err(Error::data(format!(
                    "read_denoised of scene {scene}: the loaded batch has {} scenes",
                    self.scenes
                )));
            }
            out.copy_from_slice(&self.denoised[scene * x..(scene + 1) * x]);
        }
        Ok(())
    }

    fn read_emitted(&self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()> {
        if slots.len() != self.scenes || out.len() != self.scenes * self.agents * 3 {
            return Err(Error::data(format!(
                "read_emitted: {} slots and {} outputs for {} scenes of {} agents",
                slots.len(),
                out.len(),
                self.scenes,
                self.agents
            )));
        }
        window_emitted(&self.windows, self.agents, self.slots, slots, out);
        Ok(())
    }

    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()> {
        let w = self.slots;
        let (x_len, v_len) = (self.agents * w * 3, self.agents * w);
        for e in edits {
            if e.scene >= self.scenes || e.valid.len() != v_len {
                return Err(Error::data(format!(
                    "shift of scene {}: {} validity flags, the batch has {} scenes × {v_len}",
                    e.scene,
                    e.valid.len(),
                    self.scenes
                )));
            }
            if !e.turns.is_empty() && e.turns.len() != e.emitted.len() / 3 * 4 {
                return Err(Error::data(format!(
                    "shift of scene {}: {} plan-turn values for {} emitted states",
                    e.scene,
                    e.turns.len(),
                    e.emitted.len() / 3
                )));
            }
            window_shift(&mut self.windows[e.scene * x_len..][..x_len], w, e, shape);
            estimate_shift(
                &mut self.denoised[e.scene * x_len..][..x_len],
                w,
                shape.observed,
                e.turns,
            );
            self.valid[e.scene * v_len..][..v_len].copy_from_slice(e.valid);
        }
        Ok(())
    }

    /// One Heun step of the scenes whose σ row changes, each evaluation by `denoise(x, σ,
    /// valid, scenes)` over the packed rows of those scenes.
    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
        mut denoise: impl FnMut(&[f32], &[f32], &[f32], &[usize]) -> Result<Vec<f32>>,
    ) -> Result<()> {
        let w = self.slots;
        let active = changing_scenes(sigma_cur, sigma_next, self.scenes, w)?;
        if active.is_empty() {
            return Ok(());
        }
        let (x_len, v_len) = (self.agents * w * 3, self.agents * w);
        let all = active.len() == self.scenes;
        let valid = rows_of(&self.valid, &active, all, v_len);
        let (stepped, last) = heun_update(
            &rows_of(&self.windows, &active, all, x_len),
            self.agents,
            w,
            &rows_of(sigma_cur, &active, all, w),
            &rows_of(sigma_next, &active, all, w),
            second_evaluation,
            |x, sigma| denoise(x, sigma, &valid, &active),
        )?;
        self.put_rows(&active, all, stepped, last);
        Ok(())
    }

    /// One multistep step (see [`StepEngine::step_multistep`]) of the scenes whose σ row
    /// changes, the evaluation by `denoise` as in [`Self::step`].
    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
        mut denoise: impl FnMut(&[f32], &[f32], &[f32], &[usize]) -> Result<Vec<f32>>,
    ) -> Result<()> {
        let w = self.slots;
        let active = changing_scenes(sigma_cur, sigma_next, self.scenes, w)?;
        if gamma.len() != sigma_cur.len() {
            return Err(Error::data(format!(
                "multistep step: {} γ values for {} scenes × {w} slots",
                gamma.len(),
                self.scenes
            )));
        }
        if active.is_empty() {
            return Ok(());
        }
        let (x_len, v_len) = (self.agents * w * 3, self.agents * w);
        let all = active.len() == self.scenes;
        let valid = rows_of(&self.valid, &active, all, v_len);
        let (mut stepped, estimate) = heun_update(
            &rows_of(&self.windows, &active, all, x_len),
            self.agents,
            w,
            &rows_of(sigma_cur, &active, all, w),
            &rows_of(sigma_next, &active, all, w),
            false,
            |x, sigma| denoise(x, sigma, &valid, &active),
        )?;
        multistep_correct(
            &mut stepped,
            &estimate,
            &rows_of(&self.denoised, &active, all, x_len),
            &rows_of(gamma, &active, all, w),
            self.agents,
            w,
        );
        self.put_rows(&active, all, stepped, estimate);
        Ok(())
    }

    /// Stepped windows and their estimate `[active, A, W, 3]` back into the batch: moved in
    /// when every scene stepped, scattered to the active scenes' rows otherwise.
    fn put_rows(&mut self, active: &[usize], all: bool, stepped: Vec<f32>, estimate: Vec<f32>) {
        if all {
            (self.windows, self.denoised) = (stepped, estimate);
        } else {
            let x_len = self.agents * self.slots * 3;
            scatter_rows(&mut self.windows, active, x_len, &stepped);
            scatter_rows(&mut self.denoised, active, x_len, &estimate);
        }
    }
}

/// The rows of scenes `active` of `values` (`len` per scene): borrowed when every scene is
/// active (no copy on the common lockstep path), gathered otherwise.
fn rows_of<'a>(values: &'a [f32], active: &[usize], all: bool, len: usize) -> Cow<'a, [f32]> {
    if all {
        Cow::Borrowed(values)
    } else {
        Cow::Owned(gather_rows(values, active, len))
    }
}

/// The candle reference engine.
#[derive(Debug)]
pub struct CpuEngine<'a> {
    model: &'a Denoiser,
    host: HostWindows,
    /// The static inputs as prepared (`features [B, A, 6]`, `map [B, P, Q, 2]`, `map_valid
    /// [B, P]`), kept so that one scene's can be replaced.
    inputs: StaticInputs,
    /// Their tensors, once prepared.
    tensors: Option<StaticTensors>,
}

/// A batch's static inputs as the candle denoiser takes them.
#[derive(Debug)]
struct StaticTensors {
    features: Tensor,      // [B, A, 6]
    map_tokens: MapTokens, // of map [B, P, Q, 2]
    map_valid: Tensor,     // [B, P]
}

/// A batch's static inputs on the host.
#[derive(Debug, Default)]
struct StaticInputs {
    polylines: usize,
    features: Vec<f32>,
    map: Vec<f32>,
    map_valid: Vec<f32>,
}

impl StaticInputs {
    /// Overwrites scene `scene`'s rows; errors name what does not fit.
    fn replace(
        &mut self,
        scene: usize,
        scenes: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        let per = |all: &[f32]| all.len() / scenes.max(1);
        let (f, m, v) = (per(&self.features), per(&self.map), per(&self.map_valid));
        if scene >= scenes || features.len() != f || map.len() != m || map_valid.len() != v {
            return Err(Error::data(format!(
                "prepare_scene {scene}: {} feature, {} map and {} map-flag values; the batch of \
                 {scenes} scenes takes {f}, {m} and {v} per scene",
                features.len(),
                map.len(),
                map_valid.len()
            )));
        }
        self.features[scene * f..][..f].copy_from_slice(features);
        self.map[scene * m..][..m].copy_from_slice(map);
        self.map_valid[scene * v..][..v].copy_from_slice(map_valid);
        Ok(())
    }
}

impl<'a> CpuEngine<'a> {
    pub fn new(model: &'a Denoiser) -> Self {
        Self {
            model,
            host: HostWindows::default(),
            inputs: StaticInputs::default(),
            tensors: None,
        }
    }

    /// The tensors of the static inputs as they stand.
    fn upload_inputs(&mut self) -> Result<()> {
        let device = Device::Cpu;
        let q = self.model.config.polyline_points;
        let (scenes, agents) = (self.host.scenes, self.host.agents);
        let polylines = self.inputs.polylines;
        let map = Tensor::from_vec(self.inputs.map.clone(), (scenes, polylines, q, 2), &device)?;
        self.tensors = Some(StaticTensors {
            features: Tensor::from_vec(
                self.inputs.features.clone(),
                (scenes, agents, AGENT_FEATURES),
                &device,
            )?,
            map_tokens: self.model.encode_map(&map, Mode::Infer)?,
            map_valid: Tensor::from_vec(
                self.inputs.map_valid.clone(),
                (scenes, polylines),
                &device,
            )?,
        });
        Ok(())
    }
}

/// A denoiser as [`HostWindows`] calls it: `(x, σ, valid, scenes) → D` over the packed rows of
/// `scenes`.
trait DenoiseRows: FnMut(&[f32], &[f32], &[f32], &[usize]) -> Result<Vec<f32>> {}

impl<T: FnMut(&[f32], &[f32], &[f32], &[usize]) -> Result<Vec<f32>>> DenoiseRows for T {}

/// candle's denoiser as [`HostWindows`] calls it: `(x, σ, valid, scenes) → D` over the packed
/// rows of `scenes` (the static inputs gathered when not the whole batch).
fn candle_denoise<'m>(
    model: &'m Denoiser,
    host: &HostWindows,
    tensors: &'m Option<StaticTensors>,
) -> Result<impl DenoiseRows + 'm> {
    let Some(StaticTensors {
        features,
        map_tokens,
        map_valid,
    }) = tensors
    else {
        return Err(not_prepared());
    };
    let (a, w, all) = (host.agents, host.slots, host.scenes);
    Ok(
        move |x: &[f32], sigma: &[f32], valid: &[f32], scenes: &[usize]| {
            let b = scenes.len();
            let device = Device::Cpu;
            // The whole batch as it is; a subset through an index (static inputs gathered).
            let (feats, tokens, map_flags) = if b == all {
                (features.clone(), map_tokens.clone(), map_valid.clone())
            } else {
                let index = Tensor::from_vec(
                    scenes.iter().map(|&s| s as u32).collect::<Vec<_>>(),
                    b,
                    &device,
                )?;
                (
                    features.index_select(&index, 0)?,
                    map_tokens.index_select(&index)?,
                    map_valid.index_select(&index, 0)?,
                )
            };
            Ok(model
                .denoise(
                    &Tensor::from_vec(x.to_vec(), (b, a, w, 3), &device)?,
                    &Tensor::from_vec(sigma.to_vec(), (b, w), &device)?,
                    &Tensor::from_vec(valid.to_vec(), (b, a, w), &device)?,
                    &feats,
                    &tokens,
                    &map_flags,
                    Mode::Infer,
                )?
                .flatten_all()?
                .to_vec1::<f32>()?)
        },
    )
}

/// A step before the batch's static inputs are prepared.
fn not_prepared() -> Error {
    Error::data("engine used before prepare".into())
}

impl StepEngine for CpuEngine<'_> {
    fn window_slots(&self) -> usize {
        self.model.config.window_slots
    }

    fn position_scale_m(&self) -> Option<f64> {
        Some(self.model.config.position_scale_m)
    }

    fn heading_scale(&self) -> Option<f64> {
        Some(self.model.config.heading_scale)
    }

    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        self.host = HostWindows {
            scenes,
            agents,
            slots: self.model.config.window_slots,
            ..HostWindows::default()
        };
        self.inputs = StaticInputs {
            polylines,
            features: features.to_vec(),
            map: map.to_vec(),
            map_valid: map_valid.to_vec(),
        };
        self.upload_inputs()
    }

    fn prepare_scene(
        &mut self,
        scene: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        self.inputs
            .replace(scene, self.host.scenes, features, map, map_valid)?;
        // The reference re-encodes every scene's map: simple, and exact by construction.
        self.upload_inputs()
    }

    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()> {
        self.host.load(windows, valid)
    }

    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()> {
        self.host.load_scene(scene, window, valid)
    }

    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()> {
        let denoise = candle_denoise(self.model, &self.host, &self.tensors)?;
        self.host
            .step(sigma_cur, sigma_next, second_evaluation, denoise)
    }

    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
    ) -> Result<()> {
        let denoise = candle_denoise(self.model, &self.host, &self.tensors)?;
        self.host
            .step_multistep(sigma_cur, sigma_next, gamma, denoise)
    }

    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()> {
        self.host.read_emitted(slots, out)
    }

    fn read_denoised(&mut self, scenes: &[usize], out: &mut [f32]) -> Result<()> {
        self.host.read_denoised(scenes, out)
    }

    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()> {
        self.host.shift(edits, shape)
    }
}

/// The fast CPU engine: [`FastDenoiser`] on the host windows, each evaluation's tokens split
/// across threads kept between calls (so one scene uses every core too).
#[derive(Debug)]
pub struct FastCpuEngine<'a> {
    model: &'a Denoiser,
    fast: FastDenoiser,
    host: HostWindows,
    cache: Option<SceneCache>,
    /// P of the prepared batch.
    polylines: usize,
}

impl<'a> FastCpuEngine<'a> {
    /// `threads` workers per evaluation (the tokens of a batch are split between them);
    /// [`FastCpuEngine::new`] takes the machine's available parallelism.
    pub fn with_threads(model: &'a Denoiser, threads: usize) -> Result<Self> {
        Ok(Self {
            model,
            fast: FastDenoiser::new(model, threads)?,
            host: HostWindows::default(),
            cache: None,
            polylines: 0,
        })
    }

    pub fn new(model: &'a Denoiser) -> Result<Self> {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        Self::with_threads(model, threads)
    }

    /// The fast path's per-scene-set inputs of `scenes` scenes.
    fn scene_cache(
        &self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<SceneCache> {
        let q = self.model.config.polyline_points;
        Ok(if self.model.config.agent_map.is_some() {
            // Each forward picks and encodes every agent's own polylines.
            self.fast.scene_cache(
                scenes,
                agents,
                features,
                SceneMap::Polylines(map),
                map_valid,
            )?
        } else {
            // The scene-frame map encoder runs once per scene set: candle's is fast enough there.
            let map = Tensor::from_vec(map.to_vec(), (scenes, polylines, q, 2), &Device::Cpu)?;
            let tokens = self
                .model
                .encode_polylines(&map, Mode::Infer)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            self.fast.scene_cache(
                scenes,
                agents,
                features,
                SceneMap::Tokens(&tokens),
                map_valid,
            )?
        })
    }
}

/// The fast denoiser as [`HostWindows`] calls it (see [`candle_denoise`]).
fn fast_denoise<'m>(fast: &'m FastDenoiser, cache: &'m SceneCache) -> impl DenoiseRows + 'm {
    move |x, sigma, valid, scenes| {
        let mut out = vec![0.0; x.len()];
        let inputs = FastInputs {
            x,
            sigma,
            valid,
            scene_ids: scenes,
        };
        fast.denoise(cache, &inputs, &mut out)?;
        Ok(out)
    }
}

impl StepEngine for FastCpuEngine<'_> {
    fn window_slots(&self) -> usize {
        self.model.config.window_slots
    }

    fn position_scale_m(&self) -> Option<f64> {
        Some(self.model.config.position_scale_m)
    }

    fn heading_scale(&self) -> Option<f64> {
        Some(self.model.config.heading_scale)
    }

    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        self.host = HostWindows {
            scenes,
            agents,
            slots: self.model.config.window_slots,
            ..HostWindows::default()
        };
        self.cache = Some(self.scene_cache(scenes, agents, features, polylines, map, map_valid)?);
        self.polylines = polylines;
        Ok(())
    }

    fn prepare_scene(
        &mut self,
        scene: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        let agents = self.host.agents;
        let one = self.scene_cache(1, agents, features, self.polylines, map, map_valid)?;
        let Some(cache) = &mut self.cache else {
            return Err(Error::data("prepare_scene before prepare".into()));
        };
        cache.replace_scene(scene, &one)
    }

    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()> {
        self.host.load(windows, valid)
    }

    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()> {
        self.host.load_scene(scene, window, valid)
    }

    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()> {
        let cache = self.cache.as_ref().ok_or_else(not_prepared)?;
        self.host.step(
            sigma_cur,
            sigma_next,
            second_evaluation,
            fast_denoise(&self.fast, cache),
        )
    }

    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
    ) -> Result<()> {
        let cache = self.cache.as_ref().ok_or_else(not_prepared)?;
        self.host.step_multistep(
            sigma_cur,
            sigma_next,
            gamma,
            fast_denoise(&self.fast, cache),
        )
    }

    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()> {
        self.host.read_emitted(slots, out)
    }

    fn read_denoised(&mut self, scenes: &[usize], out: &mut [f32]) -> Result<()> {
        self.host.read_denoised(scenes, out)
    }

    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()> {
        self.host.shift(edits, shape)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two scenes of 2 agents × 3 slots with distinct states and a previous estimate.
    fn windows() -> HostWindows {
        let (scenes, agents, slots) = (2, 2, 3);
        let len = scenes * agents * slots * 3;
        HostWindows {
            scenes,
            agents,
            slots,
            windows: (0..len).map(|v| (v as f32 * 0.37).sin()).collect(),
            valid: vec![1.0; scenes * agents * slots],
            denoised: (0..len).map(|v| (v as f32 * 0.11).cos()).collect(),
        }
    }

    /// A stand-in denoiser that depends on the state, σ and which scenes it sees.
    fn denoise(x: &[f32], sigma: &[f32], _: &[f32], scenes: &[usize]) -> Result<Vec<f32>> {
        let per_scene = x.len() / scenes.len();
        let per_slot = per_scene / (sigma.len() / scenes.len());
        Ok(x.iter()
            .enumerate()
            .map(|(e, v)| {
                let (k, b) = (e / per_scene, e / per_slot);
                0.5 * v + 0.1 * sigma[b % sigma.len()] + 0.01 * scenes[k] as f32
            })
            .collect())
    }

    /// A multistep step of every scene equals the same step taken scene by scene (the
    /// gathered path, the other scene's σ row held), and a held scene stays as it was.
    #[test]
    fn multistep_of_all_scenes_matches_the_gathered_path() {
        let w = 3;
        let cur = [0.0, 2.0, 4.0, 0.0, 1.0, 3.0];
        let next = [0.0, 1.0, 2.0, 0.0, 0.5, 1.5];
        let gamma = [0.0, 0.3, 0.2, 0.0, 0.4, 0.1];
        let mut all = windows();
        all.step_multistep(&cur, &next, &gamma, denoise).unwrap();
        for scene in 0..2 {
            let mut one = windows();
            let before = windows();
            // The other scene's σ row does not change: it is not stepped.
            let mut next_one = cur;
            next_one[scene * w..(scene + 1) * w].copy_from_slice(&next[scene * w..(scene + 1) * w]);
            one.step_multistep(&cur, &next_one, &gamma, denoise)
                .unwrap();
            let len = 2 * w * 3;
            let rows = |h: &HostWindows, b: usize| {
                (
                    h.windows[b * len..(b + 1) * len].to_vec(),
                    h.denoised[b * len..(b + 1) * len].to_vec(),
                )
            };
            assert_eq!(rows(&one, scene), rows(&all, scene), "scene {scene}");
            assert_eq!(rows(&one, 1 - scene), rows(&before, 1 - scene));
        }
    }
}
