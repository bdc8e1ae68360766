//! The wheel test (`WHEEL_TEST`): one wheel driven alone from `Disabled` for a set time, and
//! its result (`docs/control.md`, "Wheel test").

use super::current_loop::symmetric_limit;
use super::{Controller, Instant};
use crate::protocol::robot::{Fault, RobotState, TestOutcome, WheelTest, WheelTestResult};

/// Wheel test: the current limit is this fraction of `limits.max_current` (current drives).
pub const WHEEL_TEST_CURRENT_FRACTION: f32 = 0.25;

/// A running wheel test.
#[derive(Debug, Clone, Copy)]
pub(super) struct TestRun {
    pub(super) wheel: u8,
    /// Wheel speed setpoint, rad/s.
    pub(super) speed: f32,
    /// It ends at the first step at or after this.
    until: Instant,
    /// The wheel's angle when it began, rad.
    start_angle: f32,
    /// The current of largest magnitude commanded so far, A (signed).
    peak_current: f32,
}

impl Controller {
    /// Starts a wheel test if the robot is disabled; otherwise refuses it (a
    /// `WHEEL_TEST_RESULT` `REFUSED` at the next step).
    pub(super) fn start_test(&mut self, now: Instant, t: WheelTest) {
        // The codec refuses wheels above 3; the core does not index past them either way.
        let wheel = t.wheel.min(3);
        if self.state != RobotState::Disabled {
            self.test_result = Some(WheelTestResult {
                wheel: t.wheel,
                outcome: TestOutcome::Refused,
                angle: 0.0,
                peak_current: 0.0,
            });
            return;
        }
        self.state = RobotState::WheelTest;
        self.fault = Fault::None;
        self.halt();
        let max = self.config.limits.max_wheel_speed;
        self.test = Some(TestRun {
            wheel,
            speed: symmetric_limit(t.speed, max),
            until: Instant::from_micros(
                now.as_micros()
                    .saturating_add(u64::from(t.duration_ms) * 1000),
            ),
            start_angle: self.wheels[usize::from(wheel)].angle,
            peak_current: 0.0,
        });
        // ODrive: closed loop on the tested axis only; the others stay idle.
        self.drive.request_closed_loop(now, Some(wheel));
    }

    /// Ends the test when its time is up (at step `now`).
    pub(super) fn time_test(&mut self, now: Instant) {
        if let Some(t) = self.test
            && now >= t.until
        {
            self.end_test(TestOutcome::Done);
            self.state = RobotState::Disabled;
            self.halt();
        }
    }

    /// Ends the running wheel test, if any, with `outcome` (its result goes out at the next
    /// step). The caller sets the state.
    pub(super) fn end_test(&mut self, outcome: TestOutcome) {
        if let Some(t) = self.test.take() {
            let w = &self.wheels[usize::from(t.wheel)];
            self.test_result = Some(WheelTestResult {
                wheel: t.wheel,
                outcome,
                angle: w.angle + w.pending - t.start_angle,
                peak_current: t.peak_current,
            });
        }
    }

    /// Keeps the test's peak current (after the step's currents are known).
    pub(super) fn note_test_current(&mut self) {
        if let Some(t) = &mut self.test {
            let i = self.currents[usize::from(t.wheel)];
            if i.abs() > t.peak_current.abs() {
                t.peak_current = i;
            }
        }
    }

    /// The current limit in force, A: `limits.max_current` while enabled, a quarter of it in
    /// a wheel test, none otherwise (no wheel is driven).
    pub(super) fn current_limit(&self) -> f32 {
        let max = self.config.limits.max_current;
        match self.state {
            RobotState::Enabled => max,
            RobotState::WheelTest => WHEEL_TEST_CURRENT_FRACTION * max,
            _ => 0.0,
        }
    }
}
