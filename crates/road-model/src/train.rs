//! Training: task sampling, EDM loss, AdamW with warm-up + cosine learning rate, gradient
//! clipping, an EMA of the weights, validation, checkpoints and exact resume.
//!
//! Exact resume: every step draws from an RNG seeded by `(seed, step)`, and the checkpoint
//! holds the raw weights and AdamW moments, so continuing from step s repeats what an
//! uninterrupted run would have done.

use std::collections::HashMap;
use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, mpsc};
use std::time::Instant;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng, rngs::StdRng};
use road_data::Dataset;

use crate::batch::{Batch, SceneInput, collate, initialisation_sigma, normal_vec, task_sigma};
use crate::checkpoint::{self, CheckpointMeta, DataIdentity, TRAIN_STATE_FILE, WEIGHTS_FILE};
use crate::config::RunConfig;
use crate::model::{self, Denoiser, Mode};
use crate::{Error, Result};

const ADAM_BETA1: f64 = 0.9;
const ADAM_BETA2: f64 = 0.999;
const ADAM_EPS: f64 = 1e-8;
/// The validation batches' fixed seed (independent of the training seed).
const VALIDATION_SEED: u64 = 0x005E_ED0F_7A11;

/// One optimiser step's figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    pub step: u64,
    pub loss: f64,
    pub learning_rate: f64,
    pub grad_norm: f64,
    pub samples_per_sec: f64,
}

/// What the loop tells its caller.
#[derive(Debug, Clone, PartialEq)]
pub enum TrainEvent {
    Step(StepReport),
    Validation { step: u64, loss: f64 },
    Checkpoint { step: u64, dir: PathBuf },
}

/// Windows grouped by agent count (contiguous count ranges of at least [`Self::MIN_BUCKET`]
/// windows), so that a batch of one bucket pads to similar sizes.
#[derive(Debug, Clone)]
pub struct AgentBuckets {
    bucket_of: Vec<u32>,
    members: Vec<Vec<u32>>,
}

impl AgentBuckets {
    pub const MIN_BUCKET: usize = 256;

    pub fn new(ds: &Dataset) -> Self {
        let counts: Vec<usize> = ds.windows.iter().map(|w| w.agents.len()).collect();
        let max = counts.iter().copied().max().unwrap_or(0);
        let mut by_count = vec![Vec::new(); max + 1];
        for (i, &c) in counts.iter().enumerate() {
            by_count[c].push(i as u32);
        }
        let mut members: Vec<Vec<u32>> = vec![Vec::new()];
        for group in by_count {
            let last = members.last_mut().expect("one bucket at least");
            last.extend(group);
            if last.len() >= Self::MIN_BUCKET {
                members.push(Vec::new());
            }
        }
        // A small remainder joins the bucket before it.
        if members.len() > 1 && members.last().is_some_and(|m| m.len() < Self::MIN_BUCKET) {
            let tail = members.pop().expect("checked");
            members.last_mut().expect("checked").extend(tail);
        }
        let mut bucket_of = vec![0u32; counts.len()];
        for (b, m) in members.iter().enumerate() {
            for &i in m {
                bucket_of[i as usize] = b as u32;
            }
        }
        Self { bucket_of, members }
    }

    pub fn buckets(&self) -> usize {
        self.members.len()
    }

    /// A uniform draw from the bucket of window `anchor`.
    fn pick(&self, anchor: usize, rng: &mut StdRng) -> usize {
        let m = &self.members[self.bucket_of[anchor] as usize];
        m[rng.random_range(0..m.len())] as usize
    }
}

/// The scenes of one batch before padding: collated whole ([`sample_batch`]) or in shards
/// (one per training worker).
#[derive(Debug, Clone)]
pub struct SceneDraw {
    pub inputs: Vec<SceneInput>,
    /// `[scenes][W]` task noise levels, or `[scenes][A_s·W]` per agent (initialisation tasks).
    pub sigma: Vec<Vec<f32>>,
    /// `[scenes][A_s·W·3]` standard normal noise.
    pub noise: Vec<Vec<f32>>,
}

impl SceneDraw {
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.inputs.is_empty()
    }

    /// The scenes `range` as one padded batch.
    pub fn collate(&self, range: Range<usize>, device: &Device) -> Result<Batch> {
        collate(
            &self.inputs[range.clone()],
            &self.sigma[range.clone()],
            Some(&self.noise[range]),
            device,
        )
    }
}

