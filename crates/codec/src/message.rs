//! Frames to messages and messages to field lists: which codec reads an id ([`route`]), and
//! each message's DBC name and signals ([`AnyMessage::fields`]).

use embedded_can::{Frame, Id};
use firmware::CanFrame;
use firmware::protocol::DecodeError;
use firmware::protocol::dji::{self, EscModel};
use firmware::protocol::odrive;
use firmware::protocol::robot;

use crate::canopen::CanopenFrame;
use crate::json::Decoded;

fn robot_fields(msg: &robot::Message) -> Decoded {
    use robot::layout as l;
    use robot::{Command as C, Telemetry as T};
    let d = Decoded::new("robot", msg.def().name);
    match *msg {
        robot::Message::Command(C::Estop) => d.i(&l::ESTOP_MAGIC, l::ESTOP_MAGIC_VALUE),
        robot::Message::Command(C::Twist(t)) => d
            .f(&l::TWIST_VX, t.vx)
            .f(&l::TWIST_VY, t.vy)
            .f(&l::TWIST_WZ, t.wz)
            .i(&l::TWIST_SEQ, t.seq),
        robot::Message::Command(C::Mode(m)) => d.i(&l::MODE_REQUEST, m.raw()),
        robot::Message::Command(C::StatusRequest) => d,
        robot::Message::Command(C::ImuYawRate(g)) => d
            .f(&l::IMU_YAW_RATE_VALUE, g.yaw_rate)
            .i(&l::IMU_SEQ, g.seq),
        robot::Message::Command(C::WheelTest(t)) => d
            .i(&l::TEST_WHEEL, t.wheel)
            .f(&l::TEST_SPEED, t.speed)
            .i(&l::TEST_DURATION, t.duration_ms),
        robot::Message::Command(C::PodCounts(c)) => d
            .i(&l::POD_COUNT[0], c.counts[0])
            .i(&l::POD_COUNT[1], c.counts[1])
            .i(&l::POD_COUNT[2], c.counts[2])
            .i(&l::POD_SEQ, c.seq),
        robot::Message::Telemetry(T::OdomSlip(s)) => d
            .f(&l::SLIP_VX, s.vx)
            .f(&l::SLIP_VY, s.vy)
            .f(&l::SLIP_WZ, s.wz)
            .i(&l::SLIP_SOURCE, s.source.raw()),
        robot::Message::Telemetry(T::OdomPosition(o)) => d.f(&l::ODOM_X, o.x).f(&l::ODOM_Y, o.y),
        robot::Message::Telemetry(T::OdomVelocity(o)) => d
            .f(&l::ODOM_HEADING, o.heading)
            .f(&l::ODOM_VX, o.vx)
            .f(&l::ODOM_VY, o.vy)
            .f(&l::ODOM_WZ, o.wz),
        robot::Message::Telemetry(T::Status(s)) => d
            .i(&l::STATUS_STATE, s.state.raw())
            .i(&l::STATUS_FAULT, s.fault.raw())
            .i(&l::STATUS_RX_ERRORS, s.rx_errors)
            .i(&l::STATUS_UNKNOWN_IDS, s.unknown_ids)
            .i(&l::STATUS_MOTORS_ONLINE, s.motors_online)
            .i(&l::STATUS_HEADING_SOURCE, s.heading_source.raw())
            .i(&l::STATUS_SEQ, s.seq),
        robot::Message::Telemetry(T::StatusCounters(c)) => d
            .i(&l::COUNTERS_REPEATED_SEQ, c.repeated_seq)
            .i(&l::COUNTERS_WRONG_DLC, c.wrong_dlc)
            .i(&l::COUNTERS_OUT_OF_RANGE, c.out_of_range)
            .i(&l::COUNTERS_NON_FINITE, c.non_finite),
        robot::Message::Telemetry(T::Heartbeat(h)) => d
            .i(&l::HEARTBEAT_UPTIME, h.uptime_ms)
            .i(&l::HEARTBEAT_STATE, h.state.raw())
            .i(&l::HEARTBEAT_VERSION, h.protocol_version)
            .i(&l::HEARTBEAT_CONFIG_ID, h.config_id),
        robot::Message::Telemetry(T::WheelTestResult(r)) => d
            .i(&l::RESULT_WHEEL, r.wheel)
            .i(&l::RESULT_OUTCOME, r.outcome.raw())
            .f(&l::RESULT_ANGLE, r.angle)
            .f(&l::RESULT_PEAK_CURRENT, r.peak_current),
    }
}

