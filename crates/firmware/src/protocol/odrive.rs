//! ODrive "CAN Simple" protocol, firmware 0.6 (a velocity interface: the drive runs the loop).
//!
//! Each axis has a node id ([`NodeId`], 0..=63) and every message an id
//! `node_id << 5 | cmd_id` ([`split_id`]). [`layout`] mirrors ODrive's official DBC (0.6.10)
//! for the subset implemented; [`Command`] is what the host sends, [`Feedback`] what a drive
//! sends, [`decode`] reads either. The message table, the drive's rates and watchdog, and
//! where the decoders are more lenient than the DBC are in `docs/protocol.md`, section
//! "ODrive CAN Simple".
//!
//! # Encoding and decoding
//!
//! Messages are addressed: [`Addressed`] pairs a [`NodeId`] with a [`Command`] or
//! [`Feedback`]. Decoders reject NaN and infinite floats ([`DecodeError::NonFinite`]) and
//! unknown axis states and modes ([`DecodeError::OutOfRange`]). Encoders send non-finite
//! floats as 0 (NaN) or `±f32::MAX` (infinities) so a frame never carries NaN; the control
//! core is expected never to produce them.

use embedded_can::{Frame, StandardId};

use super::error::DecodeError;
use super::wire::{self, Field, Payload, saturate_f32};
use crate::frame::CanFrame;

/// The frame layout: the Rust mirror of the official ODrive DBC (0.6.10) for the messages
/// implemented here.
pub mod layout {
    use crate::protocol::wire::{ByteOrder::Little, Field, MessageDef, WireType::*};

    /// Bits of the id holding the command id.
    pub const CMD_BITS: u16 = 5;
    /// Mask of the command id.
    pub const CMD_MASK: u16 = (1 << CMD_BITS) - 1;
    /// Largest node id.
    pub const NODE_MAX: u8 = 63;

    /// `Heartbeat` (cmd 0x01).
    pub const HEARTBEAT: MessageDef = MessageDef::new("Heartbeat", 0x01, 8);
    /// `Estop` (cmd 0x02).
    pub const ESTOP: MessageDef = MessageDef::new("Estop", 0x02, 0);
    /// `Get_Error` (cmd 0x03): RTR request, DLC 8 response.
    pub const GET_ERROR: MessageDef = MessageDef::new("Get_Error", 0x03, 8);
    /// `Set_Axis_State` (cmd 0x07).
    pub const SET_AXIS_STATE: MessageDef = MessageDef::new("Set_Axis_State", 0x07, 8);
    /// `Get_Encoder_Estimates` (cmd 0x09).
    pub const GET_ENCODER_ESTIMATES: MessageDef = MessageDef::new("Get_Encoder_Estimates", 0x09, 8);
    /// `Set_Controller_Mode` (cmd 0x0B).
    pub const SET_CONTROLLER_MODE: MessageDef = MessageDef::new("Set_Controller_Mode", 0x0B, 8);
    /// `Set_Input_Vel` (cmd 0x0D).
    pub const SET_INPUT_VEL: MessageDef = MessageDef::new("Set_Input_Vel", 0x0D, 8);
    /// `Clear_Errors` (cmd 0x18).
    pub const CLEAR_ERRORS: MessageDef = MessageDef::new("Clear_Errors", 0x18, 1);
    /// DLCs accepted for `Clear_Errors` (the 0.5 DBC had no payload).
    pub const CLEAR_ERRORS_DLCS: [u8; 2] = [1, 0];

    /// `Heartbeat.Axis_Error` (bit set of ODrive errors).
    pub const HB_AXIS_ERROR: Field = Field::int("Axis_Error", 0, U32, Little);
    /// `Heartbeat.Axis_State`.
    pub const HB_AXIS_STATE: Field = Field::int("Axis_State", 4, U8, Little).range(0, 14);
    /// `Heartbeat.Procedure_Result`.
    pub const HB_PROCEDURE_RESULT: Field = Field::int("Procedure_Result", 5, U8, Little);
    /// `Heartbeat.Trajectory_Done_Flag` (bit 0 of byte 6).
    pub const HB_TRAJECTORY_DONE: Field = Field::int("Trajectory_Done_Flag", 6, Bit0, Little);

    /// `Get_Error.Active_Errors`.
    pub const ERR_ACTIVE: Field = Field::int("Active_Errors", 0, U32, Little);
    /// `Get_Error.Disarm_Reason`.
    pub const ERR_DISARM_REASON: Field = Field::int("Disarm_Reason", 4, U32, Little);

