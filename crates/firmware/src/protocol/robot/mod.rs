//! The robot's own protocol: twist setpoints (and an optional gyro's yaw rate) in; odometry,
//! status, counters and heartbeat out.
//!
//! Defined by `dbc/mecanum_robot.dbc` (the file is the specification; this module follows
//! it): CAN 2.0A standard ids in the block `0x300..=0x31F` ([`in_block`]), little-endian
//! fields. [`layout`] mirrors the DBC; [`Command`] is what the host (and an IMU or pod node)
//! sends,
//! [`Telemetry`] what the robot sends, [`decode`] reads either; [`PROTOCOL_VERSION`] is the
//! version implemented. The message table, the alive counters (`TWIST_CMD.seq`,
//! `IMU_YAW_RATE.seq`), the gyro's heading source, the wheel test and `STATUS_COUNTERS` are
//! specified in `docs/protocol.md`, section "Robot protocol".
//!
//! # Encoding and decoding
//!
//! Messages hold SI values ([`TwistCmd`] in m/s and rad/s, ...). Encoding rounds to the
//! nearest raw value and saturates at the field's range; a NaN is sent as 0 and infinities
//! saturate, so encoding never fails and never panics. Decoding returns SI values or a
//! [`DecodeError`].

use embedded_can::{Frame, StandardId};

use super::error::DecodeError;
use super::wire::{self, Payload};
use crate::frame::CanFrame;

/// The protocol version this module implements, sent in [`Heartbeat::protocol_version`].
///
/// Version 8 added `STATUS.fault` 13 (`DRIVE_NMT`): a CANopen drive's heartbeat reports an
/// NMT state other than operational; a version 7 receiver rejects it.
/// Version 7 added the optional `POD_COUNTS` (a tracking-pod node's counts) and
/// `ODOM_SLIP` (the odometry source and the slip estimate); a robot configured without pods
/// neither expects nor sends either.
/// Version 6 added `STATUS.fault` 9-12 (`DRIVE_SILENT`, `DRIVE_REBOOTED`, `DRIVE_SETUP`,
/// `DRIVE_TRANSITION`), the faults of CANopen drives; a version 5 receiver rejects them.
/// Version 5 sends the id of the robot's configuration ([`Config::id`](crate::Config::id))
/// in `HEARTBEAT.config_id`, reserved (0) before.
/// Version 4 added `STATUS.state` 4 (`WHEEL_TEST`) with `WHEEL_TEST` and `WHEEL_TEST_RESULT`,
/// and `STATUS.fault` 7 (`WHEEL_RUNAWAY`) and 8 (`WHEEL_FIGHT`); a version 3 receiver
/// rejects those values.
/// Version 3 made `TWIST_CMD.seq` an alive counter (a repeated `seq` is not applied) and
/// added `STATUS_COUNTERS`; a version 2 host that sends one `seq` forever stops the robot
/// after one command timeout. Version 2 added `STATUS.fault` 6 (`ENCODER_STUCK`); a version
/// 1 receiver rejects it.
pub const PROTOCOL_VERSION: u8 = 8;

pub mod layout;

u8_enum!(
    /// What the host asks the robot to do with its enable latch (`MODE_CMD.request`).
    ModeRequest {
        /// Stop and disable.
        Disable = 0 => "DISABLE",
        /// Enable (motion needs a fresh twist command afterwards).
        Enable = 1 => "ENABLE",
        /// Clear a fault or the e-stop latch; the robot ends up disabled.
        Reset = 2 => "RESET",
    }
);

u8_enum!(
    /// The robot's state (`STATUS.state`, `HEARTBEAT.state`).
    RobotState {
        /// Motors off; waiting for an enable.
        Disabled = 0 => "DISABLED",
        /// Following twist commands.
        Enabled = 1 => "ENABLED",
        /// Stopped by a fault (see [`Fault`]); needs a reset.
        Fault = 2 => "FAULT",
        /// Stopped by an e-stop; needs a reset.
        Estop = 3 => "ESTOP",
        /// Driving one wheel for the bring-up check (`WHEEL_TEST`); back to `Disabled` when it
        /// ends.
        WheelTest = 4 => "WHEEL_TEST",
    }
);

