//! Fused CPU ops with hand-written backward passes, for training: layer norm and softmax over
//! the last dimension. candle 0.11's fused versions have no backward, and the decomposed ones
//! (`layer_norm_slow`, `ops::softmax`) cost several elementwise passes, broadcasts and strided
//! reductions each, forward and backward: profiled, most of a training step. Each op here reads
//! its input once and writes its output once per pass.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};

fn f32_slice<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(data) = storage else {
        candle_core::bail!("{what}: only f32 is supported");
    };
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("{what}: the input must be contiguous"),
    }
}

/// Layer norm over the last dimension: `y = (x − mean) / √(var + eps) · w + b`.
pub fn layer_norm(x: &Tensor, w: &Tensor, b: &Tensor, eps: f32) -> Result<Tensor> {
    x.contiguous()?.apply_op3(w, b, LayerNorm { eps })
}

/// Softmax over the last dimension.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(Softmax)
}

struct LayerNorm {
    eps: f32,
}

/// Mean and 1/σ of one row.
fn row_stats(row: &[f32], eps: f32) -> (f32, f32) {
    let d = row.len() as f32;
    let mean = row.iter().sum::<f32>() / d;
    let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d;
    (mean, 1.0 / (var + eps).sqrt())
}

impl CustomOp3 for LayerNorm {
    fn name(&self) -> &'static str {
        "road-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer norm x")?;
        let w = f32_slice(s2, l2, "layer norm weight")?;
        let b = f32_slice(s3, l3, "layer norm bias")?;
        let d = l1.dims().last().copied().unwrap_or(1);
        if w.len() != d || b.len() != d {
            candle_core::bail!(
                "layer norm: weight {} and bias {} for rows of {d}",
                w.len(),
                b.len()
            );
        }
        let mut out = vec![0.0f32; x.len()];
        for (row, o) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
            let (mean, rstd) = row_stats(row, self.eps);
            for i in 0..d {
                o[i] = (row[i] - mean) * rstd * w[i] + b[i];
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = x.dim(candle_core::D::Minus1)?;
        let rows = x.elem_count() / d;
        // [rows + 2, D]: dx rows, then dw, then db.
        let packed =
            x.apply_op3_no_bwd(w, &grad.contiguous()?, &LayerNormBackward { eps: self.eps })?;
        let dx = packed.narrow(0, 0, rows)?.reshape(x.shape())?;
        let dw = packed.narrow(0, rows, 1)?.reshape(d)?;
        let db = packed.narrow(0, rows + 1, 1)?.reshape(d)?;
        Ok((Some(dx), Some(dw), Some(db)))
    }
}

struct LayerNormBackward {
    eps: f32,
}

impl CustomOp3 for LayerNormBackward {
    fn name(&self) -> &'static str {
        "road-layer-norm-backward"
    }

    /// `(x, w, grad)` → `[rows + 2, D]`: dx, then dw and db summed over rows.
    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer norm backward x")?;
        let w = f32_slice(s2, l2, "layer norm backward weight")?;
        let g = f32_slice(s3, l3, "layer norm backward grad")?;
        let d = w.len();
        let rows = x.len() / d;
        let mut out = vec![0.0f32; (rows + 2) * d];
        let (dx_all, sums) = out.split_at_mut(rows * d);
        let (dw, db) = sums.split_at_mut(d);
        let mut xhat = vec![0.0f32; d];
        for ((row, grow), dx) in x
            .chunks_exact(d)
            .zip(g.chunks_exact(d))
            .zip(dx_all.chunks_exact_mut(d))
        {
            let (mean, rstd) = row_stats(row, self.eps);
            let (mut mean_gw, mut mean_gw_xhat) = (0.0f32, 0.0f32);
            for i in 0..d {
                xhat[i] = (row[i] - mean) * rstd;
                let gw = grow[i] * w[i];
                mean_gw += gw;
                mean_gw_xhat += gw * xhat[i];
                dw[i] += grow[i] * xhat[i];
                db[i] += grow[i];
            }
            mean_gw /= d as f32;
            mean_gw_xhat /= d as f32;
            for i in 0..d {
                dx[i] = rstd * (grow[i] * w[i] - mean_gw - xhat[i] * mean_gw_xhat);
            }
        }
        Ok((CpuStorage::F32(out), Shape::from((rows + 2, d))))
    }
}