/// Draws `scenes` random windows of `ds`, cropped to the model's window (agents absent from
/// the crop dropped), with the run's task noise; `rng` decides everything. With `buckets`, the
/// first window is uniform and the others uniform within its agent-count bucket (every window
/// keeps the same probability of being drawn).
pub fn sample_scenes(
    run: &RunConfig,
    ds: &Dataset,
    scenes: usize,
    buckets: Option<&AgentBuckets>,
    rng: &mut StdRng,
) -> Result<SceneDraw> {
    let w = run.model.window_slots;
    let steps = ds.config.window_steps;
    if steps < w {
        return Err(Error::data(format!(
            "dataset windows have {steps} steps, the model needs {w}"
        )));
    }
    if ds.is_empty() {
        return Err(Error::data(format!(
            "the {} dataset has no windows",
            ds.split
        )));
    }
    if let Some(b) = buckets {
        if b.bucket_of.len() != ds.len() {
            return Err(Error::data(format!(
                "agent buckets of {} windows for a dataset of {}",
                b.bucket_of.len(),
                ds.len()
            )));
        }
    }
    let mut draw = SceneDraw {
        inputs: Vec::with_capacity(scenes),
        sigma: Vec::with_capacity(scenes),
        noise: Vec::with_capacity(scenes),
    };
    let mut anchor = None;
    for _ in 0..scenes {
        let index = match (buckets, anchor) {
            (Some(b), Some(a)) => b.pick(a, rng),
            _ => rng.random_range(0..ds.len()),
        };
        anchor.get_or_insert(index);
        let window = ds.window(index)?;
        let start = rng.random_range(0..=steps - w);
        let mut input = SceneInput::from_window(&window, start, w, &run.model);
        if run.train.rotation_augmentation {
            let angle_rad = rng.random_range(0.0..std::f32::consts::TAU);
            input.rotate(angle_rad, run.model.heading_scale as f32);
        }
        if let Some(kink) = run.train.kink_augmentation {
            let max_rad = kink.max_deg.to_radians() as f32;
            for agent in 0..input.agents {
                if max_rad > 0.0 && rng.random_bool(kink.prob) {
                    let angle_rad = rng.random_range(-max_rad..=max_rad);
                    input.kink_history(
                        agent,
                        run.planner.obs_slots,
                        angle_rad,
                        run.model.heading_scale as f32,
                    );
                }
            }
        }
        if let Some(noise_m) = run.train.history_noise_m.filter(|&m| m > 0.0) {
            let n = run.planner.obs_slots.min(w);
            let scale = (noise_m / run.model.position_scale_m) as f32;
            let noise: Vec<f32> = normal_vec(rng, input.agents * n * 2)
                .into_iter()
                .map(|z| z * scale)
                .collect();
            input.perturb_history(n, &noise);
        }
        let initialisation = run.train.initialisation_task_prob > 0.0
            && rng.random_bool(run.train.initialisation_task_prob);
        let sigma = (!initialisation).then(|| {
            task_sigma(
                rng,
                &run.model,
                run.planner.obs_slots,
                run.task_kind(),
                run.train.warmup_task_prob,
                run.train.augmentation_ratio,
            )
        });
        let mut eps = normal_vec(rng, input.agents * w * 3);
        input.drop_absent_agents(&mut eps);
        // Per agent, so drawn after absent agents are dropped.
        let sigma = match sigma {
            Some(sigma) => sigma,
            None => initialisation_sigma(
                rng,
                &run.model,
                run.planner.obs_slots,
                run.planner.obs_slots.saturating_sub(1),
                &input.valid,
                run.train.augmentation_ratio,
            ),
        };
        draw.sigma.push(sigma);
        draw.noise.push(eps);
        draw.inputs.push(input);
    }
    Ok(draw)
}

/// [`sample_scenes`] collated into one padded batch.
pub fn sample_batch(
    run: &RunConfig,
    ds: &Dataset,
    scenes: usize,
    buckets: Option<&AgentBuckets>,
    rng: &mut StdRng,
    device: &Device,
) -> Result<Batch> {
    let draw = sample_scenes(run, ds, scenes, buckets, rng)?;
    draw.collate(0..draw.len(), device)
}

/// Splits `scenes` into at most `workers` contiguous, non-empty ranges of near-equal size.
pub fn shard_ranges(scenes: usize, workers: usize) -> Vec<Range<usize>> {
    let shards = workers.clamp(1, scenes.max(1));
    (0..shards)
        .map(|i| i * scenes / shards..(i + 1) * scenes / shards)
        .collect()
}