u8_enum!(
    /// The latest fault (`STATUS.fault`). Raw values 14..=255 are reserved for later versions.
    ///
    /// How each is detected, and how fast: [`crate::control`].
    Fault {
        /// No fault.
        None = 0 => "NONE",
        /// A motor's feedback stopped arriving in time.
        MotorStale = 1 => "MOTOR_STALE",
        /// A motor never reported.
        MotorMissing = 2 => "MOTOR_MISSING",
        /// A drive reported an error.
        DriveError = 3 => "DRIVE_ERROR",
        /// Informational: the command watchdog expired and the robot stopped.
        Watchdog = 4 => "WATCHDOG",
        /// The configuration was rejected.
        Config = 5 => "CONFIG",
        /// A motor's feedback keeps arriving but its rotor angle does not move while the motor
        /// reports speed, or while it is driven hard and the other wheels say it turns.
        EncoderStuck = 6 => "ENCODER_STUCK",
        /// A wheel driven at its current limit towards its setpoint turned the other way, or
        /// further from it, for a window: a motor mounted the other way than configured, or
        /// drives wired to the wrong wheels.
        WheelRunaway = 7 => "WHEEL_RUNAWAY",
        /// The wheels pushed against each other for a window: the currents had a part that no
        /// body motion explains, as when a motor is mounted the other way than configured.
        WheelFight = 8 => "WHEEL_FIGHT",
        /// A CANopen drive's heartbeat was silent for its consumer time.
        DriveSilent = 9 => "DRIVE_SILENT",
        /// A CANopen drive booted again after it was configured: it is configured again, and
        /// the robot does not move until the host resets and enables it.
        DriveRebooted = 10 => "DRIVE_REBOOTED",
        /// A CANopen drive refused (SDO abort) or did not answer (timeout) its configuration,
        /// or is not a CiA 402 drive.
        DriveSetup = 11 => "DRIVE_SETUP",
        /// A CANopen drive did not reach the state an enable step asked for in time.
        DriveTransition = 12 => "DRIVE_TRANSITION",
        /// A started CANopen drive's heartbeat reports an NMT state other than operational
        /// (pre-operational after a communication error, stopped): it takes no targets; the
        /// host's reset starts it again.
        DriveNmt = 13 => "DRIVE_NMT",
    }
);

u8_enum!(
    /// Where the odometry's heading comes from (`STATUS.heading_source`).
    #[derive(Default)]
    HeadingSource {
        /// The wheels: the robot is configured without a gyro (`heading_source = "wheels"`).
        #[default]
        Wheels = 0 => "WHEELS",
        /// The gyro (`IMU_YAW_RATE`), less its estimated bias.
        Gyro = 1 => "GYRO",
        /// The wheels, although the robot is configured for the gyro: no valid `IMU_YAW_RATE`
        /// within the gyro timeout (or none yet). A warning, not a fault: the robot keeps
        /// driving, and takes the gyro again as soon as a valid frame arrives.
        WheelsGyroSilent = 2 => "WHEELS_GYRO_SILENT",
    }
);

u8_enum!(
    /// Where the odometry comes from (`ODOM_SLIP.source`, version 7).
    #[derive(Default)]
    OdometrySource {
        /// The wheels (and the gyro's rotation, as `STATUS.heading_source` says): the robot is
        /// configured without pods. Never sent: such a robot sends no `ODOM_SLIP`.
        #[default]
        Wheels = 0 => "WHEELS",
        /// Two pods' translation, the gyro's rotation (the wheels' while the gyro is silent).
        Pods2Gyro = 1 => "PODS2_GYRO",
        /// Three pods: translation and rotation.
        Pods3 = 2 => "PODS3",
        /// The wheels, although the robot is configured for pods: no valid `POD_COUNTS` within
        /// the pod timeout (or none yet). A warning, not a fault; the pods take over again from
        /// the second valid frame (the first sets their baseline).
        WheelsPodsSilent = 3 => "WHEELS_PODS_SILENT",
    }
);

