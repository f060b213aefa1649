//! The weights buffer: every tensor a checkpoint's forward pass reads, at aligned offsets in
//! one buffer. On upload the layer norms before a linear layer are folded into its weights,
//! projections that read the same input are stacked into one layer (q/k/v; the map's k/v, also
//! of every block at once), and the residual chains get their layers transposed, in the order
//! they run them, so that each chain binds one short range. Under f16 each layer's weight is
//! there as f16 too.

use std::collections::HashMap;

use road_model::ModelConfig;

use super::fits_chain;
use crate::kernels::linear_f16::to_f16_bytes;
use crate::kernels::residual_chain::transpose;
use crate::kernels::upload;
use crate::{Error, GpuContext, Result};

/// A tensor's place in the weights buffer (bytes).
#[derive(Debug, Clone, Copy)]
pub(super) struct Slice {
    pub(super) offset: u64,
    pub(super) size: u64,
}

/// The packed map k, v projections of every block: `[blocks · 2 · D, D]`, block by block.
pub(super) const MAP_KV_ALL: &str = "packed.map_kv_all";

/// A residual chain's copy of a layer: its weight transposed (`[in, out]`), its bias.
pub(super) const CHAIN_WEIGHT: &str = "chain_weight";
pub(super) const CHAIN_BIAS: &str = "chain_bias";

/// A layer's weight as f16 (`{layer}.weight.f16`), under [`crate::Precision::F16`].
pub(super) const F16_WEIGHT: &str = "f16";

/// The layers the residual chains run, in the order they run them (the weights buffer's
/// order): per block time attention's q, k, v and output, the agents', the map's q and output,
/// the MLP; then the head.
fn chain_order(blocks: usize) -> Vec<String> {
    let mut layers = Vec::new();
    for i in 0..blocks {
        for layer in [
            "time.qkv",
            "time.o",
            "agents.qkv",
            "agents.o",
            "map.q",
            "map.o",
            "mlp_in",
            "mlp_out",
        ] {
            layers.push(format!("blocks.{i}.{layer}"));
        }
    }
    layers.push("head".to_string());
    layers
}

