//! The frame layout: the Rust mirror of `dbc/mecanum_robot.dbc`. Every id, DLC, offset,
//! scale and range the codec uses is here.

use crate::protocol::wire::{ByteOrder::Little, Field, MessageDef, WireType::*};

/// First id of the block.
pub const ID_FIRST: u16 = 0x300;
/// Last id of the block.
pub const ID_LAST: u16 = 0x31F;

/// `ESTOP`, host → robot.
pub const ESTOP: MessageDef = MessageDef::new("ESTOP", 0x300, 1);
/// `TWIST_CMD`, host → robot.
pub const TWIST_CMD: MessageDef = MessageDef::new("TWIST_CMD", 0x301, 8);
/// `MODE_CMD`, host → robot.
pub const MODE_CMD: MessageDef = MessageDef::new("MODE_CMD", 0x302, 1);
/// `STATUS_REQ`, host → robot.
pub const STATUS_REQ: MessageDef = MessageDef::new("STATUS_REQ", 0x303, 0);
/// `IMU_YAW_RATE`, IMU node → robot.
pub const IMU_YAW_RATE: MessageDef = MessageDef::new("IMU_YAW_RATE", 0x304, 8);
/// `WHEEL_TEST`, host → robot.
pub const WHEEL_TEST: MessageDef = MessageDef::new("WHEEL_TEST", 0x305, 8);
/// `POD_COUNTS`, pod node → robot (version 7).
pub const POD_COUNTS: MessageDef = MessageDef::new("POD_COUNTS", 0x306, 8);
/// `ODOM_POSITION`, robot → host.
pub const ODOM_POSITION: MessageDef = MessageDef::new("ODOM_POSITION", 0x310, 8);
/// `ODOM_VELOCITY`, robot → host.
pub const ODOM_VELOCITY: MessageDef = MessageDef::new("ODOM_VELOCITY", 0x311, 8);
/// `STATUS`, robot → host.
pub const STATUS: MessageDef = MessageDef::new("STATUS", 0x312, 8);
/// `STATUS_COUNTERS`, robot → host (sent with every `STATUS`).
pub const STATUS_COUNTERS: MessageDef = MessageDef::new("STATUS_COUNTERS", 0x313, 8);
/// `WHEEL_TEST_RESULT`, robot → host.
pub const WHEEL_TEST_RESULT: MessageDef = MessageDef::new("WHEEL_TEST_RESULT", 0x314, 8);
/// `ODOM_SLIP`, robot → host (version 7, only with pods configured).
pub const ODOM_SLIP: MessageDef = MessageDef::new("ODOM_SLIP", 0x315, 8);
/// `HEARTBEAT`, robot → host.
pub const HEARTBEAT: MessageDef = MessageDef::new("HEARTBEAT", 0x31F, 8);

/// The e-stop magic byte.
pub const ESTOP_MAGIC_VALUE: u8 = 0xE5;
/// `ESTOP.magic`: only [`ESTOP_MAGIC_VALUE`] is accepted.
pub const ESTOP_MAGIC: Field =
    Field::int("magic", 0, U8, Little).range(ESTOP_MAGIC_VALUE as i64, ESTOP_MAGIC_VALUE as i64);

/// Linear velocity LSB, m/s.
pub const LINEAR_SCALE: f64 = 0.001;
/// Angular velocity LSB, rad/s.
pub const ANGULAR_SCALE: f64 = 0.001;
/// Symmetric raw limit of the i16 velocity fields (-32768 is reserved).
pub const VEL_RAW_MAX: i64 = 32767;