/// A twist setpoint (`TWIST_CMD`), body frame.
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct TwistCmd {
    /// Forward velocity, m/s (±32.767, LSB 0.001).
    pub vx: f32,
    /// Leftward velocity, m/s (±32.767, LSB 0.001).
    pub vy: f32,
    /// Yaw rate, counter-clockwise positive, rad/s (±32.767, LSB 0.001).
    pub wz: f32,
    /// Alive counter set by the host: one more (mod 256, or any other new value) in every
    /// twist it sends. A repeat of the last accepted one is not applied (see
    /// `docs/protocol.md`, section "Robot protocol").
    pub seq: u8,
}

/// A gyro's yaw rate (`IMU_YAW_RATE`), from an IMU node.
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct ImuYawRate {
    /// Yaw rate about the body z axis, counter-clockwise positive, rad/s, as the gyro
    /// measures it (bias included); finite, within ±35 rad/s.
    pub yaw_rate: f32,
    /// Alive counter set by the IMU node: one more (mod 256) in every frame. A repeat of the
    /// last accepted one is not used.
    pub seq: u8,
}

/// The tracking pods' encoder counts (`POD_COUNTS`, version 7), from a pod node.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct PodCounts {
    /// Each pod's count, wrapping mod 65536; with two pods the third is sent as 0 and ignored.
    pub counts: [u16; layout::PODS_MAX],
    /// Alive counter set by the pod node: one more (mod 256) in every frame. A repeat of the
    /// last accepted one is not used.
    pub seq: u8,
}

/// Drive one wheel for the bring-up check (`WHEEL_TEST`): only a disabled robot does.
#[derive(Clone, Copy, PartialEq, Debug)]
pub struct WheelTest {
    /// The wheel, 0-3 (FL, FR, RL, RR).
    pub wheel: u8,
    /// Wheel speed setpoint, rad/s, robot-forward positive; `|speed| <= 10` (LSB 0.001).
    pub speed: f32,
    /// How long, ms (1-3000).
    pub duration_ms: u16,
}

u8_enum!(
    /// How a wheel test ended (`WHEEL_TEST_RESULT.outcome`).
    TestOutcome {
        /// It ran for its duration.
        Done = 0 => "DONE",
        /// `MODE_CMD` disable or `ESTOP` ended it early.
        Stopped = 1 => "STOPPED",
        /// A fault ended it (`STATUS.fault` says which).
        Fault = 2 => "FAULT",
        /// Not run: the robot was not disabled.
        Refused = 3 => "REFUSED",
    }
);

/// The end of a wheel test (`WHEEL_TEST_RESULT`).
#[derive(Clone, Copy, PartialEq, Debug)]
pub struct WheelTestResult {
    /// The wheel tested, 0-3.
    pub wheel: u8,
    /// How it ended.
    pub outcome: TestOutcome,
    /// How far the wheel's encoder says it turned, rad, robot-forward positive as configured
    /// (LSB 0.001, saturating at ±32.767).
    pub angle: f32,
    /// The largest current commanded, A, signed (LSB 0.01; 0 for velocity-mode drives).
    pub peak_current: f32,
}

/// A message from the host (or another node, such as an IMU) to the robot.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Command {
    /// `ESTOP`: stop now and latch until a reset.
    Estop,
    /// `TWIST_CMD`: a velocity setpoint.
    Twist(TwistCmd),
    /// `MODE_CMD`: enable, disable or reset.
    Mode(ModeRequest),
    /// `STATUS_REQ`: send a `STATUS` now. Not a motion command.
    StatusRequest,
    /// `IMU_YAW_RATE`: the gyro's yaw rate. Not a motion command.
    ImuYawRate(ImuYawRate),
    /// `WHEEL_TEST`: drive one wheel for the bring-up check.
    WheelTest(WheelTest),
    /// `POD_COUNTS`: the tracking pods' counts. Not a motion command.
    PodCounts(PodCounts),
}

