//! The DJINN-style denoiser: one token per agent and window slot, blocks of time attention,
//! agent attention, map cross-attention and an MLP; EDM preconditioning per slot.
//!
//! Tensor names used in the checkpoint (see `docs/checkpoint.md`) follow the module paths
//! below, e.g. `blocks.0.time.q.weight`.

use candle_core::{DType, Module, Tensor};
use candle_nn::{LayerNorm, Linear, VarBuilder, layer_norm, linear};

use crate::Result;
use crate::batch::AGENT_FEATURES;
use crate::config::ModelConfig;

/// Additive attention bias for masked keys: exp(−1e9) is exactly 0 in f32, so a masked key
/// has no influence at all.
const MASKED: f64 = -1e9;
const LN_EPS: f64 = 1e-5;

/// Training needs differentiable ops; inference may use candle's fused kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Train,
    Infer,
}

fn norm(ln: &LayerNorm, x: &Tensor, mode: Mode) -> Result<Tensor> {
    Ok(match mode {
        Mode::Infer => ln.forward(&x.contiguous()?)?,
        Mode::Train => {
            let bias = ln.bias().expect("layer norms carry a bias");
            crate::fused::layer_norm(x, ln.weight(), bias, LN_EPS as f32)?
        }
    })
}

/// A linear layer over the last dimension as one `[N, D_in] × [D_in, D_out]` product.
/// candle's `Linear` on a 4-D input broadcasts the weight into a batched product, whose
/// backward materialises and reduces a per-batch weight gradient: several times slower.
fn lin(layer: &Linear, x: &Tensor) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let d_in = dims[dims.len() - 1];
    let rows = x.elem_count() / d_in;
    let y = layer.forward(&x.reshape((rows, d_in))?)?; // [N, D_out]
    let mut out_dims = dims;
    let last = out_dims.len() - 1;
    out_dims[last] = y.dim(1)?;
    Ok(y.reshape(out_dims)?)
}

fn softmax(x: &Tensor, mode: Mode) -> Result<Tensor> {
    Ok(match mode {
        Mode::Infer => candle_nn::ops::softmax_last_dim(x)?,
        Mode::Train => crate::fused::softmax_last_dim(x)?,
    })
}

/// One attention layer's weights (public for the other engines, which read them: `road-cpu`).
#[derive(Debug)]
pub struct Attention {
    pub q: Linear,
    pub k: Linear,
    pub v: Linear,
    pub o: Linear,
    pub heads: usize,
    /// Agent attention with [`crate::config::AgentPairs`]: the key and value offsets' weights.
    pub pairs: Option<PairWeights>,
}

/// The key offset `pair_k · r` and value offset `pair_v · r` of a pair's features `r`, both
/// `[D, F]` (head h owns rows h·dh…). Zero at initialisation, so that a model that gains them
/// (`train.init_from`) starts as the one it comes from.
#[derive(Debug)]
pub struct PairWeights {
    pub k: Tensor,
    pub v: Tensor,
}

impl Attention {
    fn new(d: usize, heads: usize, pair_features: Option<usize>, vb: VarBuilder) -> Result<Self> {
        let pairs = match pair_features {
            Some(f) => Some(PairWeights {
                k: vb.get_with_hints((d, f), "pair_k", candle_nn::Init::Const(0.0))?,
                v: vb.get_with_hints((d, f), "pair_v", candle_nn::Init::Const(0.0))?,
            }),
            None => None,
        };
        Ok(Self {
            q: linear(d, d, vb.pp("q"))?,
            k: linear(d, d, vb.pp("k"))?,
            v: linear(d, d, vb.pp("v"))?,
            o: linear(d, d, vb.pp("o"))?,
            heads,
            pairs,
        })
    }

    /// `xq [N, Lq, D]`, `xkv [N, Lk, D]`, `key_bias [N, 1, 1, Lk]`, with pair weights the
    /// pairs' features `pair_features [N, Lq, Lk, F]` → `[N, Lq, D]`. Per head h and pair
    /// (i, j): score `q_i · (k_j + K_h r_ij) / √dh`, value `v_j + V_h r_ij`; both offsets are
    /// linear in `r`, so they cost `F` (not `dh`) per pair: `q_i · K_h r_ij = (K_hᵀ q_i) · r_ij`
    /// and `Σ_j a_ij V_h r_ij = V_h Σ_j a_ij r_ij`.
    fn forward(
        &self,
        xq: &Tensor,
        xkv: &Tensor,
        key_bias: &Tensor,
        pair_features: Option<&Tensor>,
        mode: Mode,
    ) -> Result<Tensor> {
        let (n, lq, d) = xq.dims3()?;
        let lk = xkv.dim(1)?;
        let h = self.heads;
        let dh = d / h;
        let split = |t: Tensor, l: usize| -> Result<Tensor> {
            Ok(t.reshape((n, l, h, dh))?.transpose(1, 2)?.contiguous()?)
        };
        // Scaling q rather than the scores: the scores are the largest tensor here.
        let q = split((lin(&self.q, xq)? * (1.0 / (dh as f64).sqrt()))?, lq)?; // [N, H, Lq, dh]
        let k = split(lin(&self.k, xkv)?, lk)?; // [N, H, Lk, dh]
        let v = split(lin(&self.v, xkv)?, lk)?; // [N, H, Lk, dh]
        let mut scores = q.matmul(&k.t()?)?; // [N, H, Lq, Lk]
        let pairs = match (&self.pairs, pair_features) {
            (Some(w), Some(r)) => {
                let f = r.dim(3)?;
                let r = r.reshape((n * lq, lk, f))?; // [N·Lq, Lk, F]
                let q_pair = q
                    .transpose(0, 1)?
                    .reshape((h, n * lq, dh))?
                    .matmul(&w.k.reshape((h, dh, f))?)? // [H, N·Lq, F]
                    .transpose(0, 1)?
                    .contiguous()?; // [N·Lq, H, F]
                let pair_scores = q_pair
                    .matmul(&r.t()?)? // [N·Lq, H, Lk]
                    .reshape((n, lq, h, lk))?
                    .transpose(1, 2)?; // [N, H, Lq, Lk]
                scores = (scores + pair_scores)?;
                Some((w, r, f))
            }
            (None, None) => None,
            _ => {
                return Err(crate::Error::data(
                    "pair features go with pair weights (agent attention of an agent_pairs model)"
                        .into(),
                ));
            }
        };
        let attn = softmax(&scores.broadcast_add(key_bias)?, mode)?;
        let mut out = attn.matmul(&v)?; // [N, H, Lq, dh]
        if let Some((w, r, f)) = pairs {
            let mean_pair = attn
                .transpose(1, 2)?
                .contiguous()?
                .reshape((n * lq, h, lk))?
                .matmul(&r)? // [N·Lq, H, F]: Σ_j a_ij r_ij
                .transpose(0, 1)?
                .contiguous()?; // [H, N·Lq, F]
            let value_offsets = mean_pair
                .matmul(&w.v.reshape((h, dh, f))?.transpose(1, 2)?)? // [H, N·Lq, dh]
                .reshape((h, n, lq, dh))?
                .transpose(0, 1)?; // [N, H, Lq, dh]
            out = (out + value_offsets)?;
        }
        let out = out.transpose(1, 2)?.reshape((n, lq, d))?; // [N, Lq, D]
        lin(&self.o, &out)
    }
}