    /// `Set_Axis_State.Axis_Requested_State`.
    pub const REQUESTED_STATE: Field =
        Field::int("Axis_Requested_State", 0, U32, Little).range(0, 14);

    /// `Get_Encoder_Estimates.Pos_Estimate`, rev.
    pub const POS_ESTIMATE: Field = Field::int("Pos_Estimate", 0, F32, Little);
    /// `Get_Encoder_Estimates.Vel_Estimate`, rev/s.
    pub const VEL_ESTIMATE: Field = Field::int("Vel_Estimate", 4, F32, Little);

    /// `Set_Controller_Mode.Control_Mode`.
    pub const CONTROL_MODE: Field = Field::int("Control_Mode", 0, U32, Little).range(0, 3);
    /// `Set_Controller_Mode.Input_Mode`.
    pub const INPUT_MODE: Field = Field::int("Input_Mode", 4, U32, Little).range(0, 8);

    /// `Set_Input_Vel.Input_Vel`, rev/s.
    pub const INPUT_VEL: Field = Field::int("Input_Vel", 0, F32, Little);
    /// `Set_Input_Vel.Input_Torque_FF`, Nm.
    pub const INPUT_TORQUE_FF: Field = Field::int("Input_Torque_FF", 4, F32, Little);

    /// `Clear_Errors.Identify`.
    pub const IDENTIFY: Field = Field::int("Identify", 0, U8, Little);
}

u8_id!(
    /// An ODrive CAN node id, `0..=63`.
    NodeId(0..=layout::NODE_MAX)
);

impl NodeId {
    /// The 11-bit id of command `cmd` (masked to 5 bits) to or from this node.
    #[must_use]
    pub const fn can_id(self, cmd: u16) -> StandardId {
        let raw = ((self.0 as u16) << layout::CMD_BITS) | (cmd & layout::CMD_MASK);
        // node <= 63 and cmd <= 31 give raw <= 0x7FF.
        match StandardId::new(raw) {
            Some(id) => id,
            None => StandardId::ZERO,
        }
    }
}

/// Splits an 11-bit id into node id and command id.
#[must_use]
pub fn split_id(id: StandardId) -> (NodeId, u8) {
    let raw = id.as_raw();
    // raw < 0x800, so raw >> 5 < 64: always a valid node id.
    (
        NodeId((raw >> layout::CMD_BITS) as u8),
        (raw & layout::CMD_MASK) as u8,
    )
}