/// Odometry pose position (`ODOM_POSITION`), odometry frame.
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct OdomPosition {
    /// x, m (LSB 0.0001).
    pub x: f32,
    /// y, m (LSB 0.0001).
    pub y: f32,
}

/// Heading and measured body velocity (`ODOM_VELOCITY`).
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct OdomVelocity {
    /// Heading in the odometry frame, rad in `-π..=π` (LSB 0.0001); encoding wraps it.
    pub heading: f32,
    /// Forward velocity, m/s (LSB 0.001).
    pub vx: f32,
    /// Leftward velocity, m/s (LSB 0.001).
    pub vy: f32,
    /// Yaw rate, rad/s (LSB 0.001).
    pub wz: f32,
}

/// The odometry source and the slip estimate (`ODOM_SLIP`, version 7): the wheels' body
/// velocity less the pods', filtered.
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct OdomSlip {
    /// Forward slip velocity, m/s (LSB 0.001).
    pub vx: f32,
    /// Leftward slip velocity, m/s (LSB 0.001).
    pub vy: f32,
    /// Yaw-rate difference, rad/s (LSB 0.001).
    pub wz: f32,
    /// Where the odometry comes from.
    pub source: OdometrySource,
}

/// Robot status (`STATUS`).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Status {
    /// Robot state.
    pub state: RobotState,
    /// Latest fault.
    pub fault: Fault,
    /// Count of rejected frames (saturating).
    pub rx_errors: u16,
    /// Count of frames with unknown ids (saturating).
    pub unknown_ids: u16,
    /// Bit i set = wheel i online, wheels in the order FL, FR, RL, RR. Bits 4-7 are not part
    /// of it: encoding ignores them (the wire's bits 4-7 are `heading_source`).
    pub motors_online: u8,
    /// Where the odometry's heading comes from.
    pub heading_source: HeadingSource,
    /// Rolling counter.
    pub seq: u8,
}

/// Counters of frames the robot did not use (`STATUS_COUNTERS`), each saturating at
/// `u16::MAX`; sent right after every [`Status`].
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct StatusCounters {
    /// Twists not applied because their `seq` equalled that of the last accepted twist. Not
    /// part of [`Status::rx_errors`]: those frames are well-formed.
    pub repeated_seq: u16,
    /// Rejected frames with a wrong DLC.
    pub wrong_dlc: u16,
    /// Rejected frames with a field out of range.
    pub out_of_range: u16,
    /// Rejected frames with a NaN or infinite float field.
    pub non_finite: u16,
}

/// Robot heartbeat (`HEARTBEAT`).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Heartbeat {
    /// Time since boot, ms (wraps after ~49.7 days).
    pub uptime_ms: u32,
    /// Robot state.
    pub state: RobotState,
    /// Protocol version ([`PROTOCOL_VERSION`] when sent by this crate; decoded as is).
    pub protocol_version: u8,
    /// The id of the configuration the robot runs ([`Config::id`](crate::Config::id)), so a
    /// user can tell what a board was built with.
    pub config_id: u16,
}

/// A message from the robot to the host.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Telemetry {
    /// `ODOM_POSITION`.
    OdomPosition(OdomPosition),
    /// `ODOM_VELOCITY`.
    OdomVelocity(OdomVelocity),
    /// `STATUS`.
    Status(Status),
    /// `STATUS_COUNTERS`.
    StatusCounters(StatusCounters),
    /// `HEARTBEAT`.
    Heartbeat(Heartbeat),
    /// `WHEEL_TEST_RESULT`.
    WheelTestResult(WheelTestResult),
    /// `ODOM_SLIP` (version 7).
    OdomSlip(OdomSlip),
}

/// Any message of the protocol.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Message {
    /// Host → robot.
    Command(Command),
    /// Robot → host.
    Telemetry(Telemetry),
}