/// One transformer block's weights.
#[derive(Debug)]
pub struct Block {
    pub ln_time: LayerNorm,
    pub time: Attention,
    pub ln_agents: LayerNorm,
    pub agents: Attention,
    pub ln_map: LayerNorm,
    pub map: Attention,
    pub ln_mlp: LayerNorm,
    pub mlp_in: Linear,
    pub mlp_out: Linear,
}

impl Block {
    fn new(c: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let d = c.hidden;
        Ok(Self {
            ln_time: layer_norm(d, LN_EPS, vb.pp("ln_time"))?,
            time: Attention::new(d, c.heads, None, vb.pp("time"))?,
            ln_agents: layer_norm(d, LN_EPS, vb.pp("ln_agents"))?,
            agents: Attention::new(
                d,
                c.heads,
                c.agent_pairs
                    .as_ref()
                    .map(|_| crate::agent_pairs::PAIR_FEATURES),
                vb.pp("agents"),
            )?,
            ln_map: layer_norm(d, LN_EPS, vb.pp("ln_map"))?,
            map: Attention::new(d, c.heads, None, vb.pp("map"))?,
            ln_mlp: layer_norm(d, LN_EPS, vb.pp("ln_mlp"))?,
            mlp_in: linear(d, d * c.mlp_ratio, vb.pp("mlp_in"))?,
            mlp_out: linear(d * c.mlp_ratio, d, vb.pp("mlp_out"))?,
        })
    }

    /// `h [B, A, W, D]`; biases from [`Masks`]; the map keys of [`MapKeys`]; with agent pairs
    /// their features `[B·W, A, A, F]`.
    fn forward(
        &self,
        h: &Tensor,
        m: &Masks,
        map: &MapKeys,
        pair_features: Option<&Tensor>,
        mode: Mode,
    ) -> Result<Tensor> {
        let (b, a, w, d) = h.dims4()?;
        // Time attention within each agent: [B·A, W, D].
        let x = norm(&self.ln_time, h, mode)?.reshape((b * a, w, d))?;
        let h = (h + self
            .time
            .forward(&x, &x, &m.time_bias, None, mode)?
            .reshape((b, a, w, d))?)?;
        // Agent attention within each slot: [B·W, A, D].
        let x = norm(&self.ln_agents, &h, mode)?
            .transpose(1, 2)?
            .contiguous()?
            .reshape((b * w, a, d))?;
        let y = self
            .agents
            .forward(&x, &x, &m.agent_bias, pair_features, mode)?
            .reshape((b, w, a, d))?
            .transpose(1, 2)?;
        let h = (h + y)?;
        // Cross-attention to the map: [B, A·W, D] → [B, P, D] (the scene's tokens), or
        // [B·A, W, D] → [B·A, K, D] (each agent's own).
        let x = norm(&self.ln_map, &h, mode)?;
        let x = if map.per_agent {
            x.reshape((b * a, w, d))?
        } else {
            x.reshape((b, a * w, d))?
        };
        let h = (h + self
            .map
            .forward(&x, &map.tokens, &map.bias, None, mode)?
            .reshape((b, a, w, d))?)?;
        let x = norm(&self.ln_mlp, &h, mode)?;
        let y = lin(&self.mlp_out, &lin(&self.mlp_in, &x)?.relu()?)?;
        Ok((h + y)?)
    }
}

/// σ per slot `[B, W]` as `[B, 1, W, 1]`, or σ per agent and slot `[B, A, W]` as
/// `[B, A, W, 1]`: the shapes that broadcast against `[B, A, W, ·]` tokens.
fn sigma_per_token(sigma: &Tensor) -> Result<Tensor> {
    Ok(match *sigma.dims() {
        [b, w] => sigma.reshape((b, 1, w, 1))?,
        [b, a, w] => sigma.reshape((b, a, w, 1))?,
        _ => {
            return Err(crate::Error::data(format!(
                "σ of shape {:?}: [B, W] or [B, A, W]",
                sigma.dims()
            )));
        }
    })
}

