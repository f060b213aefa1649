//! The per-slot Heun step (EDM Algorithm 1 with a σ per scene and slot) and the bookkeeping
//! every CPU engine shares: which scenes of a mixed-phase batch move, and the gather / scatter
//! of their rows. The engines differ only in how they evaluate the denoiser.

use road_model::{Error, Result};

/// The scenes of a batch whose σ row changes (the others hold still this round), after
/// checking that both σ tables are `[scenes, w]`.
pub fn changing_scenes(
    sigma_cur: &[f32],
    sigma_next: &[f32],
    scenes: usize,
    w: usize,
) -> Result<Vec<usize>> {
    if sigma_cur.len() != scenes * w || sigma_next.len() != scenes * w {
        return Err(Error::data(format!(
            "σ rows: {} and {} values for {scenes} scenes × {w} slots",
            sigma_cur.len(),
            sigma_next.len(),
        )));
    }
    Ok((0..scenes)
        .filter(|&b| sigma_cur[b * w..(b + 1) * w] != sigma_next[b * w..(b + 1) * w])
        .collect())
}

/// Rows `scenes` of `values` (`len` values per scene), packed.
pub fn gather_rows(values: &[f32], scenes: &[usize], len: usize) -> Vec<f32> {
    scenes
        .iter()
        .flat_map(|&b| values[b * len..(b + 1) * len].iter().copied())
        .collect()
}

/// Writes packed rows back to scenes `scenes` of `values` (`len` values per scene).
pub fn scatter_rows(values: &mut [f32], scenes: &[usize], len: usize, packed: &[f32]) {
    for (k, &b) in scenes.iter().enumerate() {
        values[b * len..(b + 1) * len].copy_from_slice(&packed[k * len..(k + 1) * len]);
    }
}

/// One Heun step of packed windows `x [B, A, W, 3]` with σ `[B, W]` per scene and slot, the
/// denoiser given as `denoise(x, σ) → D(x; σ)` (`[B, A, W, 3]`). Slots whose σ does not change
/// are left as they are; a slot landing on σ = 0 takes the Euler result (its second evaluation
/// is never read, so it is made at σ_cur). Returns the new windows and the last evaluation's
/// D (the second's where there are two): the estimate an engine keeps for a scene's plan.
pub fn heun_update(
    x: &[f32],
    agents: usize,
    w: usize,
    sigma_cur: &[f32],
    sigma_next: &[f32],
    second_evaluation: bool,
    mut denoise: impl FnMut(&[f32], &[f32]) -> Result<Vec<f32>>,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let scenes = sigma_cur.len() / w.max(1);
    if x.len() != scenes * agents * w * 3
        || sigma_cur.len() != scenes * w
        || sigma_next.len() != sigma_cur.len()
    {
        return Err(Error::data(format!(
            "Heun step: {} states and σ rows of {} and {} values for {agents} agents × {w} slots",
            x.len(),
            sigma_cur.len(),
            sigma_next.len()
        )));
    }
    // Element e of [B, A, W, 3] → its (scene, slot) row index in σ [B, W].
    let row = |e: usize| (e / (3 * agents * w)) * w + (e / 3) % w;
    let d1 = denoise(x, sigma_cur)?;
    // Euler for every changing slot.
    let mut x_e = x.to_vec();
    for (e, (xe, xv)) in x_e.iter_mut().zip(x).enumerate() {
        let r = row(e);
        let (s, sn) = (sigma_cur[r], sigma_next[r]);
        if s != sn {
            *xe = xv + (sn - s) * (xv - d1[e]) / s;
        }
    }
    if !second_evaluation {
        return Ok((x_e, d1));
    }
    let sigma_eval: Vec<f32> = sigma_cur
        .iter()
        .zip(sigma_next)
        .map(|(&s, &sn)| if sn > 0.0 { sn } else { s })
        .collect();
    let d2 = denoise(&x_e, &sigma_eval)?;
    let mut out = x_e.clone();
    for (e, o) in out.iter_mut().enumerate() {
        let r = row(e);
        let (s, sn) = (sigma_cur[r], sigma_next[r]);
        if s != sn && sn > 0.0 {
            let slope1 = (x[e] - d1[e]) / s;
            let slope2 = (x_e[e] - d2[e]) / sn;
            *o = x[e] + (sn - s) * 0.5 * (slope1 + slope2);
        }
    }
    Ok((out, d2))
}

/// The multistep sampler's correction after an Euler step (`road_sched::Sampler::Multistep`):
/// `x += γ·(D − D_prev)` for packed windows `x [B, A, W, 3]`, this step's estimate `denoised`
/// and the slot's previous one `previous` (same shape), `gamma [B, W]` per scene and slot. The
/// reference of the `multistep_correct` kernel.
pub fn multistep_correct(
    x: &mut [f32],
    denoised: &[f32],
    previous: &[f32],
    gamma: &[f32],
    agents: usize,
    w: usize,
) {
    let row = |e: usize| (e / (3 * agents * w)) * w + (e / 3) % w;
    for (e, xe) in x.iter_mut().enumerate() {
        let g = gamma[row(e)];
        if g != 0.0 {
            *xe += g * (denoised[e] - previous[e]);
        }
    }
}