/// Whether a raw 11-bit id lies in the protocol's block (`0x300..=0x31F`).
#[must_use]
pub const fn in_block(id: u16) -> bool {
    id >= layout::ID_FIRST && id <= layout::ID_LAST
}

fn sid(raw: u16) -> StandardId {
    // All ids of the layout table are below 0x800.
    StandardId::new(raw).unwrap_or(StandardId::ZERO)
}

fn state_of(raw: i64) -> RobotState {
    // Callers range-check first; the fallback is unreachable.
    u8::try_from(raw)
        .ok()
        .and_then(RobotState::from_raw)
        .unwrap_or(RobotState::Disabled)
}

/// Wraps an angle into `(-π, π]` unless it already lies within the field's range
/// (±0.0001 · 31416, a hair wider than ±π, so a decoded ±31416 re-encodes unchanged). NaN stays
/// NaN (the field encoder maps it to 0).
fn wrap_pi(angle: f32) -> f32 {
    use core::f32::consts::{PI, TAU};
    let limit = (layout::HEADING_RAW_MAX as f64 * layout::HEADING_SCALE) as f32;
    if angle.abs() <= limit {
        return angle;
    }
    let a = angle % TAU;
    if a > PI {
        a - TAU
    } else if a <= -PI {
        a + TAU
    } else {
        a
    }
}