/// `valid [B, A, W]` with the anchor slot cleared where that slot's σ (`sigma` `[B, W]` or
/// `[B, A, W]`) exceeds `max_sigma`: the flags every anchor computation reads
/// (`AgentFrame::max_anchor_sigma`).
fn anchor_flags(valid: &Tensor, sigma: &Tensor, slot: usize, max_sigma: f64) -> Result<Tensor> {
    let (b, a, w) = valid.dims3()?;
    let at_anchor = sigma_per_token(sigma)?.narrow(2, slot, 1)?; // [B, 1|A, 1, 1]
    let trusted = at_anchor
        .le(max_sigma)?
        .to_dtype(valid.dtype())?
        .reshape((b, at_anchor.dim(1)?, 1))?
        .broadcast_as((b, a, 1))?;
    let anchor = (valid.narrow(2, slot, 1)? * trusted)?;
    let mut parts = Vec::with_capacity(3);
    if slot > 0 {
        parts.push(valid.narrow(2, 0, slot)?);
    }
    parts.push(anchor);
    if slot + 1 < w {
        parts.push(valid.narrow(2, slot + 1, w - slot - 1)?);
    }
    Ok(Tensor::cat(&parts, 2)?)
}

/// The additive attention bias of validity flags: 0 where valid, [`MASKED`] where not.
fn key_bias(flags: &Tensor) -> Result<Tensor> {
    Ok(((flags - 1.0)? * -MASKED)?)
}

/// Attention biases built once per forward.
#[derive(Debug)]
struct Masks {
    time_bias: Tensor,  // [B·A, 1, 1, W]
    agent_bias: Tensor, // [B·W, 1, 1, A]
}

impl Masks {
    fn new(valid: &Tensor) -> Result<Self> {
        let (b, a, w) = valid.dims3()?;
        Ok(Self {
            time_bias: key_bias(valid)?.reshape((b * a, 1, 1, w))?,
            agent_bias: key_bias(&valid.transpose(1, 2)?.contiguous()?)?.reshape((
                b * w,
                1,
                1,
                a,
            ))?,
        })
    }
}

/// What the map cross-attention attends to, as [`Denoiser::encode_map`] prepares it once per
/// scene set.
#[derive(Debug, Clone)]
pub enum MapTokens {
    /// One token per polyline in the scene frame, shared by every agent: `[B, P, D]`.
    Scene(Tensor),
    /// With [`crate::config::AgentMap`]: the polylines themselves (`[B, P, Q, 2]`, scene
    /// frame); each forward picks and encodes every agent's own from its anchor.
    PerAgent(Tensor),
}

impl MapTokens {
    /// The rows `index` (scenes) of the map.
    pub fn index_select(&self, index: &Tensor) -> Result<Self> {
        Ok(match self {
            Self::Scene(t) => Self::Scene(t.index_select(index, 0)?),
            Self::PerAgent(t) => Self::PerAgent(t.index_select(index, 0)?),
        })
    }
}

/// The keys of one forward's map cross-attention and their bias: the scene's
/// (`tokens [B, P, D]`, `bias [B, 1, 1, P]`) or, `per_agent`, each agent's own
/// (`[B·A, K, D]`, `[B·A, 1, 1, K]`).
#[derive(Debug)]
struct MapKeys {
    tokens: Tensor,
    bias: Tensor,
    per_agent: bool,
}

/// The denoiser `D(x; σ)`. Its weights are public for the engines that run it outside candle
/// (`road-cpu`'s fast path copies them into its own buffers).
#[derive(Debug)]
pub struct Denoiser {
    pub config: ModelConfig,
    pub embed_state: Linear,
    pub embed_noise: Linear,
    pub embed_agent: Linear,
    /// With an agent frame: relative (x, y, heading), the anchor's validity and, with a
    /// constant-velocity reference, the last observed step → D.
    pub embed_relative: Option<Linear>,
    pub slot_embedding: Tensor, // [W, D]
    pub map_point: Linear,
    pub map_point_embedding: Tensor, // [Q, D]
    pub map_mix: Linear,
    pub ln_map_out: LayerNorm,
    pub blocks: Vec<Block>,
    pub ln_out: LayerNorm,
    pub head: Linear,
}

impl Denoiser {
    pub fn new(config: &ModelConfig, vb: VarBuilder) -> Result<Self> {
        let d = config.hidden;
        let init = candle_nn::Init::Randn {
            mean: 0.0,
            stdev: 0.02,
        };
        Ok(Self {
            embed_state: linear(3, d, vb.pp("embed_state"))?,
            embed_noise: linear(1, d, vb.pp("embed_noise"))?,
            embed_agent: linear(AGENT_FEATURES, d, vb.pp("embed_agent"))?,
            embed_relative: match &config.agent_frame {
                Some(frame) => Some(linear(
                    frame.relative_features(),
                    d,
                    vb.pp("embed_relative"),
                )?),
                None => None,
            },
            slot_embedding: vb.get_with_hints((config.window_slots, d), "slot_embedding", init)?,
            map_point: linear(2, d, vb.pp("map_point"))?,
            map_point_embedding: vb.get_with_hints(
                (config.polyline_points, d),
                "map_point_embedding",
                init,
            )?,
            map_mix: linear(d, d, vb.pp("map_mix"))?,
            ln_map_out: layer_norm(d, LN_EPS, vb.pp("ln_map_out"))?,
            blocks: (0..config.blocks)
                .map(|i| Block::new(config, vb.pp(format!("blocks.{i}"))))
                .collect::<Result<_>>()?,
            ln_out: layer_norm(d, LN_EPS, vb.pp("ln_out"))?,
            head: linear(d, 3, vb.pp("head"))?,
            config: config.clone(),
        })
    }

