//! What the host asks: the robot's commands (twist, mode, e-stop, status request), the
//! command watchdog and the acceleration limits that shape the commanded twist
//! (`docs/control.md`, "States" and "Command watchdog").

use kinematics::{ChassisVelocity, Real};

use super::{Controller, Instant};
use crate::config::Limits;
use crate::protocol::DecodeError;
use crate::protocol::robot::{Command, Fault, ModeRequest, RobotState, TestOutcome, TwistCmd};

impl Controller {
    /// Takes one decoded command.
    #[inline]
    pub(super) fn on_command(&mut self, now: Instant, cmd: Command) -> Result<(), DecodeError> {
        match cmd {
            Command::Estop => {
                self.end_test(TestOutcome::Stopped);
                self.state = RobotState::Estop;
                self.halt();
            }
            Command::Twist(t) => {
                let v = ChassisVelocity::new(t.vx, t.vy, t.wz);
                // `target` only ever holds zero or a twist that passed `check_twist` under
                // the same (fixed) limits, so a twist equal to it passes too: a stream that
                // holds one setpoint skips the check.
                let v = if v == self.target {
                    v
                } else {
                    self.check_twist(t)?
                };
                if self.last_seq == Some(t.seq) {
                    // The same frame again (a stuck host, adapter or gateway): not a command.
                    self.repeated_seq = self.repeated_seq.saturating_add(1);
                } else if self.state == RobotState::Enabled && !self.stopping {
                    self.target = v;
                    self.last_seq = Some(t.seq);
                    self.last_command = Some(now.mark(self.last_command));
                }
            }
            Command::Mode(ModeRequest::Enable) => {
                if self.state == RobotState::Disabled {
                    self.state = RobotState::Enabled;
                    self.fault = Fault::None;
                    self.halt();
                    // A new session: its first twist is accepted whatever its seq.
                    self.last_seq = None;
                    self.drive.request_closed_loop(now, None);
                }
            }
            Command::Mode(ModeRequest::Disable) => {
                if matches!(self.state, RobotState::Enabled | RobotState::WheelTest) {
                    self.end_test(TestOutcome::Stopped);
                    self.state = RobotState::Disabled;
                    self.halt();
                }
            }
            Command::Mode(ModeRequest::Reset) => {
                if matches!(self.state, RobotState::Fault | RobotState::Estop) {
                    self.state = RobotState::Disabled;
                    self.fault = Fault::None;
                    self.halt();
                    self.last_seq = None;
                    self.drive.clear_errors(now);
                }
            }
            Command::StatusRequest => self.status_requested = true,
            Command::ImuYawRate(g) => self.on_gyro(now, g),
            Command::PodCounts(c) => self.on_pods(now, c),
            Command::WheelTest(t) => self.start_test(now, t),
        }
        Ok(())
    }

    /// Rejects twists beyond the configured limits (the decoder already rejected the rest).
    #[inline]
    fn check_twist(&self, t: TwistCmd) -> Result<ChassisVelocity<f32>, DecodeError> {
        let l = &self.config.limits;
        let speed = (t.vx * t.vx + t.vy * t.vy).sqrt_libm();
        for (field, v) in [("vx", t.vx), ("vy", t.vy), ("wz", t.wz)] {
            if !v.is_finite() {
                return Err(DecodeError::NonFinite {
                    field,
                    bits: v.to_bits(),
                });
            }
        }
        if speed > l.max_linear_speed {
            return Err(DecodeError::OutOfRange {
                field: "vx,vy",
                value: (speed * 1000.0) as i64,
            });
        }
        if t.wz.abs() > l.max_angular_speed {
            return Err(DecodeError::OutOfRange {
                field: "wz",
                value: (t.wz * 1000.0) as i64,
            });
        }
        Ok(ChassisVelocity::new(t.vx, t.vy, t.wz))
    }

    /// Drops every motion target and the watchdog; the motors get zero on the next step.
    pub(super) fn halt(&mut self) {
        self.target = ChassisVelocity::default();
        self.commanded = ChassisVelocity::default();
        self.last_command = None;
        self.stopping = false;
        self.drive.halt(self.state);
    }

    /// Starts the watchdog's stop when the last accepted twist is too old.
    pub(super) fn run_watchdog(&mut self, now: Instant) {
        if self.state != RobotState::Enabled || self.stopping {
            return;
        }
        let timeout_us = u64::from(self.config.timing.command_timeout_ms) * 1000;
        if let Some(last) = self.last_command
            && now.micros_since(last) > timeout_us
        {
            self.stopping = true;
            self.fault = Fault::Watchdog;
            self.target = ChassisVelocity::default();
        }
    }

    /// Moves the commanded twist towards the target within the acceleration limits (the stop
    /// deceleration while the watchdog stop runs), and completes a watchdog stop.
    pub(super) fn ramp(&mut self) {
        if self.state != RobotState::Enabled {
            self.commanded = ChassisVelocity::default();
            return;
        }
        let l: &Limits = &self.config.limits;
        let (lin, ang) = if self.stopping {
            (l.stop_linear_decel, l.stop_angular_decel)
        } else {
            (l.max_linear_accel, l.max_angular_accel)
        };
        let (dvx, dvy) = (
            self.target.vx - self.commanded.vx,
            self.target.vy - self.commanded.vy,
        );
        // At the target already (the common case): the same zero without the square root.
        let dv = if dvx == 0.0 && dvy == 0.0 {
            0.0
        } else {
            (dvx * dvx + dvy * dvy).sqrt_libm()
        };
        let max_dv = lin * self.dt;
        if dv <= max_dv {
            self.commanded.vx = self.target.vx;
            self.commanded.vy = self.target.vy;
        } else {
            let k = max_dv / dv;
            self.commanded.vx += dvx * k;
            self.commanded.vy += dvy * k;
        }
        let dw = self.target.wz - self.commanded.wz;
        let max_dw = ang * self.dt;
        self.commanded.wz = if dw.abs() <= max_dw {
            self.target.wz
        } else {
            self.commanded.wz + max_dw.copysign(dw)
        };
        if self.stopping && self.commanded == ChassisVelocity::default() {
            // Stop complete: disable, keep `Watchdog` as the reason until the next enable.
            self.state = RobotState::Disabled;
            self.stopping = false;
            self.last_command = None;
            self.drive.halt(RobotState::Disabled);
        }
    }
}
