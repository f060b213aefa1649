//! The paper's forecasting metrics over joint samples (math doc, "Evaluation").

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
    let dist = |p: [f64; 2], q: [f64; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
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