/// Every tensor the forward pass reads, in one buffer, and each one's place in it by name
/// (checkpoint names, `packed.*` for the stacked ones, `{layer}.chain_weight` and
/// `{layer}.chain_bias` for the chains' copies).
pub(super) fn lay_out(
    ctx: &GpuContext,
    config: &ModelConfig,
    tensors: &HashMap<String, Vec<f32>>,
) -> Result<(wgpu::Buffer, HashMap<String, Slice>)> {
    let get = |name: &str| -> Result<&Vec<f32>> {
        tensors
            .get(name)
            .ok_or_else(|| Error::Checkpoint(format!("missing tensor `{name}`")))
    };
    // Packed small tensors the embedding kernels read from one binding.
    let mut packed: Vec<(String, Vec<f32>)> = Vec::new();
    let mut embed_parts = vec![
        get("embed_state.weight")?,
        get("embed_state.bias")?,
        get("embed_noise.weight")?,
        get("embed_noise.bias")?,
        get("slot_embedding")?,
    ];
    if config.agent_frame.is_some() {
        embed_parts.extend([get("embed_relative.weight")?, get("embed_relative.bias")?]);
    }
    let embed: Vec<f32> = embed_parts.into_iter().flatten().copied().collect();
    packed.push(("packed.embed".into(), embed));
    let map_points: Vec<f32> = [
        get("map_point.weight")?,
        get("map_point.bias")?,
        get("map_point_embedding")?,
    ]
    .into_iter()
    .flatten()
    .copied()
    .collect();
    packed.push(("packed.map_points".into(), map_points));
    // Projections that read the same input run as one layer (`Fused::part`): q, k, v of
    // each self-attention, k, v of each map attention, weights [parts·D, D] and biases
    // stacked. Their own tensors are then not uploaded.
    let mut stacked = std::collections::HashSet::new();
    // Layer norms before a linear layer are folded into its weights (the kernel's `norm`
    // prologue only standardises the rows): the folded layers replace theirs, and the
    // norms' own tensors are not uploaded.
    let mut normed: Vec<(String, &str)> = vec![("ln_out".into(), "head")];
    for i in 0..config.blocks {
        for (norm, layer) in [
            ("ln_time", "time.q"),
            ("ln_time", "time.k"),
            ("ln_time", "time.v"),
            ("ln_agents", "agents.q"),
            ("ln_agents", "agents.k"),
            ("ln_agents", "agents.v"),
            ("ln_map", "map.q"),
            ("ln_mlp", "mlp_in"),
        ] {
            normed.push((format!("blocks.{i}.{norm}"), layer));
        }
    }
    let mut folded: HashMap<String, Vec<f32>> = HashMap::new();
    for (norm, layer) in &normed {
        // `head` is global, the rest per block (`blocks.{i}.ln_time` → `blocks.{i}.time.q`).
        let layer = match norm.rsplit_once('.') {
            Some((block, _)) => format!("{block}.{layer}"),
            None => layer.to_string(),
        };
        let (w, b) = crate::kernels::linear::fold_layer_norm(
            get(&format!("{layer}.weight"))?,
            get(&format!("{layer}.bias"))?,
            get(&format!("{norm}.weight"))?,
            get(&format!("{norm}.bias"))?,
        );
        folded.insert(format!("{layer}.weight"), w);
        folded.insert(format!("{layer}.bias"), b);
        stacked.insert(format!("{norm}.weight"));
        stacked.insert(format!("{norm}.bias"));
    }
    let get = |name: &str| -> Result<&Vec<f32>> { folded.get(name).map_or_else(|| get(name), Ok) };
    for i in 0..config.blocks {
        for (group, name, parts) in [
            ("time", "qkv", &["q", "k", "v"][..]),
            ("agents", "qkv", &["q", "k", "v"][..]),
            ("map", "kv", &["k", "v"][..]),
        ] {
            for kind in ["weight", "bias"] {
                let mut values = Vec::new();
                for part in parts {
                    let tensor = format!("blocks.{i}.{group}.{part}.{kind}");
                    values.extend_from_slice(get(&tensor)?);
                    stacked.insert(tensor);
                }
                packed.push((format!("blocks.{i}.{group}.{name}.{kind}"), values));
            }
        }
    }

    // The map's k, v of every block as one layer too (`map_kv_all`): their keys do not
    // depend on the block, so one dispatch per evaluation projects them all.
    for kind in ["weight", "bias"] {
        let mut values = Vec::new();
        for i in 0..config.blocks {
            for part in ["k", "v"] {
                values.extend_from_slice(get(&format!("blocks.{i}.map.{part}.{kind}"))?);
            }
        }
        packed.push((format!("{MAP_KV_ALL}.{kind}"), values));
    }

    // Every tensor at a 16-byte boundary at least: the chains read weights as vec4.
    let align = u64::from(ctx.device.limits().min_storage_buffer_offset_alignment).max(16);
    let mut blob: Vec<u8> = Vec::new();
    let mut slices = HashMap::new();
    let mut laid: Vec<(String, &Vec<f32>)> = tensors
        .keys()
        .filter(|n| !stacked.contains(*n))
        .map(|n| (n.clone(), folded.get(n).unwrap_or(&tensors[n])))
        .chain(packed.iter().map(|(n, v)| (n.clone(), v)))
        .collect();
    laid.sort_by(|a, b| a.0.cmp(&b.0));
    // The residual chains' layers, transposed, in the order the chains run them: each
    // chain binds the one short range that holds its layers (`weight_range`).
    let chain_tensors = if fits_chain(config) {
        let by_name: HashMap<&str, &Vec<f32>> =
            laid.iter().map(|(n, v)| (n.as_str(), *v)).collect();
        let mut chain_tensors = Vec::new();
        for layer in chain_order(config.blocks) {
            let [w, b] = [format!("{layer}.weight"), format!("{layer}.bias")].map(|name| {
                by_name
                    .get(name.as_str())
                    .copied()
                    .ok_or_else(|| Error::Checkpoint(format!("missing tensor `{name}`")))
            });
            let (w, b) = (w?, b?);
            chain_tensors.push((format!("{layer}.{CHAIN_WEIGHT}"), transpose(w, b.len())));
            chain_tensors.push((format!("{layer}.{CHAIN_BIAS}"), b.clone()));
        }
        chain_tensors
    } else {
        Vec::new()
    };
    let laid = chain_tensors
        .iter()
        .map(|(n, v)| (n.clone(), v))
        .chain(laid);
    let f16 = ctx.precision() == crate::Precision::F16;
    for (name, values) in laid {
        // Under f16 every layer's weights also as f16 (`{name}.f16`), which the f16 kernels
        // bind instead (`F16_WEIGHT`); the chains' copies are never run in f16.
        let f16_copy = (f16 && name.ends_with(".weight"))
            .then(|| (format!("{name}.{F16_WEIGHT}"), to_f16_bytes(values)));
        let f32_bytes = (name, bytemuck::cast_slice::<f32, u8>(values).to_vec());
        for (name, bytes) in std::iter::once(f32_bytes).chain(f16_copy) {
            let offset = (blob.len() as u64).div_ceil(align) * align;
            blob.resize(offset as usize, 0);
            blob.extend_from_slice(&bytes);
            slices.insert(
                name,
                Slice {
                    offset,
                    size: bytes.len() as u64,
                },
            );
        }
    }
    // Whole vec4s to the end, so that a chain's range (`weight_range`) can end on one.
    blob.resize(blob.len().div_ceil(16) * 16, 0);
    let weights = upload(ctx, "weights", &blob, wgpu::BufferUsages::STORAGE);
    Ok((weights, slices))
}