    /// Whether agent attention carries pair weights (`agent_pairs`).
    pub fn blocks_have_agent_pairs(&self) -> bool {
        !self.blocks.is_empty() && self.blocks.iter().all(|b| b.agents.pairs.is_some())
    }

    /// Map tokens, once per scene set: `map [B, P, Q, 2]` → scene-frame tokens `[B, P, D]`,
    /// or, with an agent map, the polylines kept for each forward to pick from.
    pub fn encode_map(&self, map: &Tensor, mode: Mode) -> Result<MapTokens> {
        Ok(match self.config.agent_map {
            None => MapTokens::Scene(self.encode_polylines(map, mode)?),
            Some(_) => MapTokens::PerAgent(map.clone()),
        })
    }

    /// The polyline encoder: `points [N, P, Q, 2]` → `[N, P, D]` (per-point MLP, max-pool).
    pub fn encode_polylines(&self, points: &Tensor, mode: Mode) -> Result<Tensor> {
        let x = lin(&self.map_point, points)?
            .broadcast_add(&self.map_point_embedding)?
            .relu()?; // [N, P, Q, D]
        let x = lin(&self.map_mix, &x)?.max(2)?; // [N, P, D]
        norm(&self.ln_map_out, &x, mode)
    }

    /// Each agent's own map tokens (`[B·A, K, D]`) and their bias (`[B·A, 1, 1, K]`), from the
    /// anchors of the noisy input `x [B, A, W, 3]` and the scene's polylines
    /// `map [B, P, Q, 2]`, `map_valid [B, P]`.
    #[allow(clippy::too_many_arguments)]
    fn agent_map_keys(
        &self,
        x: &Tensor,
        valid: &Tensor,
        anchor_slot: usize,
        map: &Tensor,
        map_valid: &Tensor,
        polylines: usize,
        mode: Mode,
    ) -> Result<MapKeys> {
        let (b, a, w, _) = x.dims4()?;
        let (_, _, q, _) = map.dims4()?;
        let anchors = crate::agent_map::anchors_of(
            &x.flatten_all()?.to_vec1::<f32>()?,
            &valid.flatten_all()?.to_vec1::<f32>()?,
            w,
            anchor_slot,
            self.config.heading_scale as f32,
        );
        let (points, valid) = crate::agent_map::agent_maps(
            &anchors,
            a,
            &map.flatten_all()?.to_vec1::<f32>()?,
            &map_valid.flatten_all()?.to_vec1::<f32>()?,
            q,
            polylines,
        );
        let k = valid.len() / (b * a).max(1);
        let device = map.device();
        let points = Tensor::from_vec(points, (b * a, k, q, 2), device)?;
        let valid = Tensor::from_vec(valid, (b * a, 1, 1, k), device)?;
        Ok(MapKeys {
            tokens: self.encode_polylines(&points, mode)?,
            bias: key_bias(&valid)?,
            per_agent: true,
        })
    }

    /// The agent pairs' features of noisy windows `x [B, A, W, 3]`: `[B·W, A, A, F]`.
    fn pair_features(
        &self,
        x: &Tensor,
        valid: &Tensor,
        pairs: &crate::config::AgentPairs,
        frame: &AnchorFrame,
    ) -> Result<Tensor> {
        let (b, a, w, _) = x.dims4()?;
        let x_host = x.flatten_all()?.to_vec1::<f32>()?;
        let anchors = crate::agent_map::anchors_of(
            &x_host,
            &valid.flatten_all()?.to_vec1::<f32>()?,
            w,
            frame.anchor_slot,
            self.config.heading_scale as f32,
        );
        let scales = crate::agent_pairs::PairScales::new(
            pairs,
            self.config.position_scale_m,
            self.config.heading_scale,
        );
        let features = crate::agent_pairs::pair_features_of(&x_host, &anchors, a, w, scales);
        let f = crate::agent_pairs::PAIR_FEATURES;
        Ok(Tensor::from_vec(features, (b * w, a, a, f), x.device())?)
    }

    /// `D(x; σ)`: `x_noisy [B, A, W, 3]`, `sigma [B, W]` or per agent `[B, A, W]` (> 0),
    /// `valid [B, A, W]`, `agent_features [B, A, 6]`, `map_tokens` of [`Self::encode_map`],
    /// `map_valid [B, P]` → `[B, A, W, 3]`.
    #[allow(clippy::too_many_arguments)]
    pub fn denoise(
        &self,
        x_noisy: &Tensor,
        sigma: &Tensor,
        valid: &Tensor,
        agent_features: &Tensor,
        map_tokens: &MapTokens,
        map_valid: &Tensor,
        mode: Mode,
    ) -> Result<Tensor> {
        let out = self.forward(
            x_noisy,
            sigma,
            valid,
            agent_features,
            map_tokens,
            map_valid,
            mode,
        )?;
        match &out.residual {
            None => {
                let (c_skip, c_out, _, _) = self.preconditioning(sigma)?;
                Ok((x_noisy.broadcast_mul(&c_skip)? + out.raw.broadcast_mul(&c_out)?)?)
            }
            // D = reference + (c_skip(σ·s)·y + c_out(σ·s)·F) / s, with y = s·(x − reference).
            Some(r) => {
                let y = (r.y.broadcast_mul(&r.c_skip)? + out.raw.broadcast_mul(&r.c_out)?)?;
                Ok((&r.reference + y.broadcast_div(&r.scale)?)?)
            }
        }
    }

