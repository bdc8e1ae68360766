//! Motor health at every step: each motor's freshness (missing, stale, a drive's own error),
//! then the drive's watches (stuck encoder, runaway, fight); the first fault found moves the
//! robot to `Fault` (`docs/control.md`, "Faults").

use super::{Controller, Instant};
use crate::protocol::robot::{Fault, RobotState, TestOutcome};

impl Controller {
    /// Checks the motors at step `now` (the first step at `boot`).
    pub(super) fn check_motors(&mut self, now: Instant, boot: Instant) {
        let t = &self.config.timing;
        let stale_us = self.feedback_period_us * u64::from(t.stale_periods);
        let boot_us = u64::from(t.boot_timeout_ms) * 1000;
        // One pass: each motor's freshness (online bit, staleness) and the first fault found
        // in wheel order.
        let mut online = 0u8;
        let mut fault = Fault::None;
        let enabled = self.state == RobotState::Enabled;
        for (i, w) in self.wheels.iter().enumerate() {
            let fresh = w.last_seen.is_some_and(|t| now.micros_since(t) <= stale_us);
            online |= u8::from(fresh) << i;
            if fault != Fault::None {
                continue;
            }
            // A drive being configured (CiA 402) owes no feedback yet.
            let configuring = self.drive.wheel_configuring(i);
            fault = match w.last_seen {
                None if !configuring && now.micros_since(boot) > boot_us => Fault::MotorMissing,
                Some(_) if !fresh && !configuring => Fault::MotorStale,
                _ => self.drive.wheel_fault(i, enabled),
            };
        }
        self.online = online;
        let watched = self.watch_drive(now);
        if fault == Fault::None {
            fault = watched;
        }
        if fault != Fault::None
            && matches!(
                self.state,
                RobotState::Disabled | RobotState::Enabled | RobotState::WheelTest
            )
        {
            self.end_test(TestOutcome::Fault);
            self.state = RobotState::Fault;
            self.fault = fault;
            self.halt();
        }
    }
}