/// One shard's share of the batch loss (its error sum over the whole batch's count) and the
/// gradients of that share.
fn shard_gradients(model: &Denoiser, batch: &Batch, batch_count: f64) -> Result<ShardGradients> {
    let map_tokens = model.encode_map(&batch.map, Mode::Train)?;
    let (error_sum, _) = model::edm_error_sum(model, batch, &map_tokens, Mode::Train)?;
    let loss = (error_sum / batch_count)?;
    let value = f64::from(loss.to_scalar::<f32>()?);
    Ok((value, loss.backward()?))
}

type ShardGradients = (f64, GradStore);

/// A shard for a worker: the batch and the whole batch's value count.
struct ShardJob {
    batch: Batch,
    batch_count: f64,
}

/// Worker threads that live as long as the trainer: a thread spawned per step would start
/// from a cold allocator arena every step (measured: its forward pass ran at half speed).
/// Shard 0 runs on the caller's thread; worker `i` takes shard `i + 1`.
struct ShardWorkers {
    jobs: Vec<mpsc::Sender<ShardJob>>,
    results: mpsc::Receiver<(usize, Result<ShardGradients>)>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl ShardWorkers {
    fn new(model: &Arc<Denoiser>, count: usize) -> Result<Self> {
        let (result_tx, results) = mpsc::channel();
        let mut jobs = Vec::with_capacity(count);
        let mut threads = Vec::with_capacity(count);
        for index in 0..count {
            let (job_tx, job_rx) = mpsc::channel::<ShardJob>();
            let model = Arc::clone(model);
            let result_tx = result_tx.clone();
            let thread = std::thread::Builder::new()
                .name(format!("train-worker-{}", index + 1))
                .spawn(move || {
                    for job in job_rx {
                        let outcome =
                            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                                shard_gradients(&model, &job.batch, job.batch_count)
                            }))
                            .unwrap_or_else(|panic| {
                                let message = panic
                                    .downcast_ref::<&str>()
                                    .map(|m| (*m).to_owned())
                                    .or_else(|| panic.downcast_ref::<String>().cloned())
                                    .unwrap_or_else(|| "no message".into());
                                Err(Error::Worker {
                                    worker: index + 1,
                                    message,
                                })
                            });
                        if result_tx.send((index, outcome)).is_err() {
                            break;
                        }
                    }
                })
                .map_err(|e| Error::Worker {
                    worker: index + 1,
                    message: format!("cannot start the thread: {e}"),
                })?;
            jobs.push(job_tx);
            threads.push(thread);
        }
        Ok(Self {
            jobs,
            results,
            threads,
        })
    }

    /// Gradients of every shard, in shard order: the first here, the others on the workers.
    fn run(
        &self,
        model: &Denoiser,
        shards: Vec<Batch>,
        batch_count: f64,
    ) -> Result<Vec<ShardGradients>> {
        let mut shards = shards.into_iter();
        let first = shards
            .next()
            .ok_or_else(|| Error::data("a training batch without scenes".into()))?;
        let mut sent = 0;
        let mut send_error = None;
        for (index, batch) in shards.enumerate() {
            let outcome = match self.jobs.get(index) {
                Some(jobs) => jobs
                    .send(ShardJob { batch, batch_count })
                    .map_err(|_| "the thread has stopped".to_owned()),
                None => Err(format!("no worker for shard {}", index + 2)),
            };
            match outcome {
                Ok(()) => sent += 1,
                Err(message) => {
                    send_error = Some(Error::Worker {
                        worker: index + 1,
                        message,
                    });
                    break;
                }
            }
        }
        let first = shard_gradients(model, &first, batch_count);
        // Every job sent is answered before returning, even on an error, so that no result is
        // left behind for the next step.
        let mut others: Vec<Option<Result<ShardGradients>>> = (0..sent).map(|_| None).collect();
        for _ in 0..sent {
            let (index, outcome) = self.results.recv().map_err(|_| Error::Worker {
                worker: 0,
                message: "every worker thread has stopped".into(),
            })?;
            others[index] = Some(outcome);
        }
        if let Some(e) = send_error {
            return Err(e);
        }
        std::iter::once(first)
            .chain(others.into_iter().enumerate().map(|(index, outcome)| {
                outcome.unwrap_or_else(|| {
                    Err(Error::Worker {
                        worker: index + 1,
                        message: "no answer".into(),
                    })
                })
            }))
            .collect()
    }
}

impl Drop for ShardWorkers {
    fn drop(&mut self) {
        self.jobs.clear(); // closes every job channel: the workers' loops end
        for thread in self.threads.drain(..) {
            let _ = thread.join();
        }
    }
}