    /// EDM coefficients of `sigma [B, W]` (or `[B, A, W]`) as `[B, 1, W, 1]` (`[B, A, W, 1]`)
    /// tensors: (c_skip, c_out, c_in, c_noise).
    pub fn preconditioning(&self, sigma: &Tensor) -> Result<(Tensor, Tensor, Tensor, Tensor)> {
        let sigma = sigma_per_token(sigma)?;
        let (c_skip, c_out, c_in) = self.skip_out_in(&sigma)?;
        let c_noise = (sigma.log()? * 0.25)?;
        Ok((c_skip, c_out, c_in, c_noise))
    }

    /// EDM's c_skip, c_out and c_in of a σ tensor of any shape.
    fn skip_out_in(&self, sigma: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
        let sd = self.config.edm.sigma_data;
        let denom = (sigma.sqr()? + sd * sd)?; // σ² + σd²
        let root = denom.sqrt()?;
        let c_skip = (denom.recip()? * (sd * sd))?;
        let c_out = ((sigma * sd)? / &root)?;
        let c_in = root.recip()?;
        Ok((c_skip, c_out, c_in))
    }

    /// The network `F` before preconditioning (`[B, A, W, 3]`, in the scene frame's
    /// orientation) and, with a constant-velocity reference, the terms that turn it into `D`.
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &self,
        x_noisy: &Tensor,
        sigma: &Tensor,
        valid: &Tensor,
        agent_features: &Tensor,
        map_tokens: &MapTokens,
        map_valid: &Tensor,
        mode: Mode,
    ) -> Result<NetworkOutput> {
        let w = x_noisy.dim(2)?;
        let d = self.config.hidden;
        let (_, _, c_in, c_noise) = self.preconditioning(sigma)?;
        // Invalid tokens carry zeros in, so that nothing of theirs leaks even before masking.
        let valid4 = valid.unsqueeze(3)?; // [B, A, W, 1]
        let x_in = x_noisy.broadcast_mul(&c_in)?.broadcast_mul(&valid4)?;
        let h = lin(&self.embed_state, &x_in)?; // [B, A, W, D]
        let noise = lin(&self.embed_noise, &c_noise)?; // [B, 1, W, D]
        let agent = lin(&self.embed_agent, agent_features)?.unsqueeze(2)?; // [B, A, 1, D]
        let slots = self.slot_embedding.reshape((1, 1, w, d))?;
        let mut h = h
            .broadcast_add(&noise)?
            .broadcast_add(&agent)?
            .broadcast_add(&slots)?;
        let mut residual = None;
        // The flags anchors are read with: `valid`, less the anchors still too noisy.
        let anchor_valid = match &self.config.agent_frame {
            Some(spec) => match spec.max_anchor_sigma {
                Some(max_sigma) => anchor_flags(valid, sigma, spec.anchor_slot, max_sigma)?,
                None => valid.clone(),
            },
            None => valid.clone(),
        };
        let frame = match (&self.config.agent_frame, &self.embed_relative) {
            (Some(spec), Some(embed)) => {
                let frame = AnchorFrame::new(
                    x_noisy,
                    &anchor_valid,
                    spec.anchor_slot,
                    self.config.heading_scale,
                    spec.residual_scale.is_some(),
                )?;
                let rel = match spec.residual_scale {
                    None => {
                        let scale = (c_in * spec.relative_scale)?.broadcast_mul(&valid4)?;
                        frame.relative_features(&x_noisy.broadcast_sub(&frame.anchor)?, &scale)?
                    }
                    Some(s) => {
                        let r = frame.residual(x_noisy, sigma, s, self)?;
                        let scale = (&r.c_in * spec.relative_scale)?.broadcast_mul(&valid4)?;
                        let rel = frame.relative_features(&r.y, &scale)?; // [B, A, W, 4]
                        let step = frame.step_features(s, w)?; // [B, A, W, 2]
                        residual = Some(r);
                        Tensor::cat(&[rel, step], 3)?
                    }
                };
                h = (h + lin(embed, &rel)?)?;
                Some(frame)
            }
            _ => None,
        };
        let masks = Masks::new(valid)?;
        let map = match (map_tokens, &self.config.agent_map, &self.config.agent_frame) {
            (MapTokens::Scene(tokens), None, _) => {
                let (b, p) = map_valid.dims2()?;
                MapKeys {
                    tokens: tokens.clone(),
                    bias: key_bias(map_valid)?.reshape((b, 1, 1, p))?,
                    per_agent: false,
                }
            }
            (MapTokens::PerAgent(points), Some(spec), Some(frame)) => self.agent_map_keys(
                x_noisy,
                &anchor_valid,
                frame.anchor_slot,
                points,
                map_valid,
                spec.polylines,
                mode,
            )?,
            _ => {
                return Err(crate::Error::data(
                    "map tokens of another model: encode the map with this model's encode_map"
                        .into(),
                ));
            }
        };
        let pair_features = match (&self.config.agent_pairs, &frame) {
            (Some(pairs), Some(frame)) => {
                Some(self.pair_features(x_noisy, &anchor_valid, pairs, frame)?)
            }
            _ => None,
        };
        for block in &self.blocks {
            h = block.forward(&h, &masks, &map, pair_features.as_ref(), mode)?;
        }
        let out = lin(&self.head, &norm(&self.ln_out, &h, mode)?)?; // [B, A, W, 3]
        let out = match &frame {
            Some(frame) => frame.rotate_to_scene(&out)?,
            None => out,
        };
        Ok(NetworkOutput {
            raw: out.broadcast_mul(&valid4)?,
            residual,
        })
    }
}