/// `TWIST_CMD.vx`, m/s.
pub const TWIST_VX: Field = Field::int("vx", 0, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `TWIST_CMD.vy`, m/s.
pub const TWIST_VY: Field = Field::int("vy", 2, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `TWIST_CMD.wz`, rad/s.
pub const TWIST_WZ: Field = Field::int("wz", 4, I16, Little)
    .scaled(ANGULAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `TWIST_CMD.seq`, alive counter (see `docs/protocol.md`, section "Robot protocol").
pub const TWIST_SEQ: Field = Field::int("seq", 6, U8, Little);

/// Largest `|IMU_YAW_RATE.yaw_rate|`, rad/s: beyond a MEMS gyro's ±2000 °/s full scale
/// (34.9 rad/s); a larger value is out of range.
pub const YAW_RATE_MAX: f32 = 35.0;
/// `IMU_YAW_RATE.yaw_rate`, rad/s, counter-clockwise positive (f32, finite, within
/// ±[`YAW_RATE_MAX`]).
pub const IMU_YAW_RATE_VALUE: Field = Field::int("yaw_rate", 0, F32, Little);
/// `IMU_YAW_RATE.seq`, alive counter.
pub const IMU_SEQ: Field = Field::int("seq", 4, U8, Little);

/// Most pods a `POD_COUNTS` frame carries.
pub const PODS_MAX: usize = 3;
/// `POD_COUNTS.count0..2`, wrapping encoder counts (the receiver takes the signed
/// 16-bit difference between frames).
pub const POD_COUNT: [Field; PODS_MAX] = [
    Field::int("count0", 0, U16, Little),
    Field::int("count1", 2, U16, Little),
    Field::int("count2", 4, U16, Little),
];
/// `POD_COUNTS.seq`, alive counter.
pub const POD_SEQ: Field = Field::int("seq", 6, U8, Little);

/// `ODOM_SLIP.vx`, m/s: the wheels' forward velocity less the pods'.
pub const SLIP_VX: Field = Field::int("vx", 0, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `ODOM_SLIP.vy`, m/s.
pub const SLIP_VY: Field = Field::int("vy", 2, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `ODOM_SLIP.wz`, rad/s.
pub const SLIP_WZ: Field = Field::int("wz", 4, I16, Little)
    .scaled(ANGULAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `ODOM_SLIP.source`: 0 wheels, 1 pods2_gyro, 2 pods3, 3 wheels because the pods are
/// silent; the low 4 bits of byte 6 (other values reserved, rejected).
pub const SLIP_SOURCE: Field =
    Field::int("source", 6, Bits { shift: 0, width: 4 }, Little).range(0, 3);

/// `WHEEL_TEST.wheel`: 0 FL, 1 FR, 2 RL, 3 RR.
pub const TEST_WHEEL: Field = Field::int("wheel", 0, U8, Little).range(0, 3);
/// Largest `|WHEEL_TEST.speed|`, raw (10 rad/s at the wheel: 0.76 m/s at the rim of a
/// 76 mm wheel, gentle for a wheel in the air).
pub const TEST_SPEED_RAW_MAX: i64 = 10_000;
/// `WHEEL_TEST.speed`, wheel rad/s, robot-forward positive.
pub const TEST_SPEED: Field = Field::int("speed", 1, I16, Little)
    .scaled(ANGULAR_SCALE)
    .range(-TEST_SPEED_RAW_MAX, TEST_SPEED_RAW_MAX);
/// Longest `WHEEL_TEST.duration_ms`.
pub const TEST_DURATION_MAX_MS: i64 = 3000;
/// `WHEEL_TEST.duration_ms`.
pub const TEST_DURATION: Field =
    Field::int("duration_ms", 3, U16, Little).range(1, TEST_DURATION_MAX_MS);
/// `WHEEL_TEST_RESULT.wheel`.
pub const RESULT_WHEEL: Field = Field::int("wheel", 0, U8, Little).range(0, 3);
/// `WHEEL_TEST_RESULT.outcome`: 0 done, 1 stopped, 2 fault, 3 refused.
pub const RESULT_OUTCOME: Field = Field::int("outcome", 1, U8, Little).range(0, 3);
/// Wheel angle LSB, rad.
pub const TEST_ANGLE_SCALE: f64 = 0.001;
/// `WHEEL_TEST_RESULT.angle`, rad, robot-forward positive.
pub const RESULT_ANGLE: Field = Field::int("angle", 2, I16, Little)
    .scaled(TEST_ANGLE_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// Current LSB, A.
pub const TEST_CURRENT_SCALE: f64 = 0.01;
/// `WHEEL_TEST_RESULT.peak_current`, A, the motor's sense as configured (signed).
pub const RESULT_PEAK_CURRENT: Field = Field::int("peak_current", 4, I16, Little)
    .scaled(TEST_CURRENT_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);

/// `MODE_CMD.request`: 0 disable, 1 enable, 2 reset.
pub const MODE_REQUEST: Field = Field::int("request", 0, U8, Little).range(0, 2);

/// Position LSB, m.
pub const POSITION_SCALE: f64 = 0.0001;
/// `ODOM_POSITION.x`, m.
pub const ODOM_X: Field = Field::int("x", 0, I32, Little).scaled(POSITION_SCALE);
/// `ODOM_POSITION.y`, m.
pub const ODOM_Y: Field = Field::int("y", 4, I32, Little).scaled(POSITION_SCALE);

/// Heading LSB, rad.
pub const HEADING_SCALE: f64 = 0.0001;
/// Raw limit of the heading: round(π / 0.0001).
pub const HEADING_RAW_MAX: i64 = 31416;
/// `ODOM_VELOCITY.heading`, rad.
pub const ODOM_HEADING: Field = Field::int("heading", 0, I16, Little)
    .scaled(HEADING_SCALE)
    .range(-HEADING_RAW_MAX, HEADING_RAW_MAX);
/// `ODOM_VELOCITY.vx`, m/s.
pub const ODOM_VX: Field = Field::int("vx", 2, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `ODOM_VELOCITY.vy`, m/s.
pub const ODOM_VY: Field = Field::int("vy", 4, I16, Little)
    .scaled(LINEAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);
/// `ODOM_VELOCITY.wz`, rad/s.
pub const ODOM_WZ: Field = Field::int("wz", 6, I16, Little)
    .scaled(ANGULAR_SCALE)
    .range(-VEL_RAW_MAX, VEL_RAW_MAX);

/// `STATUS.state`: 0 disabled, 1 enabled, 2 fault, 3 estop, 4 wheel test.
pub const STATUS_STATE: Field = Field::int("state", 0, U8, Little).range(0, 4);
/// `STATUS.fault`: 0 none .. 6 encoder stuck, 7 wheel runaway.
pub const STATUS_FAULT: Field = Field::int("fault", 1, U8, Little).range(0, 13);
/// `STATUS.rx_errors`: rejected frames, saturating.
pub const STATUS_RX_ERRORS: Field = Field::int("rx_errors", 2, U16, Little);
/// `STATUS.unknown_ids`: frames with unknown ids, saturating.
pub const STATUS_UNKNOWN_IDS: Field = Field::int("unknown_ids", 4, U16, Little);
/// Bits of `STATUS.motors_online` in use: one per wheel.
pub const MOTORS_ONLINE_MASK: u8 = 0x0F;
/// `STATUS.motors_online`: bit i = wheel i (FL, FR, RL, RR); the low 4 bits of byte 6.
pub const STATUS_MOTORS_ONLINE: Field =
    Field::int("motors_online", 6, Bits { shift: 0, width: 4 }, Little);
/// `STATUS.heading_source`: 0 wheels, 1 gyro, 2 wheels because the gyro is silent; the
/// high 4 bits of byte 6 (other values reserved, rejected).
pub const STATUS_HEADING_SOURCE: Field =
    Field::int("heading_source", 6, Bits { shift: 4, width: 4 }, Little).range(0, 2);
/// `STATUS.seq`: rolling counter.
pub const STATUS_SEQ: Field = Field::int("seq", 7, U8, Little);

/// `STATUS_COUNTERS.repeated_seq`: twists not applied because their `seq` repeated the
/// last accepted one, saturating.
pub const COUNTERS_REPEATED_SEQ: Field = Field::int("repeated_seq", 0, U16, Little);
/// `STATUS_COUNTERS.wrong_dlc`: rejected frames with a wrong DLC, saturating.
pub const COUNTERS_WRONG_DLC: Field = Field::int("wrong_dlc", 2, U16, Little);
/// `STATUS_COUNTERS.out_of_range`: rejected frames with a field out of range, saturating.
pub const COUNTERS_OUT_OF_RANGE: Field = Field::int("out_of_range", 4, U16, Little);
/// `STATUS_COUNTERS.non_finite`: rejected frames with a NaN or infinite float,
/// saturating.
pub const COUNTERS_NON_FINITE: Field = Field::int("non_finite", 6, U16, Little);

/// `HEARTBEAT.uptime_ms`.
pub const HEARTBEAT_UPTIME: Field = Field::int("uptime_ms", 0, U32, Little);
/// `HEARTBEAT.state`, same values as `STATUS.state`.
pub const HEARTBEAT_STATE: Field = Field::int("state", 4, U8, Little).range(0, 4);
/// `HEARTBEAT.protocol_version`.
pub const HEARTBEAT_VERSION: Field = Field::int("protocol_version", 5, U8, Little);
/// `HEARTBEAT.config_id` (version 5).
pub const HEARTBEAT_CONFIG_ID: Field = Field::int("config_id", 6, U16, Little);