/// Learning rate at `step`: linear warm-up, then cosine decay to the minimum.
pub fn learning_rate(run: &RunConfig, step: u64) -> f64 {
    let t = &run.train;
    if step < t.warmup_steps {
        return t.learning_rate * (step + 1) as f64 / t.warmup_steps as f64;
    }
    let span = t.steps.saturating_sub(t.warmup_steps).max(1) as f64;
    let progress = ((step - t.warmup_steps) as f64 / span).min(1.0);
    t.min_learning_rate
        + 0.5
            * (t.learning_rate - t.min_learning_rate)
            * (1.0 + (std::f64::consts::PI * progress).cos())
}

/// The run's fixed validation batches: `val_batches` batches of `batch_scenes` scenes drawn
/// from a seed of their own (not the run's), so that every run of a window size validates on
/// the same scenes and noise. Scenes as recorded (no rotation, kinks or history noise), so
/// that losses compare across augmentation settings. `torch_export` writes them for the
/// PyTorch path.
pub fn validation_batches(
    run: &RunConfig,
    validation_set: &Dataset,
    device: &Device,
) -> Result<Vec<Batch>> {
    let mut rng = StdRng::seed_from_u64(VALIDATION_SEED);
    let mut validation_run = run.clone();
    validation_run.train.rotation_augmentation = false;
    validation_run.train.kink_augmentation = None;
    validation_run.train.history_noise_m = None;
    (0..run.train.val_batches)
        .map(|_| {
            sample_batch(
                &validation_run,
                validation_set,
                run.train.batch_scenes,
                None,
                &mut rng,
                device,
            )
        })
        .collect()
}

fn step_rng(seed: u64, step: u64) -> StdRng {
    StdRng::seed_from_u64(seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// The training state of one run.
pub struct Trainer {
    pub run: RunConfig,
    device: Device,
    varmap: VarMap,
    /// Shared with the worker threads (its variables are updated in place between steps).
    model: Arc<Denoiser>,
    /// Variables sorted by name, with their AdamW moments and EMA.
    names: Vec<String>,
    vars: Vec<Var>,
    adam_m: Vec<Tensor>,
    adam_v: Vec<Tensor>,
    ema: Vec<Tensor>,
    pub step: u64,
    wall_secs_before: f64,
    untrained_validation_loss: Option<f64>,
    last_validation_loss: Option<f64>,
    validation: Vec<Batch>,
    data: DataIdentity,
    /// Built from the training set on the first step.
    buckets: Option<AgentBuckets>,
    /// Started on the first step that has more than one shard.
    workers: Option<ShardWorkers>,
}

impl std::fmt::Debug for Trainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("run", &self.run.name)
            .field("step", &self.step)
            .finish_non_exhaustive()
    }
}

impl Trainer {
    /// A fresh run, or the one in `resume_from` continued.
    pub fn new(
        run: RunConfig,
        validation_set: &Dataset,
        data: DataIdentity,
        resume_from: Option<&Path>,
    ) -> Result<Self> {
        let device = Device::Cpu;
        let (varmap, model) = model::init_seeded(&run.model, &device, run.train.seed)?;
        let mut names: Vec<String> = varmap
            .data()
            .lock()
            .expect("var map lock")
            .keys()
            .cloned()
            .collect();
        names.sort();
        let vars: Vec<Var> = {
            let map = varmap.data().lock().expect("var map lock");
            names.iter().map(|n| map[n].clone()).collect()
        };
        let zeros = |v: &Var| Tensor::zeros(v.shape(), DType::F32, &device);
        let adam_m = vars
            .iter()
            .map(zeros)
            .collect::<candle_core::Result<Vec<_>>>()?;
        let adam_v = vars
            .iter()
            .map(zeros)
            .collect::<candle_core::Result<Vec<_>>>()?;
        let ema = vars
            .iter()
            .map(|v| v.as_tensor().detach().copy())
            .collect::<candle_core::Result<Vec<_>>>()?;
        let validation = validation_batches(&run, validation_set, &device)?;
        let mut trainer = Self {
            run,
            device,
            varmap,
            model: Arc::new(model),
            names,
            vars,
            adam_m,
            adam_v,
            ema,
            step: 0,
            wall_secs_before: 0.0,
            untrained_validation_loss: None,
            last_validation_loss: None,
            validation,
            data,
            buckets: None,
            workers: None,
        };
        match resume_from {
            Some(dir) => trainer.restore(dir)?,
            None => {
                if let Some(dir) = trainer.run.train.init_from.clone() {
                    trainer.initialise_from(&dir)?;
                }
                trainer.untrained_validation_loss = Some(trainer.validate()?);
            }
        }
        Ok(trainer)
    }

