//! Kernels against their CPU references on the adapter present (lavapipe in CI).

use rand::{Rng, SeedableRng};
use road_gpu::kernels::edm::EdmPrecondition;
use road_gpu::{ContextOptions, GpuContext, Tolerance};
use road_sched::EdmSchedule;

/// The test adapter: validation on, `WGPU_BACKEND` / `WGPU_ADAPTER_NAME` honoured, software
/// adapters accepted. No adapter is a failure, not a skip: CI installs lavapipe.
fn context() -> GpuContext {
    GpuContext::new(&ContextOptions {
        validation: true,
        ..ContextOptions::default()
    })
    .unwrap_or_else(|e| panic!("GPU tests need an adapter: {e}"))
}

#[test]
fn edm_preconditioning_matches_the_cpu_reference() {
    let ctx = context();
    eprintln!("adapter: {}", ctx.describe());
    let kernel = EdmPrecondition::new(&ctx);
    let edm = EdmSchedule::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    for count in [1usize, 63, 64, 65, 1000, 4099] {
        // σ over the whole schedule, plus clean slots (σ = 0).
        let sigma: Vec<f32> = (0..count)
            .map(|i| {
                if i % 17 == 3 {
                    0.0
                } else {
                    edm.sigma(rng.random_range(0.0..=1.0)) as f32
                }
            })
            .collect();
        let got = kernel
            .run(&ctx, &sigma, edm.sigma_data as f32, edm.sigma_min as f32)
            .unwrap();
        assert_eq!(got.len(), count);
        let mut expected = Vec::with_capacity(count * 4);
        for &s in &sigma {
            let p = edm.preconditioning(f64::from(s));
            let c_noise = f64::from(s).max(edm.sigma_min).ln() / 4.0;
            expected.extend([
                p.c_skip as f32,
                p.c_out as f32,
                p.c_in as f32,
                c_noise as f32,
            ]);
        }
        let actual: Vec<f32> = got.iter().flatten().copied().collect();
        if let Err(m) = Tolerance::F32.check(&actual, &expected) {
            panic!("count {count}: {m} (σ = {})", sigma[m.index / 4]);
        }
    }
}
