//! candle's denoiser against the PyTorch mirror (`scripts/torch_denoiser.py`): the fixture
//! under `tests/fixtures/torch_parity/` holds a tiny checkpoint with random weights (agent
//! frame with a constant-velocity residual, agent maps, agent pairs), the inputs of three
//! padded scenes with absent agents and slots, four σ cases, and the mirror's `D(x; σ)`.
//! Regenerate it with `python scripts/torch_denoiser.py make-fixture --out
//! crates/road-model/tests/fixtures/torch_parity` (docs/checkpoint.md).
//!
//! `ROAD_TORCH_PARITY_FIXTURE=DIR` points the tests at another fixture, e.g. one of a shipped
//! checkpoint's own weights (`make-fixture --checkpoint models/road20-wide4 --out DIR`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use road_model::Mode;
use road_model::checkpoint::{self, LoadedModel};

/// The largest difference allowed between candle and PyTorch, in state units (40 m): float
/// rounding of two fp32 implementations of the same sums.
const TOLERANCE: f32 = 1e-4;

const FIXTURE_OVERRIDE: &str = "ROAD_TORCH_PARITY_FIXTURE";

fn fixture_dir() -> PathBuf {
    match std::env::var_os(FIXTURE_OVERRIDE) {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/torch_parity"),
    }
}

fn load_fixture(name: &str) -> HashMap<String, Tensor> {
    let path = fixture_dir().join(name);
    checkpoint::load_tensors(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn max_abs_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The fixture's tensors: the batch (`x_noisy [B, A, W, 3]`, `valid [B, A, W]`,
/// `agent_features [B, A, 6]`, `map [B, P, Q, 2]`, `map_valid [B, P]`), the σ cases
/// `sigma [C, B, W]` and the mirror's outputs `denoised [C, B, A, W, 3]`.
struct Fixture {
    inputs: HashMap<String, Tensor>,
    sigma_cases: Vec<Tensor>,
    expected: Vec<Tensor>,
}

impl Fixture {
    fn load() -> Self {
        let inputs = load_fixture("inputs.safetensors");
        let expected = load_fixture("expected.safetensors");
        let sigma = inputs["sigma"].clone();
        let denoised = expected["denoised"].clone();
        let cases = sigma.dim(0).unwrap();
        assert_eq!(denoised.dim(0).unwrap(), cases, "one output per σ case");
        Self {
            sigma_cases: (0..cases).map(|c| sigma.get(c).unwrap()).collect(),
            expected: (0..cases).map(|c| denoised.get(c).unwrap()).collect(),
            inputs,
        }
    }

    fn input(&self, name: &str) -> &Tensor {
        self.inputs
            .get(name)
            .unwrap_or_else(|| panic!("inputs.safetensors lacks `{name}`"))
    }

    /// candle's `D(x; σ)` of the fixture's batch at σ case `sigma`, with validity `valid`.
    fn denoise(&self, loaded: &LoadedModel, sigma: &Tensor, valid: &Tensor) -> Tensor {
        let model = &loaded.model;
        let map_tokens = model.encode_map(self.input("map"), Mode::Infer).unwrap();
        model
            .denoise(
                self.input("x_noisy"),
                sigma,
                valid,
                self.input("agent_features"),
                &map_tokens,
                self.input("map_valid"),
                Mode::Infer,
            )
            .unwrap()
    }
}

fn load_model() -> LoadedModel {
    checkpoint::load(&fixture_dir(), &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn candle_matches_the_pytorch_mirror() {
    let loaded = load_model();
    let config = &loaded.model.config;
    println!("fixture {}", fixture_dir().display());
    // The committed fixture exercises every option of the shipped agent-frame checkpoints.
    if std::env::var_os(FIXTURE_OVERRIDE).is_none() {
        let has_residual = config
            .agent_frame
            .as_ref()
            .is_some_and(|f| f.residual_scale.is_some());
        assert!(
            has_residual
                && config.agent_map.is_some()
                && config.agent_pairs.is_some()
                && loaded.model.blocks_have_agent_pairs(),
            "the fixture's model lacks an option: {config:?}"
        );
    }
    let fixture = Fixture::load();
    let valid = fixture.input("valid");
    let (b, a, w) = valid.dims3().unwrap();
    assert_eq!(w, config.window_slots);
    assert!(b >= 2 && a >= 2, "several scenes and agents");
    let flags = values(valid);
    assert!(
        flags.contains(&0.0) && flags.contains(&1.0),
        "the fixture has absent agent-slots, so masks are exercised"
    );

    let mut worst = 0.0f32;
    let mut outputs = Vec::new();
    for (case, (sigma, expected)) in fixture
        .sigma_cases
        .iter()
        .zip(&fixture.expected)
        .enumerate()
    {
        let got = fixture.denoise(&loaded, sigma, valid);
        assert_eq!(got.dims(), expected.dims(), "σ case {case}");
        let (got, want) = (values(&got), values(expected));
        assert!(
            got.iter().all(|v| v.is_finite()),
            "σ case {case}: non-finite"
        );
        assert!(
            want.iter().any(|&v| v.abs() > 1e-3),
            "σ case {case}: the expected outputs are all zero"
        );
        let difference = max_abs_difference(&got, &want);
        println!("σ case {case}: max |candle − torch| = {difference:.3e}");
        worst = worst.max(difference);
        outputs.push(got);
    }
    println!(
        "max |candle − torch| over {} σ cases: {worst:.3e} (tolerance {TOLERANCE:e})",
        outputs.len()
    );
    assert!(
        worst <= TOLERANCE,
        "candle and the PyTorch mirror differ by {worst:e}"
    );
    // Every σ case denoises the same noisy states, so only σ tells them apart: outputs that
    // agree across cases would mean σ is not wired in.
    for (i, first) in outputs.iter().enumerate() {
        for (j, second) in outputs.iter().enumerate().skip(i + 1) {
            let difference = max_abs_difference(first, second);
            assert!(
                difference > 100.0 * TOLERANCE,
                "σ cases {i} and {j} give the same output (max difference {difference:e})"
            );
        }
    }
}

/// A negative control: the comparison sees a mis-wired input. Dropping one valid agent-slot
/// (a key of its agent's time attention and of its slot's agent attention) must move the
/// outputs well beyond the tolerance.
#[test]
fn a_changed_mask_breaks_the_parity() {
    let loaded = load_model();
    let fixture = Fixture::load();
    let valid = fixture.input("valid");
    let mut flags = values(valid);
    let first_valid = flags
        .iter()
        .position(|&v| v == 1.0)
        .expect("a valid agent-slot");
    flags[first_valid] = 0.0;
    let changed = Tensor::from_vec(flags, valid.dims(), &Device::Cpu).unwrap();
    let got = values(&fixture.denoise(&loaded, &fixture.sigma_cases[0], &changed));
    let difference = max_abs_difference(&got, &values(&fixture.expected[0]));
    assert!(
        difference > 100.0 * TOLERANCE,
        "a changed mask moved the outputs by only {difference:e}"
    );
}