macro_rules! u32_enum {
    ($(#[$meta:meta])* $ty:ident { $($(#[$vmeta:meta])* $variant:ident = $raw:literal),+ $(,)? }) => {
        $(#[$meta])*
        #[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
        #[repr(u32)]
        pub enum $ty {
            $($(#[$vmeta])* $variant = $raw,)+
        }

        impl $ty {
            /// The enum value for a raw number; `None` for values not defined.
            #[must_use]
            pub const fn from_raw(raw: u32) -> Option<Self> {
                match raw {
                    $($raw => Some(Self::$variant),)+
                    _ => None,
                }
            }

            /// The raw number.
            #[must_use]
            pub const fn raw(self) -> u32 {
                self as u32
            }
        }
    };
}

u32_enum!(
    /// `AxisState` of ODrive 0.6 (the DBC's value table).
    AxisState {
        /// 0.
        Undefined = 0,
        /// 1: motor off.
        Idle = 1,
        /// 2.
        StartupSequence = 2,
        /// 3.
        FullCalibrationSequence = 3,
        /// 4.
        MotorCalibration = 4,
        /// 5.
        SensorlessControl = 5,
        /// 6.
        EncoderIndexSearch = 6,
        /// 7.
        EncoderOffsetCalibration = 7,
        /// 8: running the control loop.
        ClosedLoopControl = 8,
        /// 9.
        LockinSpin = 9,
        /// 10.
        EncoderDirFind = 10,
        /// 11.
        Homing = 11,
        /// 12.
        EncoderHallPolarityCalibration = 12,
        /// 13.
        EncoderHallPhaseCalibration = 13,
        /// 14.
        AnticoggingCalibration = 14,
    }
);

u32_enum!(
    /// `ControlMode` of ODrive 0.6.
    ControlMode {
        /// 0.
        VoltageControl = 0,
        /// 1.
        TorqueControl = 1,
        /// 2: the one this project uses.
        VelocityControl = 2,
        /// 3.
        PositionControl = 3,
    }
);

u32_enum!(
    /// `InputMode` of ODrive 0.6.
    InputMode {
        /// 0.
        Inactive = 0,
        /// 1: setpoints applied as they arrive.
        Passthrough = 1,
        /// 2: velocity setpoints ramped.
        VelRamp = 2,
        /// 3.
        PosFilter = 3,
        /// 4.
        MixChannels = 4,
        /// 5.
        TrapTraj = 5,
        /// 6.
        TorqueRamp = 6,
        /// 7.
        Mirror = 7,
        /// 8.
        Tuning = 8,
    }
);

/// Whether `frame` asks a drive for one of the messages implemented here (`Heartbeat`,
/// `Get_Error`, `Get_Encoder_Estimates`): a remote frame of any DLC, or an empty data frame,
/// on that message's id, as the ODrive documentation allows. A drive never sends one, so a
/// core reading feedback can pass over the requests of another host on the bus instead of
/// counting them as malformed feedback.
#[must_use]
pub fn is_request<F: Frame>(frame: &F) -> bool {
    let embedded_can::Id::Standard(id) = frame.id() else {
        return false;
    };
    let cmd = id.as_raw() & layout::CMD_MASK;
    (frame.is_remote_frame() || frame.dlc() == 0)
        && [
            layout::HEARTBEAT.id,
            layout::GET_ERROR.id,
            layout::GET_ENCODER_ESTIMATES.id,
        ]
        .contains(&cmd)
}

/// A message from the host to a drive.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Command {
    /// `Estop`: the drive disarms with `ESTOP_REQUESTED`.
    Estop,
    /// `Get_Error` request (see [`is_request`]); the drive answers with [`Feedback::Error`].
    GetError,
    /// `Heartbeat` request (see [`is_request`]); the drive answers with a
    /// [`Feedback::Heartbeat`] out of its schedule.
    GetHeartbeat,
    /// `Get_Encoder_Estimates` request (see [`is_request`]); the drive answers with
    /// [`Feedback::EncoderEstimates`].
    GetEncoderEstimates,
    /// `Set_Axis_State`.
    SetAxisState(AxisState),
    /// `Set_Controller_Mode`.
    SetControllerMode {
        /// Control mode.
        control_mode: ControlMode,
        /// Input mode.
        input_mode: InputMode,
    },
    /// `Set_Input_Vel`.
    SetInputVel {
        /// Velocity setpoint, rev/s (motor side).
        vel: f32,
        /// Torque feed-forward, Nm.
        torque_ff: f32,
    },
    /// `Clear_Errors`.
    ClearErrors {
        /// Blink the LED to identify the drive.
        identify: bool,
    },
}

/// `Heartbeat` contents.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Heartbeat {
    /// Active errors | disarm reason (ODrive error bits).
    pub axis_error: u32,
    /// Current axis state.
    pub axis_state: AxisState,
    /// Result of the last procedure (ODrive `ProcedureResult`, raw).
    pub procedure_result: u8,
    /// Trajectory done.
    pub trajectory_done: bool,
}

/// A message from a drive to the host.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Feedback {
    /// `Heartbeat`.
    Heartbeat(Heartbeat),
    /// `Get_Error` response.
    Error {
        /// Active error bits.
        active_errors: u32,
        /// Error bits that disarmed the axis.
        disarm_reason: u32,
    },
    /// `Get_Encoder_Estimates`.
    EncoderEstimates {
        /// Position, rev.
        pos: f32,
        /// Velocity, rev/s.
        vel: f32,
    },
}

/// A message together with the node it is sent to or comes from.
#[derive(Clone, Copy, PartialEq, Debug)]
pub struct Addressed<M> {
    /// The drive's node id.
    pub node: NodeId,
    /// The message.
    pub msg: M,
}

/// Any message of the protocol, with its node.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Message {
    /// Host → drive.
    Command(Addressed<Command>),
    /// Drive → host.
    Feedback(Addressed<Feedback>),
}

/// The raw id, node id and command id of `frame`.
fn split<F: Frame>(frame: &F) -> Result<(u16, NodeId, u16), DecodeError> {
    let raw = wire::standard_id(frame)?;
    let (node, cmd) = split_id(StandardId::new(raw).unwrap_or(StandardId::ZERO));
    Ok((raw, node, u16::from(cmd)))
}