/// What [`Denoiser::forward`] returns.
struct NetworkOutput {
    /// `F [B, A, W, 3]`, zero at invalid tokens.
    raw: Tensor,
    residual: Option<Residual>,
}

/// The constant-velocity reference of `AgentFrame::residual_scale` and its preconditioning.
/// Agents not valid at the anchor keep the plain scene-frame denoiser (reference 0, scale 1).
#[derive(Debug)]
struct Residual {
    reference: Tensor, // [B, A, W, 3]
    scale: Tensor,     // [B, A, 1, 1]: s, or 1 without an anchor
    y: Tensor,         // [B, A, W, 3]: scale · (x − reference)
    c_skip: Tensor,    // [B, A, W, 1] at σ·scale
    c_out: Tensor,     // [B, A, W, 1]
    c_in: Tensor,      // [B, A, W, 1]
}

/// Each agent's anchor pose (its state at the anchor slot, in the noisy input): the frame of
/// `ModelConfig::agent_frame`. An agent not valid at the anchor slot keeps the scene frame.
#[derive(Debug)]
struct AnchorFrame {
    anchor: Tensor,       // [B, A, 1, 3] anchor state (zero where not valid)
    anchor_valid: Tensor, // [B, A, 1, 1]
    cos: Tensor,          // [B, A, 1, 1] of the anchor heading
    sin: Tensor,          // [B, A, 1, 1]
    /// The last observed step, anchor − (anchor − 1), positions only (heading 0); zero unless
    /// both slots are valid. Only with a constant-velocity reference. `[B, A, 1, 3]`
    step: Option<Tensor>,
    anchor_slot: usize,
}

impl AnchorFrame {
    fn new(
        x: &Tensor,
        valid: &Tensor,
        slot: usize,
        heading_scale: f64,
        with_step: bool,
    ) -> Result<Self> {
        let anchor_valid = valid.narrow(2, slot, 1)?.unsqueeze(3)?; // [B, A, 1, 1]
        let anchor = x.narrow(2, slot, 1)?.broadcast_mul(&anchor_valid)?; // [B, A, 1, 3]
        let heading_rad = (anchor.narrow(3, 2, 1)? / heading_scale)?;
        let step = if with_step {
            let both = (valid.narrow(2, slot - 1, 1)?.unsqueeze(3)? * &anchor_valid)?;
            let delta = (x.narrow(2, slot, 1)? - x.narrow(2, slot - 1, 1)?)?;
            let positions = delta.narrow(3, 0, 2)?.broadcast_mul(&both)?;
            Some(Tensor::cat(&[positions, both.zeros_like()?], 3)?)
        } else {
            None
        };
        Ok(Self {
            cos: heading_rad.cos()?,
            sin: heading_rad.sin()?,
            anchor,
            anchor_valid,
            step,
            anchor_slot: slot,
        })
    }

    /// `d [B, A, W, 3]` (a displacement from the anchor) rotated into its heading, times
    /// `scale [B, A, W, 1]`; the anchor's validity as a fourth feature: `[B, A, W, 4]`.
    fn relative_features(&self, d: &Tensor, scale: &Tensor) -> Result<Tensor> {
        let (dx, dy, dh) = (d.narrow(3, 0, 1)?, d.narrow(3, 1, 1)?, d.narrow(3, 2, 1)?);
        let forward = (dx.broadcast_mul(&self.cos)? + dy.broadcast_mul(&self.sin)?)?;
        let left = (dy.broadcast_mul(&self.cos)? - dx.broadcast_mul(&self.sin)?)?;
        let scale = scale.broadcast_mul(&self.anchor_valid)?;
        let flag = self.anchor_valid.broadcast_as(dh.shape())?;
        Ok(Tensor::cat(
            &[
                (forward * &scale)?,
                (left * &scale)?,
                (dh * &scale)?,
                flag.contiguous()?,
            ],
            3,
        )?)
    }

    /// The last observed step in the anchor's heading, times `scale` (40: metres per step),
    /// the same for every slot: `[B, A, W, 2]`.
    fn step_features(&self, scale: f64, w: usize) -> Result<Tensor> {
        let step = self
            .step
            .as_ref()
            .expect("a residual frame carries its step");
        let (dx, dy) = (step.narrow(3, 0, 1)?, step.narrow(3, 1, 1)?);
        let forward = (dx.broadcast_mul(&self.cos)? + dy.broadcast_mul(&self.sin)?)?;
        let left = (dy.broadcast_mul(&self.cos)? - dx.broadcast_mul(&self.sin)?)?;
        let (b, a, _, _) = step.dims4()?;
        Ok((Tensor::cat(&[forward, left], 3)? * scale)?
            .broadcast_as((b, a, w, 2))?
            .contiguous()?)
    }

    /// The constant-velocity reference of `x [B, A, W, 3]` at noise `sigma [B, W]` or `[B, A, W]`.
    fn residual(
        &self,
        x: &Tensor,
        sigma: &Tensor,
        residual_scale: f64,
        model: &Denoiser,
    ) -> Result<Residual> {
        let (_, _, w, _) = x.dims4()?;
        let step = self
            .step
            .as_ref()
            .expect("a residual frame carries its step");
        let offsets: Vec<f32> = (0..w)
            .map(|slot| slot as f32 - self.anchor_slot as f32)
            .collect();
        let offsets = Tensor::from_vec(offsets, (1, 1, w, 1), x.device())?;
        let reference = self.anchor.broadcast_add(&step.broadcast_mul(&offsets)?)?;
        let scale = ((&self.anchor_valid * (residual_scale - 1.0))? + 1.0)?;
        let y = (x - &reference)?.broadcast_mul(&scale)?;
        let sigma_y = sigma_per_token(sigma)?.broadcast_mul(&scale)?; // [B, A, W, 1]
        let (c_skip, c_out, c_in) = model.skip_out_in(&sigma_y)?;
        Ok(Residual {
            reference,
            scale,
            y,
            c_skip,
            c_out,
            c_in,
        })
    }