fn odrive_fields(msg: &odrive::Message) -> Decoded {
    use odrive::layout as l;
    use odrive::{Command as C, Feedback as F};
    let node = msg.node().get();
    let d =
        Decoded::new("odrive", format!("Axis{node}_{}", msg.def().name)).extra("node", node.into());
    match *msg {
        odrive::Message::Command(a) => match a.msg {
            C::Estop => d,
            C::GetError | C::GetHeartbeat | C::GetEncoderEstimates => d.extra("request", 1),
            C::SetAxisState(s) => d.i(&l::REQUESTED_STATE, s.raw()),
            C::SetControllerMode {
                control_mode,
                input_mode,
            } => d
                .i(&l::CONTROL_MODE, control_mode.raw())
                .i(&l::INPUT_MODE, input_mode.raw()),
            C::SetInputVel { vel, torque_ff } => {
                d.f(&l::INPUT_VEL, vel).f(&l::INPUT_TORQUE_FF, torque_ff)
            }
            C::ClearErrors { identify } => d.i(&l::IDENTIFY, identify),
        },
        odrive::Message::Feedback(a) => match a.msg {
            F::Heartbeat(h) => d
                .i(&l::HB_AXIS_ERROR, h.axis_error)
                .i(&l::HB_AXIS_STATE, h.axis_state.raw())
                .i(&l::HB_PROCEDURE_RESULT, h.procedure_result)
                .i(&l::HB_TRAJECTORY_DONE, h.trajectory_done),
            F::Error {
                active_errors,
                disarm_reason,
            } => d
                .i(&l::ERR_ACTIVE, active_errors)
                .i(&l::ERR_DISARM_REASON, disarm_reason),
            F::EncoderEstimates { pos, vel } => d.f(&l::POS_ESTIMATE, pos).f(&l::VEL_ESTIMATE, vel),
        },
    }
}

fn dji_fields(msg: &dji::Message) -> Decoded {
    use dji::layout as l;
    match msg {
        dji::Message::Command(c) => {
            let mut d = Decoded::new("dji", c.group.def().name);
            for (field, amps) in c.group.fields().iter().zip(c.amps()) {
                d = d.f(field, amps);
            }
            d
        }
        dji::Message::Feedback(fb) => {
            Decoded::new("dji", format!("{}_{}", l::FEEDBACK.name, fb.esc.get()))
                .extra("esc", fb.esc.get().into())
                .i(&l::ROTOR_ANGLE, fb.rotor_angle)
                .i(&l::ROTOR_SPEED, fb.rotor_speed_rpm)
                .f(&l::TORQUE_CURRENT, fb.current_amps())
                .i(&l::TEMPERATURE, fb.temperature_c)
        }
    }
}

/// Any decoded message.
pub(crate) enum AnyMessage {
    Robot(robot::Message),
    Odrive(odrive::Message),
    Dji(dji::Message),
    Canopen(CanopenFrame),
}

impl AnyMessage {
    pub(crate) fn fields(&self) -> Decoded {
        match self {
            Self::Robot(m) => robot_fields(m),
            Self::Odrive(m) => odrive_fields(m),
            Self::Dji(m) => dji_fields(m),
            Self::Canopen(m) => m.fields(),
        }
    }

    pub(crate) fn to_can_frame(&self) -> CanFrame {
        match self {
            Self::Robot(m) => m.to_can_frame(),
            Self::Odrive(m) => m.to_can_frame(),
            Self::Dji(m) => m.to_can_frame(),
            Self::Canopen(m) => m.to_can_frame(),
        }
    }

    /// The routing that reads this message's frame back (`decode --canopen` for CANopen).
    pub(crate) fn routing(&self) -> Routing {
        Routing {
            model: EscModel::C620,
            canopen: matches!(self, Self::Canopen(_)),
        }
    }
}

/// Largest ODrive node routed to the ODrive codec (the DBC covers nodes 0-3).
const ODRIVE_MAX_NODE: u16 = 3;

/// Which codecs `decode` uses for ids outside the robot block.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Routing {
    /// The DJI ESC model (the current scale).
    pub(crate) model: EscModel,
    /// CANopen for every id outside the robot block, instead of DJI and ODrive.
    pub(crate) canopen: bool,
}

impl Default for Routing {
    fn default() -> Self {
        Self {
            model: EscModel::C620,
            canopen: false,
        }
    }
}

pub(crate) fn route(frame: &CanFrame, routing: Routing) -> Result<AnyMessage, DecodeError> {
    let id = match frame.id() {
        Id::Standard(id) => id.as_raw(),
        Id::Extended(id) => return Err(DecodeError::ExtendedId { id: id.as_raw() }),
    };
    if robot::in_block(id) {
        robot::decode(frame).map(AnyMessage::Robot)
    } else if routing.canopen {
        CanopenFrame::decode(frame).map(AnyMessage::Canopen)
    } else if dji::is_dji_id(id) {
        dji::decode(frame, routing.model).map(AnyMessage::Dji)
    } else if id >> odrive::layout::CMD_BITS <= ODRIVE_MAX_NODE {
        odrive::decode(frame).map(AnyMessage::Odrive)
    } else {
        Err(DecodeError::UnknownId { id: frame.id() })
    }
}
