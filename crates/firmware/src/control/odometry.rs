//! Odometry: each step's wheel increments through the forward kinematics onto the SE(2) pose,
//! the rotation taken from the gyro (`IMU_YAW_RATE`, less its learned bias) while one is
//! configured and alive (`docs/control.md`, "Gyro heading").

use kinematics::{ChassisVelocity, WheelDeltas, WheelSpeeds};

use super::{Controller, Instant};
use crate::config::HeadingMode;
use crate::protocol::robot::{HeadingSource, ImuYawRate, RobotState};

/// A wheel turning slower than this (either way) is at rest for the gyro's bias estimate,
/// rad/s: 3.8 mm/s at the rim of a 76 mm wheel.
pub const STANDSTILL_WHEEL_SPEED: f32 = 0.05;
/// The gyro's bias estimate is the running mean of its standstill readings up to this many,
/// then an exponential average with this weight.
pub const GYRO_BIAS_MAX_SAMPLES: u32 = 2000;

/// The gyro (`IMU_YAW_RATE`), its bias estimate and the standstill that feeds it.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Gyro {
    /// Latest accepted yaw rate, bias included, rad/s.
    rate: f32,
    /// Arrival of the latest accepted frame (never moved back).
    last_at: Option<Instant>,
    /// `seq` of the latest accepted frame; `None`: the next is accepted whatever its `seq`.
    last_seq: Option<u8>,
    /// Bias estimate, rad/s.
    pub(super) bias: f32,
    /// Readings in the estimate, at most [`GYRO_BIAS_MAX_SAMPLES`].
    pub(super) samples: u32,
    /// Since when the robot stands still, as of the last step; `None` while it does not.
    still_since: Option<Instant>,
    /// The heading source of the last step.
    pub(super) source: HeadingSource,
}

impl Controller {
    /// Takes a valid `IMU_YAW_RATE`: the gyro's latest rate, and a bias sample while the
    /// robot has stood still long enough (since before the last step, and still now).
    pub(super) fn on_gyro(&mut self, now: Instant, g: ImuYawRate) {
        // Still standing still now: no twist accepted and no wheel turning since the step.
        let still = self.standing_still();
        let o = &self.config.odometry;
        let gyro = &mut self.gyro;
        if gyro.last_seq == Some(g.seq) {
            // The same frame again (a stuck node or gateway): not a sign of life.
            self.repeated_seq = self.repeated_seq.saturating_add(1);
            return;
        }
        gyro.last_seq = Some(g.seq);
        gyro.rate = g.yaw_rate;
        gyro.last_at = Some(now.mark(gyro.last_at));
        let settle_us = u64::from(o.gyro_standstill_ms) * 1000;
        let settled = still
            && gyro
                .still_since
                .is_some_and(|t| now.micros_since(t) >= settle_us);
        if settled && o.gyro_bias_estimation && o.heading_source == HeadingMode::Gyro {
            gyro.samples = (gyro.samples + 1).min(GYRO_BIAS_MAX_SAMPLES);
            gyro.bias += (g.yaw_rate - gyro.bias) / gyro.samples as f32;
        }
    }

    /// With a gyro configured: whether it is alive (the heading source of this step), and
    /// whether the robot stands still (for the bias estimate).
    pub(super) fn update_gyro(&mut self, now: Instant) {
        let o = &self.config.odometry;
        if o.heading_source == HeadingMode::Wheels {
            return;
        }
        let timeout_us = u64::from(o.gyro_timeout_ms) * 1000;
        let alive = self
            .gyro
            .last_at
            .is_some_and(|t| now.micros_since(t) <= timeout_us);
        // `last_seq` is kept through a silence: a node stuck on one frame stays silent. A
        // restarted node loses at most its first frame (if its `seq` happens to repeat).
        self.gyro.source = if alive {
            HeadingSource::Gyro
        } else {
            HeadingSource::WheelsGyroSilent
        };
        self.gyro.still_since = if self.online == 0b1111 && self.standing_still() {
            Some(self.gyro.still_since.unwrap_or(now))
        } else {
            None
        };
    }

    /// No motion commanded (not enabled, or a zero target and a zero commanded twist) and
    /// every wheel's latest speed below [`STANDSTILL_WHEEL_SPEED`].
    fn standing_still(&self) -> bool {
        let zero = ChassisVelocity::default();
        let commanded =
            self.state == RobotState::Enabled && (self.target != zero || self.commanded != zero);
        !commanded
            && self
                .wheels
                .iter()
                .all(|w| w.speed.abs() <= STANDSTILL_WHEEL_SPEED)
    }

    /// Moves the pose by the step's wheel increments (and the gyro's rotation), or by the
    /// pods' increments when they give the odometry, and measures the body's velocity from
    /// the wheels' speeds.
    pub(super) fn integrate_odometry(&mut self) {
        let deltas = WheelDeltas(self.wheels.map(|w| w.pending));
        for w in &mut self.wheels {
            w.angle += w.pending;
            w.pending = 0.0;
        }
        let wheels = self.kin.forward(&WheelSpeeds(self.wheels.map(|w| w.speed)));
        self.measured = wheels;
        let gyro = self.gyro.source == HeadingSource::Gyro;
        let rate = self.gyro.rate - self.gyro.bias;
        if gyro {
            self.measured.wz = rate;
        }
        let mut step = self.kin.displacement(&deltas);
        if self.pods.configured() {
            let heading = if gyro { rate * self.dt } else { step.dtheta };
            if self.integrate_pods(step, heading, wheels) {
                return;
            }
        }
        if gyro {
            // The wheels' translation, the gyro's rotation.
            step.dtheta = rate * self.dt;
        }
        self.odometry.apply(step);
    }
}