    /// `f [B, A, W, 3]` from the anchor frame back to the scene frame (heading unchanged).
    fn rotate_to_scene(&self, f: &Tensor) -> Result<Tensor> {
        let (f0, f1, f2) = (f.narrow(3, 0, 1)?, f.narrow(3, 1, 1)?, f.narrow(3, 2, 1)?);
        let x = (f0.broadcast_mul(&self.cos)? - f1.broadcast_mul(&self.sin)?)?;
        let y = (f0.broadcast_mul(&self.sin)? + f1.broadcast_mul(&self.cos)?)?;
        Ok(Tensor::cat(&[x, y, f2], 3)?)
    }
}

/// The EDM training loss: `λ(σ)·|D − x0|²`, averaged over valid agent-slots. Returns a scalar
/// tensor.
pub fn edm_loss(
    model: &Denoiser,
    batch: &crate::batch::Batch,
    map_tokens: &MapTokens,
    mode: Mode,
) -> Result<Tensor> {
    let (error_sum, count) = edm_error_sum(model, batch, map_tokens, mode)?;
    Ok(error_sum.div(&count.maximum(1.0)?)?)
}

/// The EDM loss's numerator and denominator: the squared error summed over valid
/// agent-slots, and the number of values summed (3 per valid agent-slot). Scalar tensors.
///
/// Written on `F` so that no cancellation of `D − x0` enters at small σ: without a reference
/// `λ(σ)·|D − x0|² = |F − (x0 − c_skip·x)/c_out|²`; with one (`D = r + (c_skip'·y + c_out'·F)/s`,
/// coefficients at σ·s) it is `λ(σ)·(c_out'/s)²·|F − (s·(x0 − r) − c_skip'·y)/c_out'|²`: the
/// same objective in the scene frame's units, so validation losses stay comparable.
pub fn edm_error_sum(
    model: &Denoiser,
    batch: &crate::batch::Batch,
    map_tokens: &MapTokens,
    mode: Mode,
) -> Result<(Tensor, Tensor)> {
    let out = model.forward(
        &batch.x_noisy,
        &batch.sigma,
        &batch.valid,
        &batch.agent_features,
        map_tokens,
        &batch.map_valid,
        mode,
    )?;
    let valid4 = batch.valid.unsqueeze(3)?;
    let err = match &out.residual {
        None => {
            let (c_skip, c_out, _, _) = model.preconditioning(&batch.sigma)?;
            let target =
                (&batch.x0 - batch.x_noisy.broadcast_mul(&c_skip)?)?.broadcast_div(&c_out)?;
            (out.raw - target)?.sqr()?
        }
        Some(r) => {
            let x0 = (&batch.x0 - &r.reference)?.broadcast_mul(&r.scale)?;
            let target = (x0 - r.y.broadcast_mul(&r.c_skip)?)?.broadcast_div(&r.c_out)?;
            let sd = model.config.edm.sigma_data;
            let s2 = sigma_per_token(&batch.sigma)?.sqr()?;
            let lambda = ((&s2 + sd * sd)? / (s2 * (sd * sd))?)?; // [B, 1|A, W, 1]
            let weight = r
                .c_out
                .broadcast_div(&r.scale)?
                .sqr()?
                .broadcast_mul(&lambda)?; // [B, A, W, 1]
            (out.raw - target)?.sqr()?.broadcast_mul(&weight)?
        }
    };
    let err = err.broadcast_mul(&valid4)?;
    let count = (batch.valid.sum_all()? * 3.0)?;
    Ok((err.sum_all()?, count))
}

/// The number of scalar parameters of a config (for model cards and FLOP counts).
pub fn parameter_count(vars: &[candle_core::Var]) -> usize {
    vars.iter().map(|v| v.elem_count()).sum()
}

/// A model with its variables (candle's unseeded initialisation; see [`init_seeded`]).
pub fn init(
    config: &ModelConfig,
    device: &candle_core::Device,
) -> Result<(candle_nn::VarMap, Denoiser)> {
    let varmap = candle_nn::VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let model = Denoiser::new(config, vb)?;
    Ok((varmap, model))
}