impl Command {
    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Estop => layout::ESTOP,
            Self::Twist(_) => layout::TWIST_CMD,
            Self::Mode(_) => layout::MODE_CMD,
            Self::StatusRequest => layout::STATUS_REQ,
            Self::ImuYawRate(_) => layout::IMU_YAW_RATE,
            Self::WheelTest(_) => layout::WHEEL_TEST,
            Self::PodCounts(_) => layout::POD_COUNTS,
        }
    }

    /// Decodes a host → robot frame.
    ///
    /// # Errors
    /// See [`DecodeError`]; `UnknownId` also for robot → host ids.
    #[inline]
    pub fn decode<F: Frame>(frame: &F) -> Result<Self, DecodeError> {
        let id = wire::standard_id(frame)?;
        let def = match id {
            x if x == layout::ESTOP.id => layout::ESTOP,
            x if x == layout::TWIST_CMD.id => layout::TWIST_CMD,
            x if x == layout::MODE_CMD.id => layout::MODE_CMD,
            x if x == layout::STATUS_REQ.id => layout::STATUS_REQ,
            x if x == layout::IMU_YAW_RATE.id => layout::IMU_YAW_RATE,
            x if x == layout::WHEEL_TEST.id => layout::WHEEL_TEST,
            x if x == layout::POD_COUNTS.id => layout::POD_COUNTS,
            _ => return Err(wire::unknown(frame)),
        };
        let p = wire::data_payload(frame, id, &[def.dlc])?;
        Ok(match id {
            x if x == layout::ESTOP.id => {
                layout::ESTOP_MAGIC.checked(&p)?;
                Self::Estop
            }
            x if x == layout::TWIST_CMD.id => Self::Twist(TwistCmd {
                vx: layout::TWIST_VX.physical(&p)?,
                vy: layout::TWIST_VY.physical(&p)?,
                wz: layout::TWIST_WZ.physical(&p)?,
                seq: layout::TWIST_SEQ.raw(&p) as u8,
            }),
            x if x == layout::MODE_CMD.id => {
                let raw = layout::MODE_REQUEST.raw(&p);
                let request = u8::try_from(raw)
                    .ok()
                    .and_then(ModeRequest::from_raw)
                    .ok_or(DecodeError::OutOfRange {
                        field: layout::MODE_REQUEST.name,
                        value: raw,
                    })?;
                Self::Mode(request)
            }
            x if x == layout::IMU_YAW_RATE.id => {
                let field = layout::IMU_YAW_RATE_VALUE;
                let yaw_rate = field.finite(&p)?;
                if yaw_rate.abs() > layout::YAW_RATE_MAX {
                    return Err(DecodeError::OutOfRange {
                        field: field.name,
                        // An f32 field's raw value is its bits.
                        value: field.raw(&p),
                    });
                }
                Self::ImuYawRate(ImuYawRate {
                    yaw_rate,
                    seq: layout::IMU_SEQ.raw(&p) as u8,
                })
            }
            x if x == layout::WHEEL_TEST.id => Self::WheelTest(WheelTest {
                wheel: layout::TEST_WHEEL.checked(&p)? as u8,
                speed: layout::TEST_SPEED.physical(&p)?,
                duration_ms: layout::TEST_DURATION.checked(&p)? as u16,
            }),
            x if x == layout::POD_COUNTS.id => Self::PodCounts(PodCounts {
                counts: layout::POD_COUNT.map(|f| f.raw(&p) as u16),
                seq: layout::POD_SEQ.raw(&p) as u8,
            }),
            _ => Self::StatusRequest,
        })
    }

    /// Encodes into a [`CanFrame`] (rounding and saturating SI values).
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        let def = self.def();
        let mut p = Payload::new();
        match self {
            Self::Estop => layout::ESTOP_MAGIC.put_raw(&mut p, layout::ESTOP_MAGIC_VALUE.into()),
            Self::Twist(t) => {
                layout::TWIST_VX.put_physical(&mut p, t.vx);
                layout::TWIST_VY.put_physical(&mut p, t.vy);
                layout::TWIST_WZ.put_physical(&mut p, t.wz);
                layout::TWIST_SEQ.put_raw(&mut p, t.seq.into());
            }
            Self::Mode(m) => layout::MODE_REQUEST.put_raw(&mut p, m.raw().into()),
            Self::StatusRequest => {}
            Self::ImuYawRate(g) => {
                // NaN as 0, beyond the range (infinities too) saturated to it.
                let max = layout::YAW_RATE_MAX;
                let rate = wire::saturate_f32(g.yaw_rate).max(-max).min(max);
                layout::IMU_YAW_RATE_VALUE.put_f32(&mut p, rate);
                layout::IMU_SEQ.put_raw(&mut p, g.seq.into());
            }
            Self::WheelTest(t) => {
                layout::TEST_WHEEL.put_raw(&mut p, t.wheel.min(3).into());
                layout::TEST_SPEED.put_physical(&mut p, t.speed);
                layout::TEST_DURATION.put_raw(
                    &mut p,
                    i64::from(t.duration_ms).clamp(1, layout::TEST_DURATION_MAX_MS),
                );
            }
            Self::PodCounts(c) => {
                for (field, count) in layout::POD_COUNT.iter().zip(c.counts) {
                    field.put_raw(&mut p, count.into());
                }
                layout::POD_SEQ.put_raw(&mut p, c.seq.into());
            }
        }
        CanFrame::from_buffer(sid(def.id), p.0, def.dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
    }
}