impl Command {
    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Estop => layout::ESTOP,
            Self::GetError => layout::GET_ERROR,
            Self::GetHeartbeat => layout::HEARTBEAT,
            Self::GetEncoderEstimates => layout::GET_ENCODER_ESTIMATES,
            Self::SetAxisState(_) => layout::SET_AXIS_STATE,
            Self::SetControllerMode { .. } => layout::SET_CONTROLLER_MODE,
            Self::SetInputVel { .. } => layout::SET_INPUT_VEL,
            Self::ClearErrors { .. } => layout::CLEAR_ERRORS,
        }
    }

    /// Decodes a host → drive frame (any node).
    ///
    /// # Errors
    /// See [`DecodeError`]; `UnknownId` for command ids not implemented here or sent by drives
    /// (a `Get_Error` data frame is a [`Feedback`]).
    pub fn decode<F: Frame>(frame: &F) -> Result<Addressed<Self>, DecodeError> {
        let (id, node, cmd) = split(frame)?;
        let msg = if cmd == layout::ESTOP.id {
            wire::data_payload(frame, id, &[layout::ESTOP.dlc])?;
            Self::Estop
        } else if is_request(frame) {
            if cmd == layout::HEARTBEAT.id {
                Self::GetHeartbeat
            } else if cmd == layout::GET_ERROR.id {
                Self::GetError
            } else {
                Self::GetEncoderEstimates
            }
        } else if cmd == layout::SET_AXIS_STATE.id {
            let p = wire::data_payload(frame, id, &[layout::SET_AXIS_STATE.dlc])?;
            Self::SetAxisState(read_enum(&p, layout::REQUESTED_STATE, AxisState::from_raw)?)
        } else if cmd == layout::SET_CONTROLLER_MODE.id {
            let p = wire::data_payload(frame, id, &[layout::SET_CONTROLLER_MODE.dlc])?;
            Self::SetControllerMode {
                control_mode: read_enum(&p, layout::CONTROL_MODE, ControlMode::from_raw)?,
                input_mode: read_enum(&p, layout::INPUT_MODE, InputMode::from_raw)?,
            }
        } else if cmd == layout::SET_INPUT_VEL.id {
            let p = wire::data_payload(frame, id, &[layout::SET_INPUT_VEL.dlc])?;
            Self::SetInputVel {
                vel: layout::INPUT_VEL.finite(&p)?,
                torque_ff: layout::INPUT_TORQUE_FF.finite(&p)?,
            }
        } else if cmd == layout::CLEAR_ERRORS.id {
            let p = wire::data_payload(frame, id, &layout::CLEAR_ERRORS_DLCS)?;
            Self::ClearErrors {
                identify: layout::IDENTIFY.raw(&p) != 0,
            }
        } else {
            return Err(wire::unknown(frame));
        };
        Ok(Addressed { node, msg })
    }

    /// Encodes for `node` into a [`CanFrame`].
    #[must_use]
    pub fn to_can_frame(&self, node: NodeId) -> CanFrame {
        let def = self.def();
        let id = node.can_id(def.id);
        let mut p = Payload::new();
        match *self {
            Self::Estop => {}
            Self::GetError | Self::GetHeartbeat | Self::GetEncoderEstimates => {
                return CanFrame::remote(id, def.dlc);
            }
            Self::SetAxisState(s) => layout::REQUESTED_STATE.put_raw(&mut p, s.raw().into()),
            Self::SetControllerMode {
                control_mode,
                input_mode,
            } => {
                layout::CONTROL_MODE.put_raw(&mut p, control_mode.raw().into());
                layout::INPUT_MODE.put_raw(&mut p, input_mode.raw().into());
            }
            Self::SetInputVel { vel, torque_ff } => {
                layout::INPUT_VEL.put_f32(&mut p, saturate_f32(vel));
                layout::INPUT_TORQUE_FF.put_f32(&mut p, saturate_f32(torque_ff));
            }
            Self::ClearErrors { identify } => layout::IDENTIFY.put_raw(&mut p, identify.into()),
        }
        CanFrame::from_buffer(id, p.0, def.dlc)
    }

    /// Encodes for `node` into any [`Frame`] type; `None` only if that type rejects a valid
    /// frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self, node: NodeId) -> Option<F> {
        self.to_can_frame(node).convert()
    }
}

/// `field` of `p` as the enum value `from_raw` gives; `OutOfRange` for a raw value outside the
/// field's range or one the enum does not define.
fn read_enum<T>(
    p: &Payload,
    field: Field,
    from_raw: fn(u32) -> Option<T>,
) -> Result<T, DecodeError> {
    let raw = field.checked(p)?;
    u32::try_from(raw)
        .ok()
        .and_then(from_raw)
        .ok_or(DecodeError::OutOfRange {
            field: field.name,
            value: raw,
        })
}