/// A fresh model whose weights depend only on `seed` (candle cannot seed its CPU RNG):
/// linear weights Kaiming-normal (fan-in, ReLU gain), linear biases uniform ±1/√fan_in,
/// layer norms 1 and 0, learned embeddings N(0, 0.02²).
pub fn init_seeded(
    config: &ModelConfig,
    device: &candle_core::Device,
    seed: u64,
) -> Result<(candle_nn::VarMap, Denoiser)> {
    use rand::{Rng, SeedableRng};
    let (varmap, model) = init(config, device)?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let vars = varmap.data().lock().expect("var map lock");
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    for name in names {
        let var = &vars[name];
        let dims = var.dims().to_vec();
        let n = var.elem_count();
        let leaf = name.rsplit('.').nth(1).unwrap_or("");
        let values: Vec<f32> = if name.ends_with(".pair_k") || name.ends_with(".pair_v") {
            // Zero: a model that gains agent pairs starts as the one it comes from.
            vec![0.0; n]
        } else if leaf.starts_with("ln_") {
            vec![if name.ends_with(".weight") { 1.0 } else { 0.0 }; n]
        } else if name.ends_with(".weight") {
            let std = (2.0 / dims[1] as f64).sqrt();
            crate::batch::normal_vec(&mut rng, n)
                .into_iter()
                .map(|z| (f64::from(z) * std) as f32)
                .collect()
        } else if name.ends_with(".bias") {
            let weight = &vars[&name.replace(".bias", ".weight")];
            let bound = 1.0 / (weight.dims()[1] as f64).sqrt();
            (0..n)
                .map(|_| rng.random_range(-bound..bound) as f32)
                .collect()
        } else {
            crate::batch::normal_vec(&mut rng, n)
                .into_iter()
                .map(|z| z * 0.02)
                .collect()
        };
        var.set(&Tensor::from_vec(values, dims, device)?)?;
    }
    drop(vars);
    Ok((varmap, model))
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::AnchorFrame;

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    /// One scene, two agents, three slots; the anchor is slot 1. Agent 0 heads along +y
    /// (π/2) from (1, 2); agent 1 is not valid at the anchor slot.
    fn frame() -> (Tensor, AnchorFrame) {
        let heading_scale = 0.25;
        let up = std::f32::consts::FRAC_PI_2 * heading_scale;
        #[rustfmt::skip]
        let x = Tensor::from_vec(
            vec![
                1.0, 1.0, up,   1.0, 2.0, up,   1.0, 3.0, up + 0.1,
                5.0, 5.0, 0.3,  9.0, 9.0, 0.0,  6.0, 5.0, 0.3,
            ],
            (1, 2, 3, 3),
            &Device::Cpu,
        )
        .unwrap();
        let valid =
            Tensor::from_vec(vec![1f32, 1., 1., 1., 0., 1.], (1, 2, 3), &Device::Cpu).unwrap();
        let frame = AnchorFrame::new(&x, &valid, 1, f64::from(heading_scale), true).unwrap();
        (x, frame)
    }

    #[test]
    fn relative_features_put_the_anchor_heading_along_x() {
        let (x, frame) = frame();
        let scale = Tensor::full(2f32, (1, 2, 3, 1), &Device::Cpu).unwrap();
        let d = x.broadcast_sub(&frame.anchor).unwrap();
        let rel = values(&frame.relative_features(&d, &scale).unwrap()); // [1, 2, 3, 4]
        let agent0 = &rel[..12];
        // One unit behind, at the anchor, one unit ahead (heading +0.1), all scaled by 2.
        let want0 = [-2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 0.0, 0.2, 1.0];
        for (got, want) in agent0.iter().zip(want0) {
            assert!(
                (got - want).abs() < 1e-5,
                "agent 0: {agent0:?} against {want0:?}"
            );
        }
        // No anchor: every relative feature and the flag are zero.
        assert!(
            rel[12..].iter().all(|&v| v == 0.0),
            "agent 1: {:?}",
            &rel[12..]
        );
    }

    /// The constant-velocity reference: agent 0 moves one unit along +y per slot, so its
    /// reference is its own path and only the heading change at slot 2 is left as residual;
    /// agent 1 has no anchor and keeps the scene frame (reference 0, scale 1).
    #[test]
    fn the_residual_is_the_deviation_from_constant_velocity() {
        let (x, frame) = frame();
        let model = crate::model::init(
            &crate::ModelConfig {
                hidden: 8,
                heads: 2,
                blocks: 1,
                window_slots: 3,
                ..crate::ModelConfig::default()
            },
            &Device::Cpu,
        )
        .unwrap()
        .1;
        let sigma = Tensor::from_vec(vec![0.002f32, 0.1, 1.0], (1, 3), &Device::Cpu).unwrap();
        let r = frame.residual(&x, &sigma, 40.0, &model).unwrap();
        let y = values(&r.y);
        let want0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0];
        for (got, want) in y[..9].iter().zip(want0) {
            assert!((got - want).abs() < 1e-4, "agent 0: {:?}", &y[..9]);
        }
        assert_eq!(values(&r.scale), [40.0, 1.0]);
        assert_eq!(&values(&r.reference)[9..], [0.0; 9]);
        assert_eq!(&y[9..], &values(&x)[9..]);
        // Agent 0 is preconditioned at σ·40, agent 1 at σ.
        let c_in = values(&r.c_in);
        let want_c_in = |s: f32| 1.0 / (s * s + 0.25).sqrt();
        assert!((c_in[1] - want_c_in(4.0)).abs() < 1e-6);
        assert!((c_in[4] - want_c_in(0.1)).abs() < 1e-6);
        // The step features: one unit along the anchor heading, in metres at scale 40.
        let step = values(&frame.step_features(40.0, 3).unwrap());
        assert!(
            (step[0] - 40.0).abs() < 1e-4 && step[1].abs() < 1e-4,
            "{step:?}"
        );
        assert!(step[6..].iter().all(|&v| v == 0.0), "{step:?}");
    }

    #[test]
    fn output_turns_back_to_the_scene_frame() {
        let (_, frame) = frame();
        let forward =
            Tensor::from_vec([1f32, 0.0, 0.5].repeat(6), (1, 2, 3, 3), &Device::Cpu).unwrap();
        let out = values(&frame.rotate_to_scene(&forward).unwrap());
        // Agent 0's forward is the scene's +y; agent 1 keeps the scene frame.
        for (token, got) in out.chunks(3).enumerate() {
            let want = if token < 3 {
                [0.0, 1.0, 0.5]
            } else {
                [1.0, 0.0, 0.5]
            };
            for (g, w) in got.iter().zip(want) {
                assert!(
                    (g - w).abs() < 1e-6,
                    "token {token}: {got:?} against {want:?}"
                );
            }
        }
    }
}