    pub fn parameter_count(&self) -> usize {
        model::parameter_count(&self.vars)
    }

    pub fn untrained_validation_loss(&self) -> Option<f64> {
        self.untrained_validation_loss
    }

    /// The batch loss of `draw` (mean over its valid values) and its gradient for every
    /// variable (in [`Self::variable_names`] order), with the run's data parallelism: each
    /// worker differentiates its shard's error sum divided by the whole batch's count, so the
    /// shards' losses and gradients add up to the batch's. Shards are summed in a fixed order:
    /// a run stays deterministic.
    pub fn loss_and_gradients(&mut self, draw: &SceneDraw) -> Result<(f64, Vec<Tensor>)> {
        let shards = shard_ranges(draw.len(), self.run.train.workers)
            .into_iter()
            .map(|range| draw.collate(range, &self.device))
            .collect::<Result<Vec<_>>>()?;
        let valid_slots = shards.iter().try_fold(0.0f64, |acc, b| {
            Ok::<_, Error>(acc + f64::from(b.valid.sum_all()?.to_scalar::<f32>()?))
        })?;
        let batch_count = (3.0 * valid_slots).max(1.0);
        let workers_needed = shards.len() - 1;
        if self
            .workers
            .as_ref()
            .is_none_or(|w| w.jobs.len() < workers_needed)
        {
            self.workers = Some(ShardWorkers::new(&self.model, workers_needed)?);
        }
        let workers = self.workers.as_ref().expect("workers were just started");
        let results = workers.run(&self.model, shards, batch_count)?;
        let loss: f64 = results.iter().map(|(value, _)| value).sum();
        let mut gradients = Vec::with_capacity(self.vars.len());
        for var in &self.vars {
            let mut sum: Option<Tensor> = None;
            for (_, grads) in &results {
                if let Some(shard) = grads.get(var.as_tensor()) {
                    sum = Some(match sum {
                        Some(total) => (total + shard)?,
                        None => shard.clone(),
                    });
                }
            }
            gradients.push(match sum {
                Some(g) => g,
                None => var.as_tensor().zeros_like()?,
            });
        }
        Ok((loss, gradients))
    }

    /// The variables' names, sorted (the order of [`Self::loss_and_gradients`]).
    pub fn variable_names(&self) -> &[String] {
        &self.names
    }

    /// One optimiser step on a fresh batch.
    pub fn train_step(&mut self, train_set: &Dataset) -> Result<StepReport> {
        let started = Instant::now();
        let mut rng = step_rng(self.run.train.seed, self.step);
        if self.run.train.bucket_by_agents
            && self
                .buckets
                .as_ref()
                .is_none_or(|b| b.bucket_of.len() != train_set.len())
        {
            self.buckets = Some(AgentBuckets::new(train_set));
        }
        let buckets = self
            .buckets
            .as_ref()
            .filter(|_| self.run.train.bucket_by_agents);
        let draw = sample_scenes(
            &self.run,
            train_set,
            self.run.train.batch_scenes,
            buckets,
            &mut rng,
        )?;
        let (loss_value, grad_list) = self.loss_and_gradients(&draw)?;
        if !loss_value.is_finite() {
            return Err(Error::Diverged {
                step: self.step,
                loss: loss_value,
            });
        }
        let (grad_norm, lr) = self.apply_gradients(&grad_list)?;
        let secs = started.elapsed().as_secs_f64();
        Ok(StepReport {
            step: self.step,
            loss: loss_value,
            learning_rate: lr,
            grad_norm,
            samples_per_sec: self.run.train.batch_scenes as f64 / secs.max(1e-9),
        })
    }