impl Feedback {
    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Heartbeat(_) => layout::HEARTBEAT,
            Self::Error { .. } => layout::GET_ERROR,
            Self::EncoderEstimates { .. } => layout::GET_ENCODER_ESTIMATES,
        }
    }

    /// Decodes a drive → host frame (any node).
    ///
    /// # Errors
    /// See [`DecodeError`]; `UnknownId` for command ids not implemented here or sent by the
    /// host.
    pub fn decode<F: Frame>(frame: &F) -> Result<Addressed<Self>, DecodeError> {
        let (id, node, cmd) = split(frame)?;
        let msg = if cmd == layout::HEARTBEAT.id {
            let p = wire::data_payload(frame, id, &[layout::HEARTBEAT.dlc])?;
            Self::Heartbeat(Heartbeat {
                axis_error: layout::HB_AXIS_ERROR.raw(&p) as u32,
                axis_state: read_enum(&p, layout::HB_AXIS_STATE, AxisState::from_raw)?,
                procedure_result: layout::HB_PROCEDURE_RESULT.raw(&p) as u8,
                trajectory_done: layout::HB_TRAJECTORY_DONE.raw(&p) != 0,
            })
        } else if cmd == layout::GET_ERROR.id {
            let p = wire::data_payload(frame, id, &[layout::GET_ERROR.dlc])?;
            Self::Error {
                active_errors: layout::ERR_ACTIVE.raw(&p) as u32,
                disarm_reason: layout::ERR_DISARM_REASON.raw(&p) as u32,
            }
        } else if cmd == layout::GET_ENCODER_ESTIMATES.id {
            let p = wire::data_payload(frame, id, &[layout::GET_ENCODER_ESTIMATES.dlc])?;
            Self::EncoderEstimates {
                pos: layout::POS_ESTIMATE.finite(&p)?,
                vel: layout::VEL_ESTIMATE.finite(&p)?,
            }
        } else {
            return Err(wire::unknown(frame));
        };
        Ok(Addressed { node, msg })
    }

    /// Encodes from `node` into a [`CanFrame`] (what a simulated drive sends).
    #[must_use]
    pub fn to_can_frame(&self, node: NodeId) -> CanFrame {
        let mut p = Payload::new();
        match *self {
            Self::Heartbeat(h) => {
                layout::HB_AXIS_ERROR.put_raw(&mut p, h.axis_error.into());
                layout::HB_AXIS_STATE.put_raw(&mut p, h.axis_state.raw().into());
                layout::HB_PROCEDURE_RESULT.put_raw(&mut p, h.procedure_result.into());
                layout::HB_TRAJECTORY_DONE.put_raw(&mut p, h.trajectory_done.into());
            }
            Self::Error {
                active_errors,
                disarm_reason,
            } => {
                layout::ERR_ACTIVE.put_raw(&mut p, active_errors.into());
                layout::ERR_DISARM_REASON.put_raw(&mut p, disarm_reason.into());
            }
            Self::EncoderEstimates { pos, vel } => {
                layout::POS_ESTIMATE.put_f32(&mut p, saturate_f32(pos));
                layout::VEL_ESTIMATE.put_f32(&mut p, saturate_f32(vel));
            }
        }
        let def = self.def();
        CanFrame::from_buffer(node.can_id(def.id), p.0, def.dlc)
    }

    /// Encodes from `node` into any [`Frame`] type; `None` only if that type rejects a valid
    /// frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self, node: NodeId) -> Option<F> {
        self.to_can_frame(node).convert()
    }
}

impl Message {
    /// Encodes into a [`CanFrame`].
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        match self {
            Self::Command(a) => a.msg.to_can_frame(a.node),
            Self::Feedback(a) => a.msg.to_can_frame(a.node),
        }
    }

    /// The message's layout row.
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Command(a) => a.msg.def(),
            Self::Feedback(a) => a.msg.def(),
        }
    }

    /// The node the message is addressed to or comes from.
    #[must_use]
    pub const fn node(&self) -> NodeId {
        match self {
            Self::Command(a) => a.node,
            Self::Feedback(a) => a.node,
        }
    }
}

/// Decodes any frame of the protocol, in either direction.
///
/// # Errors
/// See [`DecodeError`].
pub fn decode<F: Frame>(frame: &F) -> Result<Message, DecodeError> {
    match Command::decode(frame) {
        Err(DecodeError::UnknownId { .. }) => Feedback::decode(frame).map(Message::Feedback),
        other => other.map(Message::Command),
    }
}
