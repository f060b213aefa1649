//! What the engine's integration tests share: a small model with road20-wide4's features and
//! its seeded weights on the GPU.

use std::collections::HashMap;

use road_gpu::GpuContext;
use road_gpu::engine::GpuDenoiser;
use road_model::ModelConfig;

/// road20-wide4's features (agent frame, agent maps, agent pairs) at a small size.
pub fn config() -> ModelConfig {
    ModelConfig {
        hidden: 32,
        heads: 2,
        blocks: 2,
        agent_frame: Some(road_model::AgentFrame {
            anchor_slot: 9,
            relative_scale: 1.0,
            residual_scale: Some(40.0),
            max_anchor_sigma: None,
        }),
        agent_map: Some(road_model::AgentMap { polylines: 4 }),
        agent_pairs: Some(road_model::AgentPairs {
            direction_scale_m: 10.0,
            near_scale_m: 5.0,
            far_scale_m: 20.0,
        }),
        ..ModelConfig::default()
    }
}

/// `config`'s model with seeded weights, uploaded to `ctx`.
pub fn denoiser(ctx: &GpuContext, config: &ModelConfig) -> GpuDenoiser {
    let (varmap, _) =
        road_model::model::init_seeded(config, &candle_core::Device::Cpu, 42).unwrap();
    let tensors: HashMap<String, Vec<f32>> = varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(name, var)| {
            let values = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            (name.clone(), values)
        })
        .collect();
    GpuDenoiser::new(ctx, config, &tensors).unwrap()
}