    /// One optimiser step with the given gradients (one per variable, in
    /// [`Self::variable_names`] order): clipping by the global norm, AdamW (decoupled weight
    /// decay, bias-corrected moments, ε added to the root), the EMA update, the step count.
    /// Returns the gradient norm before clipping and the learning rate used.
    pub fn apply_gradients(&mut self, grad_list: &[Tensor]) -> Result<(f64, f64)> {
        if grad_list.len() != self.vars.len() {
            return Err(Error::data(format!(
                "{} gradients for {} variables",
                grad_list.len(),
                self.vars.len()
            )));
        }
        // Global gradient norm, for clipping.
        let mut sq = 0.0f64;
        for g in grad_list {
            sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
        }
        let grad_norm = sq.sqrt();
        let clip = if grad_norm > self.run.train.grad_clip {
            self.run.train.grad_clip / grad_norm
        } else {
            1.0
        };
        let lr = learning_rate(&self.run, self.step);
        let t = (self.step + 1) as i32;
        let (bc1, bc2) = (1.0 - ADAM_BETA1.powi(t), 1.0 - ADAM_BETA2.powi(t));
        let wd = self.run.train.weight_decay;
        let ema_decay = self.run.train.ema_decay;
        for (i, var) in self.vars.iter().enumerate() {
            let g = (&grad_list[i] * clip)?;
            let m = ((&self.adam_m[i] * ADAM_BETA1)? + (&g * (1.0 - ADAM_BETA1))?)?;
            let v = ((&self.adam_v[i] * ADAM_BETA2)? + (g.sqr()? * (1.0 - ADAM_BETA2))?)?;
            let p = var.as_tensor().detach();
            let update = ((&m / bc1)? / ((&v / bc2)?.sqrt()? + ADAM_EPS)?)?;
            let p = ((&p * (1.0 - lr * wd))? - (update * lr)?)?;
            var.set(&p)?;
            self.ema[i] = ((&self.ema[i] * ema_decay)? + (&p * (1.0 - ema_decay))?)?;
            self.adam_m[i] = m;
            self.adam_v[i] = v;
        }
        self.step += 1;
        Ok((grad_norm, lr))
    }

    /// A model built from the EMA weights.
    pub fn ema_model(&self) -> Result<Denoiser> {
        let tensors: HashMap<String, Tensor> = self
            .names
            .iter()
            .cloned()
            .zip(self.ema.iter().cloned())
            .collect();
        Denoiser::new(
            &self.run.model,
            VarBuilder::from_tensors(tensors, DType::F32, &self.device),
        )
    }

    /// Mean loss of the EMA weights over the fixed validation batches.
    pub fn validate(&mut self) -> Result<f64> {
        let model = self.ema_model()?;
        let mut total = 0.0;
        for batch in &self.validation {
            let map_tokens = model.encode_map(&batch.map, Mode::Infer)?;
            total += f64::from(
                model::edm_loss(&model, batch, &map_tokens, Mode::Infer)?.to_scalar::<f32>()?,
            );
        }
        let loss = total / self.validation.len().max(1) as f64;
        self.last_validation_loss = Some(loss);
        Ok(loss)
    }

