//! The paper's forecasting metrics over joint samples (math doc, "Evaluation").

use road_data::geometry::dist;
use serde::Serialize;

/// Scene-level displacement figures of one scene (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SceneMetrics {
    /// Minimum over samples of the mean over agents of each agent's average displacement.
    pub min_scene_ade_m: f64,
    /// Minimum over samples of the mean over agents of the final displacement.
    pub min_scene_fde_m: f64,
    /// Agents for which no sample ends within the miss threshold.
    pub missed_agents: usize,
    /// Agents evaluated (with a valid final logged state).
    pub agents: usize,
}

/// `samples[s][agent][t]` and `truth[agent][t]` are `Option<[x_m, y_m]>`-like: `truth` None
/// where the log has no state (those steps are skipped; agents without a final state are not
/// evaluated).
pub fn scene_metrics(
    samples: &[Vec<Vec<[f64; 2]>>],
    truth: &[Vec<Option<[f64; 2]>>],
    miss_threshold_m: f64,
) -> SceneMetrics {
    let agents: Vec<usize> = (0..truth.len())
        .filter(|&a| truth[a].last().is_some_and(Option::is_some))
        .collect();
    let mut min_ade = f64::INFINITY;
    let mut min_fde = f64::INFINITY;
    let mut hit = vec![false; truth.len()];
    for sample in samples {
        let (mut ade_sum, mut fde_sum) = (0.0, 0.0);
        for &a in &agents {
            let steps: Vec<f64> = truth[a]
                .iter()
                .enumerate()
                .filter_map(|(t, q)| q.map(|q| dist(sample[a][t], q)))
                .collect();
            ade_sum += steps.iter().sum::<f64>() / steps.len() as f64;
            let last = truth[a].len() - 1;
            let fde = dist(
                sample[a][last],
                truth[a][last].expect("agents with a final state"),
            );
            fde_sum += fde;
            hit[a] |= fde <= miss_threshold_m;
        }
        if !agents.is_empty() {
            min_ade = min_ade.min(ade_sum / agents.len() as f64);
            min_fde = min_fde.min(fde_sum / agents.len() as f64);
        }
    }
    SceneMetrics {
        min_scene_ade_m: min_ade,
        min_scene_fde_m: min_fde,
        missed_agents: agents.iter().filter(|&&a| !hit[a]).count(),
        agents: agents.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn joint_minimum_is_over_whole_samples() {
        // Two agents, two steps. Sample 0 is perfect for agent 0 and 4 m off for agent 1;
        // sample 1 the other way round: per-agent minima would be 0, the joint minimum is not.
        let truth = vec![
            vec![Some([0.0, 0.0]), Some([1.0, 0.0])],
            vec![Some([0.0, 5.0]), Some([1.0, 5.0])],
        ];
        let s0 = vec![vec![[0.0, 0.0], [1.0, 0.0]], vec![[0.0, 9.0], [1.0, 9.0]]];
        let s1 = vec![vec![[0.0, 4.0], [1.0, 4.0]], vec![[0.0, 5.0], [1.0, 5.0]]];
        let m = scene_metrics(&[s0, s1], &truth, 2.0);
        assert!((m.min_scene_ade_m - 2.0).abs() < 1e-12);
        assert!((m.min_scene_fde_m - 2.0).abs() < 1e-12);
        // Each agent is hit by one sample: no misses.
        assert_eq!((m.missed_agents, m.agents), (0, 2));
        let far = vec![vec![[0.0, 0.0], [9.0, 0.0]], vec![[0.0, 5.0], [1.0, 5.0]]];
        assert_eq!(scene_metrics(&[far], &truth, 2.0).missed_agents, 1);
    }
}

/// A ratio of sums over scenes (`Σ numerator / Σ denominator`: a mean over scenes with
/// denominators of 1, a rate over agents with agent counts) with a 95 % percentile-bootstrap
/// interval over scenes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    pub value: f64,
    pub ci_low: f64,
    pub ci_high: f64,
}