impl Telemetry {
    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::OdomPosition(_) => layout::ODOM_POSITION,
            Self::OdomVelocity(_) => layout::ODOM_VELOCITY,
            Self::Status(_) => layout::STATUS,
            Self::StatusCounters(_) => layout::STATUS_COUNTERS,
            Self::Heartbeat(_) => layout::HEARTBEAT,
            Self::WheelTestResult(_) => layout::WHEEL_TEST_RESULT,
            Self::OdomSlip(_) => layout::ODOM_SLIP,
        }
    }

    /// Decodes a robot → host frame.
    ///
    /// # Errors
    /// See [`DecodeError`]; `UnknownId` also for host → robot ids.
    pub fn decode<F: Frame>(frame: &F) -> Result<Self, DecodeError> {
        let id = wire::standard_id(frame)?;
        let def = match id {
            x if x == layout::ODOM_POSITION.id => layout::ODOM_POSITION,
            x if x == layout::ODOM_VELOCITY.id => layout::ODOM_VELOCITY,
            x if x == layout::STATUS.id => layout::STATUS,
            x if x == layout::STATUS_COUNTERS.id => layout::STATUS_COUNTERS,
            x if x == layout::HEARTBEAT.id => layout::HEARTBEAT,
            x if x == layout::WHEEL_TEST_RESULT.id => layout::WHEEL_TEST_RESULT,
            x if x == layout::ODOM_SLIP.id => layout::ODOM_SLIP,
            _ => return Err(wire::unknown(frame)),
        };
        let p = wire::data_payload(frame, id, &[def.dlc])?;
        Ok(match id {
            x if x == layout::ODOM_POSITION.id => Self::OdomPosition(OdomPosition {
                x: layout::ODOM_X.physical(&p)?,
                y: layout::ODOM_Y.physical(&p)?,
            }),
            x if x == layout::ODOM_VELOCITY.id => Self::OdomVelocity(OdomVelocity {
                heading: layout::ODOM_HEADING.physical(&p)?,
                vx: layout::ODOM_VX.physical(&p)?,
                vy: layout::ODOM_VY.physical(&p)?,
                wz: layout::ODOM_WZ.physical(&p)?,
            }),
            x if x == layout::STATUS.id => {
                let state = state_of(layout::STATUS_STATE.checked(&p)?);
                let fault_raw = layout::STATUS_FAULT.checked(&p)?;
                let fault = u8::try_from(fault_raw)
                    .ok()
                    .and_then(Fault::from_raw)
                    .unwrap_or(Fault::None);
                Self::Status(Status {
                    state,
                    fault,
                    rx_errors: layout::STATUS_RX_ERRORS.raw(&p) as u16,
                    unknown_ids: layout::STATUS_UNKNOWN_IDS.raw(&p) as u16,
                    motors_online: layout::STATUS_MOTORS_ONLINE.raw(&p) as u8,
                    heading_source: u8::try_from(layout::STATUS_HEADING_SOURCE.checked(&p)?)
                        .ok()
                        .and_then(HeadingSource::from_raw)
                        .unwrap_or_default(),
                    seq: layout::STATUS_SEQ.raw(&p) as u8,
                })
            }
            x if x == layout::STATUS_COUNTERS.id => Self::StatusCounters(StatusCounters {
                repeated_seq: layout::COUNTERS_REPEATED_SEQ.raw(&p) as u16,
                wrong_dlc: layout::COUNTERS_WRONG_DLC.raw(&p) as u16,
                out_of_range: layout::COUNTERS_OUT_OF_RANGE.raw(&p) as u16,
                non_finite: layout::COUNTERS_NON_FINITE.raw(&p) as u16,
            }),
            x if x == layout::WHEEL_TEST_RESULT.id => {
                let raw = layout::RESULT_OUTCOME.checked(&p)?;
                Self::WheelTestResult(WheelTestResult {
                    wheel: layout::RESULT_WHEEL.checked(&p)? as u8,
                    outcome: u8::try_from(raw)
                        .ok()
                        .and_then(TestOutcome::from_raw)
                        .unwrap_or(TestOutcome::Done),
                    angle: layout::RESULT_ANGLE.physical(&p)?,
                    peak_current: layout::RESULT_PEAK_CURRENT.physical(&p)?,
                })
            }
            x if x == layout::ODOM_SLIP.id => Self::OdomSlip(OdomSlip {
                vx: layout::SLIP_VX.physical(&p)?,
                vy: layout::SLIP_VY.physical(&p)?,
                wz: layout::SLIP_WZ.physical(&p)?,
                source: u8::try_from(layout::SLIP_SOURCE.checked(&p)?)
                    .ok()
                    .and_then(OdometrySource::from_raw)
                    .unwrap_or_default(),
            }),
            _ => Self::Heartbeat(Heartbeat {
                uptime_ms: layout::HEARTBEAT_UPTIME.raw(&p) as u32,
                state: state_of(layout::HEARTBEAT_STATE.checked(&p)?),
                protocol_version: layout::HEARTBEAT_VERSION.raw(&p) as u8,
                config_id: layout::HEARTBEAT_CONFIG_ID.raw(&p) as u16,
            }),
        })
    }

    /// Encodes into a [`CanFrame`] (rounding and saturating SI values, wrapping the heading).
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        let def = self.def();
        let mut p = Payload::new();
        match self {
            Self::OdomPosition(o) => {
                layout::ODOM_X.put_physical(&mut p, o.x);
                layout::ODOM_Y.put_physical(&mut p, o.y);
            }
            Self::OdomVelocity(o) => {
                layout::ODOM_HEADING.put_physical(&mut p, wrap_pi(o.heading));
                layout::ODOM_VX.put_physical(&mut p, o.vx);
                layout::ODOM_VY.put_physical(&mut p, o.vy);
                layout::ODOM_WZ.put_physical(&mut p, o.wz);
            }
            Self::Status(s) => {
                layout::STATUS_STATE.put_raw(&mut p, s.state.raw().into());
                layout::STATUS_FAULT.put_raw(&mut p, s.fault.raw().into());
                layout::STATUS_RX_ERRORS.put_raw(&mut p, s.rx_errors.into());
                layout::STATUS_UNKNOWN_IDS.put_raw(&mut p, s.unknown_ids.into());
                layout::STATUS_MOTORS_ONLINE.put_raw(
                    &mut p,
                    (s.motors_online & layout::MOTORS_ONLINE_MASK).into(),
                );
                layout::STATUS_HEADING_SOURCE.put_raw(&mut p, s.heading_source.raw().into());
                layout::STATUS_SEQ.put_raw(&mut p, s.seq.into());
            }
            Self::StatusCounters(c) => {
                layout::COUNTERS_REPEATED_SEQ.put_raw(&mut p, c.repeated_seq.into());
                layout::COUNTERS_WRONG_DLC.put_raw(&mut p, c.wrong_dlc.into());
                layout::COUNTERS_OUT_OF_RANGE.put_raw(&mut p, c.out_of_range.into());
                layout::COUNTERS_NON_FINITE.put_raw(&mut p, c.non_finite.into());
            }
            Self::Heartbeat(h) => {
                layout::HEARTBEAT_UPTIME.put_raw(&mut p, h.uptime_ms.into());
                layout::HEARTBEAT_STATE.put_raw(&mut p, h.state.raw().into());
                layout::HEARTBEAT_VERSION.put_raw(&mut p, h.protocol_version.into());
                layout::HEARTBEAT_CONFIG_ID.put_raw(&mut p, h.config_id.into());
            }
            Self::WheelTestResult(r) => {
                layout::RESULT_WHEEL.put_raw(&mut p, r.wheel.min(3).into());
                layout::RESULT_OUTCOME.put_raw(&mut p, r.outcome.raw().into());
                layout::RESULT_ANGLE.put_physical(&mut p, r.angle);
                layout::RESULT_PEAK_CURRENT.put_physical(&mut p, r.peak_current);
            }
            Self::OdomSlip(s) => {
                layout::SLIP_VX.put_physical(&mut p, s.vx);
                layout::SLIP_VY.put_physical(&mut p, s.vy);
                layout::SLIP_WZ.put_physical(&mut p, s.wz);
                layout::SLIP_SOURCE.put_raw(&mut p, s.source.raw().into());
            }
        }
        CanFrame::from_buffer(sid(def.id), p.0, def.dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
    }
}

impl Message {
    /// Encodes into a [`CanFrame`].
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        match self {
            Self::Command(c) => c.to_can_frame(),
            Self::Telemetry(t) => t.to_can_frame(),
        }
    }

    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Command(c) => c.def(),
            Self::Telemetry(t) => t.def(),
        }
    }
}

/// Decodes any frame of the protocol, in either direction.
///
/// # Errors
/// See [`DecodeError`].
pub fn decode<F: Frame>(frame: &F) -> Result<Message, DecodeError> {
    match Command::decode(frame) {
        Err(DecodeError::UnknownId { .. }) => Telemetry::decode(frame).map(Message::Telemetry),
        other => other.map(Message::Command),
    }
}