    /// Writes the checkpoint folder (EMA weights, train state, config).
    pub fn save(&self, dir: &Path, wall_secs: f64, hardware: &str) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let ema: HashMap<String, Tensor> = self
            .names
            .iter()
            .cloned()
            .zip(self.ema.iter().cloned())
            .collect();
        checkpoint::save_tensors(&ema, &dir.join(WEIGHTS_FILE))?;
        let mut state = HashMap::new();
        for (i, name) in self.names.iter().enumerate() {
            state.insert(format!("param.{name}"), self.vars[i].as_tensor().detach());
            state.insert(format!("adam_m.{name}"), self.adam_m[i].clone());
            state.insert(format!("adam_v.{name}"), self.adam_v[i].clone());
        }
        checkpoint::save_tensors(&state, &dir.join(TRAIN_STATE_FILE))?;
        CheckpointMeta {
            run: self.run.clone(),
            data: self.data.clone(),
            step: self.step,
            parameters: self.parameter_count(),
            wall_secs: self.wall_secs_before + wall_secs,
            hardware: hardware.to_owned(),
            validation_loss: self.last_validation_loss,
            untrained_validation_loss: self.untrained_validation_loss,
        }
        .save(dir)
    }

    /// `train.init_from`: the weights (and their EMA) of another checkpoint. Tensors the
    /// checkpoint lacks (a part this config adds, e.g. `agent_pairs`) keep their
    /// initialisation; they are logged. Returns their names.
    fn initialise_from(&mut self, dir: &Path) -> Result<Vec<String>> {
        let path = dir.join(WEIGHTS_FILE);
        let mut weights = checkpoint::load_tensors(&path, &self.device)?;
        fit_slot_embedding(&mut weights, self.run.model.window_slots, &path)?;
        let fresh = checkpoint::check_fit(&self.varmap, &weights, &path)?;
        for (i, name) in self.names.iter().enumerate() {
            if let Some(w) = weights.get(name) {
                self.vars[i].set(w)?;
                self.ema[i] = w.copy()?;
            } else if is_residual_branch_output(name) {
                // A block the checkpoint lacks starts as the identity: its residual branches
                // add zero until training moves their output projections.
                let zero = self.vars[i].as_tensor().zeros_like()?;
                self.vars[i].set(&zero)?;
                self.ema[i] = zero;
            }
        }
        if !fresh.is_empty() {
            tracing::info!(
                from = %path.display(),
                "tensors the checkpoint lacks start from their initialisation: {}",
                fresh.join(", ")
            );
        }
        Ok(fresh)
    }

    fn restore(&mut self, dir: &Path) -> Result<()> {
        let meta = CheckpointMeta::load(dir)?;
        if meta.run.model != self.run.model || meta.run.planner != self.run.planner {
            return Err(Error::Checkpoint {
                path: dir.join(checkpoint::META_FILE),
                reason: "the checkpoint's model or planner differs from the run's config".into(),
            });
        }
        let path = dir.join(TRAIN_STATE_FILE);
        let state = checkpoint::load_tensors(&path, &self.device)?;
        let ema_path = dir.join(WEIGHTS_FILE);
        let ema = checkpoint::load_tensors(&ema_path, &self.device)?;
        checkpoint::check_against(&self.varmap, &ema, &ema_path)?;
        let get = |key: String| {
            state.get(&key).cloned().ok_or_else(|| Error::Checkpoint {
                path: path.clone(),
                reason: format!("missing tensor `{key}`"),
            })
        };
        for (i, name) in self.names.iter().enumerate() {
            self.vars[i].set(&get(format!("param.{name}"))?)?;
            self.adam_m[i] = get(format!("adam_m.{name}"))?;
            self.adam_v[i] = get(format!("adam_v.{name}"))?;
            self.ema[i] = ema[name].clone();
        }
        self.step = meta.step;
        self.wall_secs_before = meta.wall_secs;
        self.untrained_validation_loss = meta.untrained_validation_loss;
        self.last_validation_loss = meta.validation_loss;
        Ok(())
    }

    /// Trains until `until_step` (or the config's step count), validating, logging to
    /// `dir/train_log.csv` and checkpointing into `dir` as configured.
    pub fn run_until(
        &mut self,
        train_set: &Dataset,
        dir: &Path,
        until_step: u64,
        hardware: &str,
        mut on_event: impl FnMut(&TrainEvent),
    ) -> Result<()> {
        let started = Instant::now();
        let mut last_checkpoint = Instant::now();
        let log_path = dir.join("train_log.csv");
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let fresh_log = !log_path.exists();
        if !fresh_log {
            // A resumed run drops the rows logged after its checkpoint: they are redone.
            let text = std::fs::read_to_string(&log_path).map_err(|e| Error::io(&log_path, e))?;
            let kept: String = text
                .lines()
                .enumerate()
                .filter(|(i, line)| {
                    *i == 0
                        || line
                            .split(',')
                            .next()
                            .and_then(|s| s.parse::<u64>().ok())
                            .is_some_and(|s| s <= self.step)
                })
                .map(|(_, line)| format!("{line}\n"))
                .collect();
            checkpoint::write_atomic(&log_path, kept.as_bytes())?;
        }
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(|e| Error::io(&log_path, e))?;
        let mut write_log = |line: String| {
            log.write_all(line.as_bytes())
                .map_err(|e| Error::io(&log_path, e))
        };
        if fresh_log {
            write_log(
                "step,loss,learning_rate,grad_norm,samples_per_sec,validation_loss,wall_secs\n"
                    .into(),
            )?;
            if let Some(v) = self.untrained_validation_loss {
                write_log(format!("0,,,,,{v},0\n"))?;
            }
        }
        let until = until_step.min(self.run.train.steps);
        while self.step < until {
            let report = self.train_step(train_set)?;
            on_event(&TrainEvent::Step(report));
            let wall = self.wall_secs_before + started.elapsed().as_secs_f64();
            let mut val = String::new();
            if self
                .step
                .is_multiple_of(self.run.train.val_every_steps.max(1))
                || self.step == until
            {
                let loss = self.validate()?;
                on_event(&TrainEvent::Validation {
                    step: self.step,
                    loss,
                });
                val = loss.to_string();
            }
            write_log(format!(
                "{},{},{},{},{:.2},{},{:.1}\n",
                report.step,
                report.loss,
                report.learning_rate,
                report.grad_norm,
                report.samples_per_sec,
                val,
                wall
            ))?;
            if last_checkpoint.elapsed().as_secs() >= self.run.train.checkpoint_every_secs
                || self.step == until
            {
                self.save(dir, started.elapsed().as_secs_f64(), hardware)?;
                last_checkpoint = Instant::now();
                on_event(&TrainEvent::Checkpoint {
                    step: self.step,
                    dir: dir.to_owned(),
                });
            }
        }
        Ok(())
    }
}