impl std::fmt::Display for Estimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = f.precision().unwrap_or(3);
        write!(
            f,
            "{:.p$} [{:.p$}, {:.p$}]",
            self.value, self.ci_low, self.ci_high
        )
    }
}

/// Bootstrap resamples behind every [`Estimate`]: enough for stable 2.5 / 97.5 percentiles.
pub const BOOTSTRAP_RESAMPLES: usize = 2000;

/// `Σ numerator / Σ denominator` over `per_scene` with its 95 % interval from resampling the
/// scenes with replacement (`seed` fixes the resamples, so a report is reproducible). Empty
/// input or a zero denominator gives NaN.
pub fn bootstrap_ratio(per_scene: &[(f64, f64)], seed: u64) -> Estimate {
    use rand::{Rng, SeedableRng};
    let ratio = |num: f64, den: f64| if den > 0.0 { num / den } else { f64::NAN };
    let (num, den) = per_scene
        .iter()
        .fold((0.0, 0.0), |(n, d), &(a, b)| (n + a, d + b));
    let value = ratio(num, den);
    if per_scene.is_empty() {
        return Estimate {
            value,
            ci_low: f64::NAN,
            ci_high: f64::NAN,
        };
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut stats: Vec<f64> = (0..BOOTSTRAP_RESAMPLES)
        .map(|_| {
            let (mut n, mut d) = (0.0, 0.0);
            for _ in 0..per_scene.len() {
                let (a, b) = per_scene[rng.random_range(0..per_scene.len())];
                n += a;
                d += b;
            }
            ratio(n, d)
        })
        .filter(|v| v.is_finite())
        .collect();
    if stats.is_empty() {
        // Every resample's denominator was 0 (no step to count, say): no interval.
        return Estimate {
            value,
            ci_low: f64::NAN,
            ci_high: f64::NAN,
        };
    }
    stats.sort_by(f64::total_cmp);
    let at = |q: f64| stats[((stats.len() - 1) as f64 * q).round() as usize];
    Estimate {
        value,
        ci_low: at(0.025),
        ci_high: at(0.975),
    }
}

#[cfg(test)]
mod bootstrap_tests {
    use super::bootstrap_ratio;

    #[test]
    fn interval_brackets_the_mean_and_shrinks_with_more_scenes() {
        let scenes = |n: usize| -> Vec<(f64, f64)> {
            (0..n).map(|i| ((i % 10) as f64, 1.0)).collect() // mean 4.5, sd ≈ 2.9
        };
        let small = bootstrap_ratio(&scenes(20), 1);
        let large = bootstrap_ratio(&scenes(2000), 1);
        for e in [small, large] {
            assert!((e.value - 4.5).abs() < 1e-12, "{e}");
            assert!(e.ci_low < e.value && e.value < e.ci_high, "{e}");
        }
        // The interval's width falls like 1/√n: ≈ 2.5 at 20 scenes, ≈ 0.25 at 2000.
        let width = |e: super::Estimate| e.ci_high - e.ci_low;
        assert!(width(small) > 1.5 && width(small) < 3.5, "{small}");
        assert!(width(large) > 0.15 && width(large) < 0.35, "{large}");
    }

    #[test]
    fn rates_weigh_scenes_by_their_denominators() {
        // 1 of 1 agents missed in one scene, 0 of 9 in the other: 0.1, not the mean 0.5.
        let e = bootstrap_ratio(&[(1.0, 1.0), (0.0, 9.0)], 3);
        assert!((e.value - 0.1).abs() < 1e-12, "{e}");
        assert!(bootstrap_ratio(&[], 0).value.is_nan());
        // Nothing to count in any scene: no rate and no interval, and no panic.
        let none = bootstrap_ratio(&[(0.0, 0.0), (0.0, 0.0)], 3);
        assert!(none.value.is_nan() && none.ci_low.is_nan() && none.ci_high.is_nan());
    }
}
