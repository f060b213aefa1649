//! A plan turned with a correction of its agent's emitted state: the lane guard's steer (in
//! closed loop) and kink augmentation (in training) turn an agent's future slots the same way.

/// The values of one agent in `road_rollout::ShiftEdit::turns`: its plan left as it is.
pub const NO_TURN: [f32; 4] = [0.0; 4];

/// One future slot's state `[3]` turned by `turn` (`road_rollout::ShiftEdit::turns`): the position
/// rotated by the angle about the pivot, the heading changed by as much. The reference of the
/// turn in the `window_shift` kernel (which computes in the same order). A zero turn leaves
/// the state bit for bit as it is.
pub fn turn_plan(state: &mut [f32], turn: &[f32]) {
    let [pivot_x, pivot_y, angle_rad, heading_change] = [turn[0], turn[1], turn[2], turn[3]];
    if angle_rad == 0.0 && heading_change == 0.0 {
        return;
    }
    let (sin, cos) = angle_rad.sin_cos();
    let (dx, dy) = (state[0] - pivot_x, state[1] - pivot_y);
    state[0] = pivot_x + (cos * dx - sin * dy);
    state[1] = pivot_y + (sin * dx + cos * dy);
    state[2] += heading_change;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quarter_turn_rotates_about_the_pivot_and_changes_the_heading() {
        let mut state = [3.0f32, 2.0, 0.1];
        turn_plan(&mut state, &[2.0, 2.0, std::f32::consts::FRAC_PI_2, 0.4]);
        let expected = [2.0f32, 3.0, 0.5];
        for (got, want) in state.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{state:?} against {expected:?}");
        }
    }

    #[test]
    fn no_turn_leaves_a_state_bit_for_bit() {
        let mut state = [0.1f32, -7.3, 1e-3];
        turn_plan(&mut state, &NO_TURN);
        assert_eq!(state, [0.1f32, -7.3, 1e-3]);
    }
}
