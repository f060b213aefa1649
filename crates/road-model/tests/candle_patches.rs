//! The two changes of the vendored candle-core (`vendor/candle-core/ROAD-PATCHES.md`):
//! gradients stored without a zero tensor to add them to, and sums over any dims that walk the
//! source in order. Both are checked against values computed here by hand.

use candle_core::{Device, Tensor, Var};
use proptest::prelude::*;

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

/// `Σ_{reduced dims}` of a row-major `data` of shape `dims`, in f64, keeping the other dims in
/// order.
fn reference_sum(data: &[f32], dims: &[usize], reduce: &[usize]) -> Vec<f64> {
    let kept: Vec<usize> = (0..dims.len()).filter(|d| !reduce.contains(d)).collect();
    let out_len: usize = kept.iter().map(|&d| dims[d]).product();
    let mut out = vec![0.0f64; out_len];
    let mut index = vec![0usize; dims.len()];
    for &v in data {
        let mut o = 0;
        for &d in &kept {
            o = o * dims[d] + index[d];
        }
        out[o] += f64::from(v);
        for d in (0..dims.len()).rev() {
            index[d] += 1;
            if index[d] < dims[d] {
                break;
            }
            index[d] = 0;
        }
    }
    out
}

fn shape_and_dims() -> impl Strategy<Value = (Vec<usize>, Vec<usize>)> {
    prop::collection::vec(1usize..6, 1..5).prop_flat_map(|dims| {
        let rank = dims.len();
        (
            Just(dims),
            prop::collection::vec(any::<bool>(), rank).prop_map(|pick| {
                let reduce: Vec<usize> = (0..pick.len()).filter(|&d| pick[d]).collect();
                if reduce.is_empty() { vec![0] } else { reduce }
            }),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// `sum_keepdim` over any set of dims, of contiguous and of transposed (strided) tensors.
    #[test]
    fn sums_over_any_dims_match_the_reference(
        (dims, reduce) in shape_and_dims(),
        seed in any::<u64>(),
        transposed in any::<bool>(),
    ) {
        let n: usize = dims.iter().product();
        let data: Vec<f32> = (0..n)
            .map(|i| (((i as u64).wrapping_mul(2654435761).wrapping_add(seed) % 1000) as f32) / 100.0 - 5.0)
            .collect();
        let mut t = Tensor::from_vec(data.clone(), dims.as_slice(), &Device::Cpu).unwrap();
        let mut logical = data;
        let mut shape = dims.clone();
        if transposed && dims.len() >= 2 {
            // A strided view: swap the first and last dims, reference on the transposed values.
            let last = dims.len() - 1;
            t = t.transpose(0, last).unwrap();
            logical = values(&t.contiguous().unwrap());
            shape.swap(0, last);
        }
        let sum = t.sum_keepdim(reduce.clone()).unwrap();
        let expected = reference_sum(&logical, &shape, &reduce);
        let got = values(&sum);
        prop_assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(&expected) {
            prop_assert!((f64::from(*g) - e).abs() <= 1e-4 * (1.0 + e.abs()), "{} vs {}", g, e);
        }
    }
}

/// A node that several ops read (fan-in), the right-hand side of a subtraction (the first
/// gradient stored negated), a broadcast and a transposed read:
/// f = Σ (x + b)·x − Σ x² + Σ xᵀ·k = Σ_ij b_j x_ij + Σ_ij k_ji x_ij, so
/// ∂f/∂x_ij = b_j + k_ji and ∂f/∂b_j = Σ_i x_ij.
#[test]
fn gradients_accumulate_over_fan_in_subtraction_and_broadcast() {
    let dev = Device::Cpu;
    let x_vals: Vec<f32> = (0..12).map(|i| 0.5 * i as f32 - 2.0).collect();
    let b_vals = vec![1.5f32, -0.5, 2.0, 0.25];
    let k_vals: Vec<f32> = (0..12).map(|i| 0.1 * i as f32).collect();
    let x = Var::from_vec(x_vals.clone(), (3, 4), &dev).unwrap();
    let b = Var::from_vec(b_vals.clone(), 4, &dev).unwrap();
    let k = Tensor::from_vec(k_vals.clone(), (4, 3), &dev).unwrap();
    let u = x.broadcast_add(b.as_tensor()).unwrap();
    let v = (u * x.as_tensor()).unwrap();
    let w = (v - x.sqr().unwrap()).unwrap();
    let t = (x.t().unwrap() * &k).unwrap();
    let f = (w.sum_all().unwrap() + t.sum_all().unwrap()).unwrap();
    let grads = f.backward().unwrap();
    let gx = values(grads.get(x.as_tensor()).unwrap());
    let gb = values(grads.get(b.as_tensor()).unwrap());
    for i in 0..3 {
        for j in 0..4 {
            let expected = b_vals[j] + k_vals[j * 3 + i];
            assert!(
                (gx[i * 4 + j] - expected).abs() < 1e-5,
                "x[{i},{j}]: {} vs {expected}",
                gx[i * 4 + j]
            );
        }
    }
    for j in 0..4 {
        let expected: f32 = (0..3).map(|i| x_vals[i * 4 + j]).sum();
        assert!(
            (gb[j] - expected).abs() < 1e-5,
            "b[{j}]: {} vs {expected}",
            gb[j]
        );
    }
}

/// A variable read once through a subtraction's right-hand side gets the negated gradient.
#[test]
fn a_gradient_first_reached_through_a_subtraction_is_negated() {
    let dev = Device::Cpu;
    let x = Var::from_vec(vec![1.0f32, 2.0, 3.0], 3, &dev).unwrap();
    let c = Tensor::from_vec(vec![4.0f32, 5.0, 6.0], 3, &dev).unwrap();
    let f = (&c - x.as_tensor())
        .unwrap()
        .sqr()
        .unwrap()
        .sum_all()
        .unwrap();
    let grads = f.backward().unwrap();
    // ∂/∂x Σ (c − x)² = −2 (c − x).
    assert_eq!(
        values(grads.get(x.as_tensor()).unwrap()),
        vec![-6.0, -6.0, -6.0]
    );
}