struct Softmax;

impl CustomOp1 for Softmax {
    fn name(&self) -> &'static str {
        "road-softmax"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(storage, layout, "softmax")?;
        let d = layout.dims().last().copied().unwrap_or(1);
        let mut out = vec![0.0f32; x.len()];
        for (row, o) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
            let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let mut sum = 0.0f32;
            for (oi, &xi) in o.iter_mut().zip(row) {
                *oi = (xi - max).exp();
                sum += *oi;
            }
            let inv = 1.0 / sum;
            o.iter_mut().for_each(|v| *v *= inv);
        }
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }

    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            res.apply_op2_no_bwd(&grad.contiguous()?, &SoftmaxBackward)?,
        ))
    }
}

struct SoftmaxBackward;

impl CustomOp2 for SoftmaxBackward {
    fn name(&self) -> &'static str {
        "road-softmax-backward"
    }

    /// `(y, grad)` → `y · (grad − Σ grad·y)` per row.
    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let y = f32_slice(s1, l1, "softmax backward y")?;
        let g = f32_slice(s2, l2, "softmax backward grad")?;
        let d = l1.dims().last().copied().unwrap_or(1);
        let mut out = vec![0.0f32; y.len()];
        for ((yr, gr), o) in y
            .chunks_exact(d)
            .zip(g.chunks_exact(d))
            .zip(out.chunks_exact_mut(d))
        {
            let dot: f32 = yr.iter().zip(gr).map(|(a, b)| a * b).sum();
            for i in 0..d {
                o[i] = yr[i] * (gr[i] - dot);
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;

    fn close(a: &Tensor, b: &Tensor, tol: f32) {
        let a: Vec<f32> = a.flatten_all().unwrap().to_vec1().unwrap();
        let b: Vec<f32> = b.flatten_all().unwrap().to_vec1().unwrap();
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!((x - y).abs() <= tol * (1.0 + y.abs()), "[{i}] {x} vs {y}");
        }
    }

    /// Values and gradients against candle's decomposed ops.
    #[test]
    fn layer_norm_matches_the_decomposed_op_forward_and_backward() {
        let dev = Device::Cpu;
        let x =
            Var::from_tensor(&(Tensor::randn(0f32, 2.0, (3, 5, 16), &dev).unwrap() + 0.7).unwrap())
                .unwrap();
        let w = Var::from_tensor(&Tensor::randn(1f32, 0.3, 16, &dev).unwrap()).unwrap();
        let b = Var::from_tensor(&Tensor::randn(0f32, 0.3, 16, &dev).unwrap()).unwrap();
        let probe = Tensor::randn(0f32, 1.0, (3, 5, 16), &dev).unwrap();
        let fused = layer_norm(&x, &w, &b, 1e-5).unwrap();
        let slow = candle_nn::ops::layer_norm_slow(&x, &w, &b, 1e-5).unwrap();
        close(&fused, &slow, 1e-5);
        let gf = (fused * &probe)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gs = (slow * &probe)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for v in [&x, &w, &b] {
            close(gf.get(v).unwrap(), gs.get(v).unwrap(), 1e-4);
        }
    }

    #[test]
    fn softmax_matches_the_decomposed_op_forward_and_backward() {
        let dev = Device::Cpu;
        let x = Var::from_tensor(&Tensor::randn(0f32, 3.0, (4, 3, 7), &dev).unwrap()).unwrap();
        // A masked entry, as attention's key bias makes them.
        let mask = Tensor::from_vec(vec![0f32, 0., 0., 0., 0., 0., -1e9], 7, &dev).unwrap();
        let input = x.broadcast_add(&mask).unwrap();
        let probe = Tensor::randn(0f32, 1.0, (4, 3, 7), &dev).unwrap();
        let fused = softmax_last_dim(&input).unwrap();
        let slow = candle_nn::ops::softmax(&input, candle_core::D::Minus1).unwrap();
        close(&fused, &slow, 1e-6);
        let gf = (fused * &probe)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gs = (slow * &probe)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        close(gf.get(&x).unwrap(), gs.get(&x).unwrap(), 1e-5);
    }
}
