//! [`TimedEngine`]: any engine, with the time spent inside it summed, so that a tick's time
//! splits into the engine's and the host's around it (`road bench serve`'s host share: the
//! planner's smoothing, the driver's bookkeeping, everything that is not a kernel or a
//! readback).

use std::time::{Duration, Instant};

use road_model::Result;

use crate::engine::StepEngine;
use crate::window::{ShiftEdit, ShiftShape};

/// `inner`, every call but the shape queries timed into [`Self::spent`].
pub struct TimedEngine<'e> {
    inner: &'e mut dyn StepEngine,
    spent: Duration,
}

impl std::fmt::Debug for TimedEngine<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TimedEngine")
            .field("spent", &self.spent)
            .finish_non_exhaustive()
    }
}

impl<'e> TimedEngine<'e> {
    pub fn new(inner: &'e mut dyn StepEngine) -> Self {
        Self {
            inner,
            spent: Duration::ZERO,
        }
    }

    /// Time spent in the engine since it was made or last taken.
    pub fn take_spent(&mut self) -> Duration {
        std::mem::take(&mut self.spent)
    }

    fn timed<T>(&mut self, call: impl FnOnce(&mut dyn StepEngine) -> T) -> T {
        let started = Instant::now();
        let out = call(&mut *self.inner);
        self.spent += started.elapsed();
        out
    }
}

impl StepEngine for TimedEngine<'_> {
    fn window_slots(&self) -> usize {
        self.inner.window_slots()
    }

    fn position_scale_m(&self) -> Option<f64> {
        self.inner.position_scale_m()
    }

    fn heading_scale(&self) -> Option<f64> {
        self.inner.heading_scale()
    }

    fn prepare(
        &mut self,
        scenes: usize,
        agents: usize,
        features: &[f32],
        polylines: usize,
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        self.timed(|e| e.prepare(scenes, agents, features, polylines, map, map_valid))
    }

    fn prepare_scene(
        &mut self,
        scene: usize,
        features: &[f32],
        map: &[f32],
        map_valid: &[f32],
    ) -> Result<()> {
        self.timed(|e| e.prepare_scene(scene, features, map, map_valid))
    }

    fn load(&mut self, windows: &[f32], valid: &[f32]) -> Result<()> {
        self.timed(|e| e.load(windows, valid))
    }

    fn load_scene(&mut self, scene: usize, window: &[f32], valid: &[f32]) -> Result<()> {
        self.timed(|e| e.load_scene(scene, window, valid))
    }

    fn step(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        second_evaluation: bool,
    ) -> Result<()> {
        self.timed(|e| e.step(sigma_cur, sigma_next, second_evaluation))
    }

    fn read_emitted(&mut self, slots: &[Option<usize>], out: &mut [f32]) -> Result<()> {
        self.timed(|e| e.read_emitted(slots, out))
    }

    fn read_denoised(&mut self, scenes: &[usize], out: &mut [f32]) -> Result<()> {
        self.timed(|e| e.read_denoised(scenes, out))
    }

    fn read_emitted_and_denoised(
        &mut self,
        slots: &[Option<usize>],
        out: &mut [f32],
        scenes: &[usize],
        denoised: &mut [f32],
    ) -> Result<()> {
        self.timed(|e| e.read_emitted_and_denoised(slots, out, scenes, denoised))
    }

    fn step_multistep(
        &mut self,
        sigma_cur: &[f32],
        sigma_next: &[f32],
        gamma: &[f32],
    ) -> Result<()> {
        self.timed(|e| e.step_multistep(sigma_cur, sigma_next, gamma))
    }

    fn shift(&mut self, edits: &[ShiftEdit<'_>], shape: ShiftShape) -> Result<()> {
        self.timed(|e| e.shift(edits, shape))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An engine that takes 2 ms a step and answers its shape queries.
    struct Slow {
        steps: usize,
    }

    impl StepEngine for Slow {
        fn window_slots(&self) -> usize {
            20
        }
        fn position_scale_m(&self) -> Option<f64> {
            Some(40.0)
        }
        fn prepare(
            &mut self,
            _: usize,
            _: usize,
            _: &[f32],
            _: usize,
            _: &[f32],
            _: &[f32],
        ) -> Result<()> {
            Ok(())
        }
        fn load(&mut self, _: &[f32], _: &[f32]) -> Result<()> {
            Ok(())
        }
        fn load_scene(&mut self, _: usize, _: &[f32], _: &[f32]) -> Result<()> {
            Ok(())
        }
        fn step(&mut self, _: &[f32], _: &[f32], _: bool) -> Result<()> {
            self.steps += 1;
            std::thread::sleep(Duration::from_millis(2));
            Ok(())
        }
        fn read_emitted(&mut self, _: &[Option<usize>], _: &mut [f32]) -> Result<()> {
            Ok(())
        }
        fn shift(&mut self, _: &[ShiftEdit<'_>], _: ShiftShape) -> Result<()> {
            Ok(())
        }
    }

    #[test]
    fn the_time_inside_the_engine_is_summed_and_taken() {
        let mut slow = Slow { steps: 0 };
        let mut timed = TimedEngine::new(&mut slow);
        assert_eq!(timed.window_slots(), 20);
        assert_eq!(timed.position_scale_m(), Some(40.0));
        assert_eq!(timed.heading_scale(), None);
        for _ in 0..3 {
            timed.step(&[], &[], true).unwrap();
        }
        let spent = timed.take_spent();
        assert!(spent >= Duration::from_millis(6), "{spent:?}");
        assert_eq!(timed.take_spent(), Duration::ZERO, "taken");
        // What the inner engine refuses is refused as it says.
        let err = timed.read_denoised(&[0], &mut []).unwrap_err().to_string();
        assert!(err.contains("read_denoised"), "{err}");
        assert_eq!(slow.steps, 3);
    }
}
