//! The EDM noise schedule (Karras et al. 2022) with the local diffusion time `u` of the math doc.
//!
//! `u ∈ [0, 1]`: 0 is clean, 1 is pure noise. For `u > 0`,
//! `σ(u) = (σ_min^(1/ρ) + u·(σ_max^(1/ρ) − σ_min^(1/ρ)))^ρ`; `u = 0` is exactly clean (`σ = 0`),
//! which is where EDM's last sampling step lands after its ρ-spaced levels.

use serde::{Deserialize, Serialize};

/// EDM's constants. `Default` holds EDM's (and the paper's) values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EdmSchedule {
    pub sigma_min: f64,
    pub sigma_max: f64,
    pub rho: f64,
    pub sigma_data: f64,
}

impl Default for EdmSchedule {
    fn default() -> Self {
        Self {
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            sigma_data: 0.5,
        }
    }
}

/// EDM's preconditioning coefficients for one noise level:
/// `D(x; σ) = c_skip·x + c_out·F(c_in·x; c_noise)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Preconditioning {
    pub c_skip: f64,
    pub c_out: f64,
    pub c_in: f64,
    pub c_noise: f64,
}

impl EdmSchedule {
    /// Noise level of local diffusion time `u` (clamped to [0, 1]); `u = 0` → 0 (clean).
    pub fn sigma(&self, u: f64) -> f64 {
        let u = u.clamp(0.0, 1.0);
        if u == 0.0 {
            return 0.0;
        }
        let inv_rho = 1.0 / self.rho;
        let lo = self.sigma_min.powf(inv_rho);
        let hi = self.sigma_max.powf(inv_rho);
        (lo + u * (hi - lo)).powf(self.rho)
    }

    /// Inverse of [`Self::sigma`] on `[σ_min, σ_max]`; 0 for σ = 0.
    pub fn u_of_sigma(&self, sigma: f64) -> f64 {
        if sigma <= 0.0 {
            return 0.0;
        }
        let inv_rho = 1.0 / self.rho;
        let lo = self.sigma_min.powf(inv_rho);
        let hi = self.sigma_max.powf(inv_rho);
        ((sigma.powf(inv_rho) - lo) / (hi - lo)).clamp(0.0, 1.0)
    }

    /// Preconditioning coefficients at noise level `sigma` (> 0).
    pub fn preconditioning(&self, sigma: f64) -> Preconditioning {
        let sd2 = self.sigma_data * self.sigma_data;
        let s2 = sigma * sigma;
        Preconditioning {
            c_skip: sd2 / (s2 + sd2),
            c_out: sigma * self.sigma_data / (s2 + sd2).sqrt(),
            c_in: 1.0 / (s2 + sd2).sqrt(),
            c_noise: sigma.ln() / 4.0,
        }
    }

    /// EDM loss weight `λ(σ) = (σ² + σ_d²) / (σ·σ_d)²`.
    pub fn loss_weight(&self, sigma: f64) -> f64 {
        let sd2 = self.sigma_data * self.sigma_data;
        (sigma * sigma + sd2) / (sigma * sigma * sd2)
    }
}

/// Warm-up profile: `u_k(τ) = clip(k/F + τ, 0, 1)` for future slot `k ∈ [0, F)`.
pub fn warmup_u(future_slot: usize, future_slots: usize, tau: f64) -> f64 {
    (future_slot as f64 / future_slots as f64 + tau).clamp(0.0, 1.0)
}

/// Rolling profile: `u_k(τ) = clip((k + τ)/F, 0, 1)` for future slot `k ∈ [0, F)`.
pub fn rolling_u(future_slot: usize, future_slots: usize, tau: f64) -> f64 {
    ((future_slot as f64 + tau) / future_slots as f64).clamp(0.0, 1.0)
}

/// Full-diffusion profile (AR, DJINN): every future slot at `u = τ`.
pub fn full_u(_future_slot: usize, _future_slots: usize, tau: f64) -> f64 {
    tau.clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 + 1e-9 * b.abs()
    }

    #[test]
    fn sigma_endpoints_and_inverse() {
        let s = EdmSchedule::default();
        assert_eq!(s.sigma(0.0), 0.0);
        assert!(close(s.sigma(1.0), 80.0));
        assert!(close(s.sigma(1e-300), 0.002));
        for i in 1..=100 {
            let u = i as f64 / 100.0;
            assert!(close(s.u_of_sigma(s.sigma(u)), u), "u = {u}");
            assert!(s.sigma(u) > s.sigma(u - 0.01));
        }
    }

    #[test]
    fn preconditioning_matches_hand_computed_values() {
        let s = EdmSchedule::default();
        // σ = 0.5 = σ_d: c_skip = 0.5, c_out = 0.25/√0.5, c_in = 1/√0.5, c_noise = ln(0.5)/4.
        let p = s.preconditioning(0.5);
        assert!(close(p.c_skip, 0.5));
        assert!(close(p.c_out, std::f64::consts::SQRT_2 / 4.0));
        assert!(close(p.c_in, std::f64::consts::SQRT_2));
        assert!(close(p.c_noise, -0.173_286_795_139_986_3));
        // σ = 80: c_skip = 0.25/6400.25, c_in = 1/√6400.25.
        let p = s.preconditioning(80.0);
        assert!(close(p.c_skip, 0.25 / 6400.25));
        assert!(close(p.c_in, 1.0 / 6400.25_f64.sqrt()));
        assert!(close(p.c_out, 40.0 / 6400.25_f64.sqrt()));
        // λ(σ_d) = 0.5 / 0.0625 = 8.
        assert!(close(s.loss_weight(0.5), 8.0));
    }

    #[test]
    fn profiles_match_the_math_doc() {
        // Warm-up: τ = 1 all noise; τ = 0 slot k at k/F.
        for k in 0..10 {
            assert_eq!(warmup_u(k, 10, 1.0), 1.0);
            assert!(close(warmup_u(k, 10, 0.0), k as f64 / 10.0));
            assert!(close(rolling_u(k, 10, 1.0), (k + 1) as f64 / 10.0));
            assert!(close(rolling_u(k, 10, 0.0), k as f64 / 10.0));
        }
    }
}