/// `train.init_from` across planners whose windows differ (RoAD-20's W = 20 into AR's 11 or
/// DJINN's 40): the slot embedding `[W', D]` keeps its first `min(W, W')` rows, and each slot
/// past the checkpoint's window starts as its last (future) slot, which training then tells
/// apart. Every other tensor is independent of W.
fn fit_slot_embedding(
    weights: &mut HashMap<String, Tensor>,
    window_slots: usize,
    path: &Path,
) -> Result<()> {
    const NAME: &str = "slot_embedding";
    let Some(embedding) = weights.get(NAME) else {
        return Ok(());
    };
    let (from_slots, _d) = embedding.dims2()?;
    if from_slots == window_slots {
        return Ok(());
    }
    let kept = embedding.narrow(0, 0, from_slots.min(window_slots))?;
    let fitted = if window_slots > from_slots {
        let last = embedding.narrow(0, from_slots - 1, 1)?;
        let repeated = last.repeat((window_slots - from_slots, 1))?;
        Tensor::cat(&[&kept, &repeated], 0)?
    } else {
        kept
    };
    tracing::info!(
        from = %path.display(),
        "the slot embedding of a {from_slots}-slot window fitted to {window_slots} slots"
    );
    weights.insert(NAME.to_owned(), fitted);
    Ok(())
}

/// Whether `name` is the output projection of one of a block's residual branches (time,
/// agent and map attention, the MLP): zero there makes a new block the identity, so that a
/// run that adds blocks (`train.init_from` from a shallower checkpoint) starts as the model
/// it comes from.
fn is_residual_branch_output(name: &str) -> bool {
    let Some(rest) = name.strip_prefix("blocks.") else {
        return false;
    };
    let Some((_, tensor)) = rest.split_once('.') else {
        return false;
    };
    matches!(
        tensor,
        "time.o.weight"
            | "time.o.bias"
            | "agents.o.weight"
            | "agents.o.bias"
            | "map.o.weight"
            | "map.o.bias"
            | "mlp_out.weight"
            | "mlp_out.bias"
    )
}

#[cfg(test)]
mod tests {
    use road_data::{Split, WindowConfig, WindowRef};

    use super::*;

    /// A dataset whose windows have the given agent counts (nothing else is read).
    fn windows_with(counts: &[usize]) -> Dataset {
        let mut ds = Dataset::from_parts(
            Split::Train,
            &WindowConfig::default(),
            vec![],
            vec![],
            vec![],
        )
        .unwrap();
        ds.windows = counts
            .iter()
            .map(|&c| WindowRef {
                recording: 0,
                start_frame: 0,
                origin_m: [0.0, 0.0],
                agents: (0..c as u32).collect(),
                polylines: vec![],
            })
            .collect();
        ds
    }

    #[test]
    fn agent_buckets_partition_the_windows_by_count_ranges() {
        // Skewed like the data: many small scenes, few large ones.
        let counts: Vec<usize> = (0..5000).map(|i| 2 + (i * i) % 29 / (1 + i % 3)).collect();
        let ds = windows_with(&counts);
        let b = AgentBuckets::new(&ds);
        assert!(b.buckets() >= 3, "{} buckets", b.buckets());
        let mut seen = vec![0u32; counts.len()];
        let mut ranges = Vec::new();
        for (k, m) in b.members.iter().enumerate() {
            assert!(
                m.len() >= AgentBuckets::MIN_BUCKET,
                "bucket {k}: {}",
                m.len()
            );
            let lo = m.iter().map(|&i| counts[i as usize]).min().unwrap();
            let hi = m.iter().map(|&i| counts[i as usize]).max().unwrap();
            ranges.push((lo, hi));
            for &i in m {
                seen[i as usize] += 1;
                assert_eq!(b.bucket_of[i as usize] as usize, k);
            }
        }
        assert!(
            seen.iter().all(|&s| s == 1),
            "every window in exactly one bucket"
        );
        // Contiguous, non-overlapping count ranges in order.
        for pair in ranges.windows(2) {
            assert!(pair[0].1 < pair[1].0, "{ranges:?}");
        }
        // A draw stays in its anchor's bucket.
        let mut rng = StdRng::seed_from_u64(1);
        for anchor in [0usize, 17, 4999] {
            for _ in 0..50 {
                let i = b.pick(anchor, &mut rng);
                assert_eq!(b.bucket_of[i], b.bucket_of[anchor]);
            }
        }
        // Fewer windows than a bucket: one bucket.
        assert_eq!(AgentBuckets::new(&windows_with(&[2, 5, 9])).buckets(), 1);
    }
}
