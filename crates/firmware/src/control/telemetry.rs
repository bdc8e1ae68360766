//! What the core reports: the frames it sends at their rates (odometry and slip, status and its
//! counters, the heartbeat, a wheel test's result), and the [`Snapshot`] logs and tests read.

use kinematics::{ChassisVelocity, Pose2, WheelSpeeds};

use super::{Controller, Instant, Outbox, push};
use crate::protocol::RxErrorCounters;
use crate::protocol::robot::{self, Fault, HeadingSource, OdometrySource, RobotState};

/// Which of the robot's frames at their own rates a step owes.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Due {
    /// Odometry (and the slip, with pods).
    pub(super) odom: bool,
    /// Status, its counters and the heartbeat.
    pub(super) status: bool,
}

impl Due {
    /// What either owes.
    pub(super) fn or(self, other: Self) -> Self {
        Self {
            odom: self.odom || other.odom,
            status: self.status || other.status,
        }
    }
}

/// Snapshot of the controller for logs and tests.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Snapshot {
    /// State.
    pub state: RobotState,
    /// Current fault, or the reason of the last watchdog stop.
    pub fault: Fault,
    /// Odometry pose.
    pub pose: Pose2<f32>,
    /// Body velocity measured by the wheels (forward kinematics; the gyro's yaw rate while
    /// it gives the heading).
    pub measured: ChassisVelocity<f32>,
    /// Body velocity being commanded after acceleration limits.
    pub commanded: ChassisVelocity<f32>,
    /// Wheel speed setpoints, rad/s.
    pub wheel_setpoints: WheelSpeeds<f32, 4>,
    /// Measured wheel speeds, rad/s.
    pub wheel_speeds: WheelSpeeds<f32, 4>,
    /// Wheel angles since the start, rad (robot-forward positive), as the odometry
    /// integrated them (f32: about 8 mrad resolution at 65,536 rad).
    pub wheel_angles: [f32; 4],
    /// Motor currents commanded, A (current-mode drives; zero otherwise).
    pub currents: [f32; 4],
    /// Bit i set when wheel i's motor is online: its last feedback was within the
    /// staleness window at the last step.
    pub motors_online: u8,
    /// Rejected frames by kind.
    pub rx_errors: RxErrorCounters,
    /// `TWIST_CMD`s not applied because their `seq` repeated the last accepted one's
    /// (saturating; `docs/control.md`, "Command watchdog"). Not rejected frames: they
    /// decode, so `rx_errors` does not count them. Repeated `IMU_YAW_RATE` frames are
    /// counted here too.
    pub repeated_seq: u32,
    /// Where the odometry's heading came from at the last step.
    pub heading_source: HeadingSource,
    /// The gyro's estimated bias, rad/s (0 until learned, and without a gyro).
    pub gyro_bias: f32,
    /// Standstill readings in the gyro's bias estimate (at most
    /// [`GYRO_BIAS_MAX_SAMPLES`](super::GYRO_BIAS_MAX_SAMPLES)).
    pub gyro_bias_samples: u32,
    /// Where the odometry came from at the last step.
    pub odometry_source: OdometrySource,
    /// How many tracking pods are configured (0-3).
    pub pods: u8,
    /// The pods' wheel angles since the start, rad, as their counts say (the first
    /// `pods`; a silence's turns are not in them).
    pub pod_angles: [f32; crate::config::PODS_MAX],
    /// The wheels' body velocity less the pods', filtered (zero without pods, or while
    /// they are silent).
    pub slip: ChassisVelocity<f32>,
    /// Steps run.
    pub steps: u64,
}

impl Controller {
    /// Everything a log or a test wants to see.
    #[must_use]
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            state: self.state,
            fault: self.fault,
            pose: self.odometry.pose(),
            measured: self.measured,
            commanded: self.commanded,
            wheel_setpoints: self.setpoints,
            wheel_speeds: WheelSpeeds(self.wheels.map(|w| w.speed)),
            wheel_angles: self.wheels.map(|w| w.angle),
            currents: self.currents,
            motors_online: self.online,
            rx_errors: self.rx_errors,
            repeated_seq: self.repeated_seq,
            heading_source: self.gyro.source,
            gyro_bias: self.gyro.bias,
            gyro_bias_samples: self.gyro.samples,
            odometry_source: self.pods.source,
            pods: self.pods.count,
            pod_angles: self.pods.angles,
            slip: self.pods.slip,
            steps: self.steps,
        }
    }

    /// The robot's frames due at step `now`: odometry (`due.odom`), status and its counters
    /// (`due.status`, or asked for), a wheel test's result, the heartbeat (`due.status`).
    pub(super) fn emit_telemetry(
        &mut self,
        out: &mut Outbox,
        now: Instant,
        boot: Instant,
        due: Due,
    ) {
        if due.odom {
            let p = self.odometry.pose();
            let v = self.pods.velocity(self.measured);
            push(
                out,
                robot::Telemetry::OdomPosition(robot::OdomPosition { x: p.x, y: p.y })
                    .to_can_frame(),
            );
            push(
                out,
                robot::Telemetry::OdomVelocity(robot::OdomVelocity {
                    heading: p.heading,
                    vx: v.vx,
                    vy: v.vy,
                    wz: v.wz,
                })
                .to_can_frame(),
            );
            if self.pods.configured() {
                let s = self.pods.slip;
                push(
                    out,
                    robot::Telemetry::OdomSlip(robot::OdomSlip {
                        vx: s.vx,
                        vy: s.vy,
                        wz: s.wz,
                        source: self.pods.source,
                    })
                    .to_can_frame(),
                );
            }
        }
        if due.status || self.status_requested {
            self.status_requested = false;
            let e = &self.rx_errors;
            let sat = |n: u32| u16::try_from(n).unwrap_or(u16::MAX);
            push(
                out,
                robot::Telemetry::Status(robot::Status {
                    state: self.state,
                    fault: self.fault,
                    rx_errors: sat(e.total().saturating_sub(e.unknown_id)),
                    unknown_ids: sat(e.unknown_id),
                    motors_online: self.online,
                    heading_source: self.gyro.source,
                    seq: self.status_seq,
                })
                .to_can_frame(),
            );
            self.status_seq = self.status_seq.wrapping_add(1);
            // Right after STATUS, which has no room left for them.
            push(
                out,
                robot::Telemetry::StatusCounters(robot::StatusCounters {
                    repeated_seq: sat(self.repeated_seq),
                    wrong_dlc: sat(e.wrong_dlc),
                    out_of_range: sat(e.out_of_range),
                    non_finite: sat(e.non_finite),
                })
                .to_can_frame(),
            );
        }
        if let Some(r) = self.test_result.take() {
            push(out, robot::Telemetry::WheelTestResult(r).to_can_frame());
        }
        if due.status {
            let uptime_ms = now.micros_since(boot) / 1000;
            push(
                out,
                robot::Telemetry::Heartbeat(robot::Heartbeat {
                    // Wraps after 49.7 days, as the DBC says (a host checks that it advances).
                    uptime_ms: uptime_ms as u32,
                    state: self.state,
                    protocol_version: robot::PROTOCOL_VERSION,
                    config_id: self.config_id,
                })
                .to_can_frame(),
            );
        }
    }
}
