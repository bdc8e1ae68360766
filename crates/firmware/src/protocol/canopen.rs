//! CANopen (CiA 301) frames as a CiA 402 velocity drive's master needs them: NMT, SYNC,
//! expedited SDO, EMCY, heartbeat and boot-up, and the PDOs as this project maps them.
//!
//! Every id is a function code plus a [`NodeId`] (`1..=127`). [`layout`] mirrors
//! `dbc/cia402.dbc` (which spells the frames out for nodes 1 and 2); [`Message`] is any frame
//! of the protocol, in either direction, [`decode`] reads one and
//! [`Message::to_can_frame`] writes one. The PDO contents are the mapping the master writes
//! into each drive, so a frame on a PDO id decodes as that mapping; the mapping, the
//! configuration sequence and the drive states are specified in `docs/protocol.md`, section
//! "CANopen CiA 402".
//!
//! Only expedited SDO transfers (1-4 data bytes) are implemented: the initiation of a
//! segmented or block transfer decodes as [`DecodeError::OutOfRange`] on the command byte,
//! which a master then treats as a failed transfer.

use embedded_can::{Frame, StandardId};

use super::error::DecodeError;
use super::wire::{self, Payload};
use crate::frame::CanFrame;

/// The frame layout: the Rust mirror of `dbc/cia402.dbc` (ids are the function codes; a
/// node's frame is `id + node`).
pub mod layout {
    use crate::protocol::wire::{ByteOrder::Little, Field, MessageDef, WireType::*};

    /// Largest node id.
    pub const NODE_MAX: u8 = 127;

    /// NMT node control (id 0x000, master → all).
    pub const NMT: MessageDef = MessageDef {
        name: "NMT",
        id: 0x000,
        dlc: 2,
    };
    /// SYNC (id 0x080, master → all); DLC 0, or 1 with a counter.
    pub const SYNC: MessageDef = MessageDef {
        name: "SYNC",
        id: 0x080,
        dlc: 0,
    };
    /// DLCs accepted for SYNC.
    pub const SYNC_DLCS: [u8; 2] = [0, 1];
    /// EMCY (0x080 + node).
    pub const EMCY: MessageDef = MessageDef {
        name: "EMCY",
        id: 0x080,
        dlc: 8,
    };
    /// TPDO1 (0x180 + node): statusword and the (first) axis's actual velocity.
    pub const TPDO1: MessageDef = MessageDef {
        name: "TPDO1",
        id: 0x180,
        dlc: 6,
    };
    /// TPDO2 (0x280 + node): the second axis's actual velocity (dual-axis nodes).
    pub const TPDO2: MessageDef = MessageDef {
        name: "TPDO2",
        id: 0x280,
        dlc: 4,
    };
    /// RPDO1 (0x200 + node): controlword and the (first) axis's target velocity.
    pub const RPDO1: MessageDef = MessageDef {
        name: "RPDO1",
        id: 0x200,
        dlc: 6,
    };
    /// RPDO3 (0x400 + node): the second axis's target velocity (dual-axis nodes). RPDO2's
    /// predefined id, 0x300 + node, is the robot protocol's block.
    pub const RPDO3: MessageDef = MessageDef {
        name: "RPDO3",
        id: 0x400,
        dlc: 4,
    };
    /// SDO server → client (0x580 + node).
    pub const SDO_RESPONSE: MessageDef = MessageDef {
        name: "SDO_RESPONSE",
        id: 0x580,
        dlc: 8,
    };
    /// SDO client → server (0x600 + node).
    pub const SDO_REQUEST: MessageDef = MessageDef {
        name: "SDO_REQUEST",
        id: 0x600,
        dlc: 8,
    };
    /// Heartbeat and boot-up (0x700 + node).
    pub const HEARTBEAT: MessageDef = MessageDef {
        name: "HEARTBEAT",
        id: 0x700,
        dlc: 1,
    };

    /// `NMT.command` (see [`super::NmtCommand`]).
    pub const NMT_COMMAND: Field = Field::int("command", 0, U8, Little);
    /// `NMT.node`: 0 addresses every node.
    pub const NMT_NODE: Field = Field::int("node", 1, U8, Little).range(0, NODE_MAX as i64);
    /// `SYNC.counter` (DLC 1 only).
    pub const SYNC_COUNTER: Field = Field::int("counter", 0, U8, Little).range(1, 240);

    /// `EMCY.error_code` (CiA 301 table 21; 0 = error reset).
    pub const EMCY_ERROR_CODE: Field = Field::int("error_code", 0, U16, Little);
    /// `EMCY.error_register` (object 0x1001).
    pub const EMCY_ERROR_REGISTER: Field = Field::int("error_register", 2, U8, Little);
    /// The first manufacturer-specific byte of EMCY (the DBC's 40-bit `manufacturer` signal
    /// is this byte and the next field).
    pub const EMCY_MANUFACTURER_LOW: Field = Field::int("manufacturer", 3, U8, Little);
    /// Manufacturer-specific bytes 4-7 of EMCY.
    pub const EMCY_MANUFACTURER_HIGH: Field = Field::int("manufacturer", 4, U32, Little);

    /// `TPDO1.statusword` (object 0x6041).
    pub const STATUSWORD: Field = Field::int("statusword", 0, U16, Little);
    /// `TPDO1.velocity_actual` (0x606C, sub 0 or 1), drive units.
    pub const VELOCITY_ACTUAL: Field = Field::int("velocity_actual", 2, I32, Little);
    /// `TPDO2.velocity_actual_2` (0x606C sub 2), drive units.
    pub const VELOCITY_ACTUAL_2: Field = Field::int("velocity_actual_2", 0, I32, Little);
    /// `RPDO1.controlword` (object 0x6040).
    pub const CONTROLWORD: Field = Field::int("controlword", 0, U16, Little);
    /// `RPDO1.target_velocity` (0x60FF, sub 0 or 1), drive units.
    pub const TARGET_VELOCITY: Field = Field::int("target_velocity", 2, I32, Little);
    /// `RPDO3.target_velocity_2` (0x60FF sub 2), drive units.
    pub const TARGET_VELOCITY_2: Field = Field::int("target_velocity_2", 0, I32, Little);

    /// SDO command byte (client or server command specifier, size and transfer bits).
    pub const SDO_COMMAND: Field = Field::int("command", 0, U8, Little);
    /// SDO object index.
    pub const SDO_INDEX: Field = Field::int("index", 1, U16, Little);
    /// SDO object sub-index.
    pub const SDO_SUBINDEX: Field = Field::int("subindex", 3, U8, Little);
    /// SDO data (expedited, little-endian, unused high bytes zero), or the abort code.
    pub const SDO_DATA: Field = Field::int("data", 4, U32, Little);

    /// `HEARTBEAT.state` (bit 7 is node guarding's toggle bit, not used by heartbeats).
    pub const HEARTBEAT_STATE: Field = Field::int("state", 0, U8, Little);

    /// SDO command byte: client "initiate download" (ccs 1), expedited, size given: `0x23`
    /// for 4 bytes, `0x27` 3, `0x2B` 2, `0x2F` 1.
    pub const SDO_DOWNLOAD: u8 = 0x23;
    /// SDO command byte: client "initiate upload" (ccs 2).
    pub const SDO_UPLOAD: u8 = 0x40;
    /// SDO command byte: server "initiate upload" response, expedited with size (`0x43` 4
    /// bytes ... `0x4F` 1); `0x42` (size not given) reads as 4 bytes.
    pub const SDO_UPLOADED: u8 = 0x43;
    /// SDO command byte: server "initiate download" response (scs 3).
    pub const SDO_DOWNLOADED: u8 = 0x60;
    /// SDO command byte: abort transfer (either direction).
    pub const SDO_ABORT: u8 = 0x80;
}

/// A CANopen node id, `1..=127`.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub struct NodeId(u8);

impl NodeId {
    /// A node id; `None` for 0 and above 127.
    #[must_use]
    pub const fn new(raw: u8) -> Option<Self> {
        if raw >= 1 && raw <= layout::NODE_MAX {
            Some(Self(raw))
        } else {
            None
        }
    }

    /// The raw node id.
    #[must_use]
    pub const fn get(self) -> u8 {
        self.0
    }

    /// The id of message `def` to or from this node.
    #[must_use]
    pub const fn can_id(self, def: wire::MessageDef) -> StandardId {
        // Function codes are at most 0x700 and nodes at most 127: the sum is below 0x800.
        match StandardId::new(def.id + self.0 as u16) {
            Some(id) => id,
            None => StandardId::ZERO,
        }
    }
}

/// An NMT command (`NMT.command`).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[repr(u8)]
pub enum NmtCommand {
    /// Enter operational: PDOs flow.
    Start = 0x01,
    /// Enter stopped.
    Stop = 0x02,
    /// Enter pre-operational: SDOs only.
    EnterPreOperational = 0x80,
    /// Reset the application (and the communication).
    ResetNode = 0x81,
    /// Reset the communication objects (PDO configuration) to their defaults.
    ResetCommunication = 0x82,
}

/// A node's NMT state, as its heartbeat reports it.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[repr(u8)]
pub enum NmtState {
    /// The boot-up message: the node has (re)started and is pre-operational.
    BootUp = 0x00,
    /// Stopped.
    Stopped = 0x04,
    /// Operational.
    Operational = 0x05,
    /// Pre-operational.
    PreOperational = 0x7F,
}

u8_enum!(NmtCommand {
    Start = 0x01 => "START",
    Stop = 0x02 => "STOP",
    EnterPreOperational = 0x80 => "PRE_OPERATIONAL",
    ResetNode = 0x81 => "RESET_NODE",
    ResetCommunication = 0x82 => "RESET_COMMUNICATION",
});
u8_enum!(NmtState {
    BootUp = 0x00 => "BOOT_UP",
    Stopped = 0x04 => "STOPPED",
    Operational = 0x05 => "OPERATIONAL",
    PreOperational = 0x7F => "PRE_OPERATIONAL",
});

/// The CiA 402 drive state a statusword reports (object 0x6041, bits 0-3, 5 and 6).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum DriveState402 {
    /// Not ready to switch on (initialising).
    NotReadyToSwitchOn,
    /// Switch on disabled (after power-up, a fault reset, a quick stop).
    SwitchOnDisabled,
    /// Ready to switch on (after shutdown, 0x06).
    ReadyToSwitchOn,
    /// Switched on (after switch on, 0x07).
    SwitchedOn,
    /// Operation enabled (after enable operation, 0x0F): the drive follows its target.
    OperationEnabled,
    /// Quick stop active (after quick stop, 0x02).
    QuickStopActive,
    /// Fault reaction active.
    FaultReactionActive,
    /// Fault.
    Fault,
}

impl DriveState402 {
    /// The state of a statusword; `None` for bit patterns CiA 402 does not define.
    #[must_use]
    pub const fn from_statusword(sw: u16) -> Option<Self> {
        Some(match (sw & 0x4F, sw & 0x6F) {
            (0x00, _) => Self::NotReadyToSwitchOn,
            (0x40, _) => Self::SwitchOnDisabled,
            (_, 0x21) => Self::ReadyToSwitchOn,
            (_, 0x23) => Self::SwitchedOn,
            (_, 0x27) => Self::OperationEnabled,
            (_, 0x07) => Self::QuickStopActive,
            (0x0F, _) => Self::FaultReactionActive,
            (0x08, _) => Self::Fault,
            _ => return None,
        })
    }

    /// The state a drive goes to on `controlword` (CiA 402's device control, the drive's
    /// side), `previous` the controlword before it: a fault leaves only on a rising edge of
    /// bit 7; shutdown, switch on, enable operation, disable voltage and quick stop as the
    /// profile's transitions 2-12 say; operation enabled only if `may_enable` (the drive's
    /// mode and its own conditions allow it). For the simulated and scripted drives: the
    /// master only reads states ([`Self::from_statusword`]).
    #[must_use]
    pub const fn on_controlword(self, cw: u16, previous: u16, may_enable: bool) -> Self {
        use DriveState402 as S;
        if let S::Fault | S::FaultReactionActive = self {
            let rising_reset = cw & 0x80 != 0 && previous & 0x80 == 0;
            return if rising_reset && matches!(self, S::Fault) {
                S::SwitchOnDisabled
            } else {
                self
            };
        }
        if cw & 0x80 != 0 {
            // Fault reset outside a fault: no transition.
            return self;
        }
        match (self, cw & 0x0F) {
            // Disable voltage (bit 1 clear): transitions 7, 9, 10, 12.
            (_, c) if c & 0x02 == 0 => S::SwitchOnDisabled,
            // Quick stop (bit 2 clear): 11 from operation enabled, 7 and 10 otherwise.
            (S::OperationEnabled | S::QuickStopActive, c) if c & 0x04 == 0 => S::QuickStopActive,
            (_, c) if c & 0x04 == 0 => S::SwitchOnDisabled,
            // Shutdown: 2, 6, 8.
            (S::SwitchOnDisabled | S::SwitchedOn | S::OperationEnabled, 0x06) => S::ReadyToSwitchOn,
            // Switch on (3) and disable operation (5).
            (S::ReadyToSwitchOn | S::OperationEnabled, 0x07) => S::SwitchedOn,
            // Enable operation: 4.
            (S::SwitchedOn, 0x0F) if may_enable => S::OperationEnabled,
            _ => self,
        }
    }

    /// A statusword reporting this state, as the project's simulated drives send it (bit 4,
    /// voltage enabled, and bit 9, remote, set).
    #[must_use]
    pub const fn statusword(self) -> u16 {
        match self {
            Self::NotReadyToSwitchOn => 0x0200,
            Self::SwitchOnDisabled => 0x0250,
            Self::ReadyToSwitchOn => 0x0231,
            Self::SwitchedOn => 0x0233,
            Self::OperationEnabled => 0x0237,
            Self::QuickStopActive => 0x0217,
            Self::FaultReactionActive => 0x021F,
            Self::Fault => 0x0218,
        }
    }

    /// A name for logs (CiA 402's, in capitals).
    #[must_use]
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::NotReadyToSwitchOn => "NOT_READY_TO_SWITCH_ON",
            Self::SwitchOnDisabled => "SWITCH_ON_DISABLED",
            Self::ReadyToSwitchOn => "READY_TO_SWITCH_ON",
            Self::SwitchedOn => "SWITCHED_ON",
            Self::OperationEnabled => "OPERATION_ENABLED",
            Self::QuickStopActive => "QUICK_STOP_ACTIVE",
            Self::FaultReactionActive => "FAULT_REACTION_ACTIVE",
            Self::Fault => "FAULT",
        }
    }
}

/// Statusword bit 3: a fault (or its reaction) is active.
pub const STATUSWORD_FAULT: u16 = 1 << 3;

/// Controlword commands (object 0x6040) of the CiA 402 state machine.
pub mod controlword {
    /// Shutdown: to ready to switch on (no torque).
    pub const SHUTDOWN: u16 = 0x06;
    /// Switch on: to switched on.
    pub const SWITCH_ON: u16 = 0x07;
    /// Enable operation: to operation enabled.
    pub const ENABLE_OPERATION: u16 = 0x0F;
    /// Quick stop (bit 2 clear): to quick stop active, then switch on disabled.
    pub const QUICK_STOP: u16 = 0x02;
    /// Disable voltage (bit 1 clear): to switch on disabled, from any powered state.
    pub const DISABLE_VOLTAGE: u16 = 0x00;
    /// Fault reset: its rising edge (bit 7) leaves fault for switch on disabled.
    pub const FAULT_RESET: u16 = 0x80;
}

/// An SDO request, client (master) → server (drive).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SdoRequest {
    /// Read an object.
    Upload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Write an object of `size` bytes (1..=4), expedited.
    Download {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value, little-endian in the `size` low bytes.
        value: u32,
        /// Data bytes, 1..=4.
        size: u8,
    },
    /// Abort a transfer.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code (CiA 301 table 22).
        code: u32,
    },
}

/// An SDO response, server (drive) → client (master).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SdoResponse {
    /// The value of an object read (expedited).
    Uploaded {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value (bytes beyond `size` zero).
        value: u32,
        /// Data bytes, 1..=4.
        size: u8,
    },
    /// A write was done.
    Downloaded {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// The transfer was refused.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code (CiA 301 table 22).
        code: u32,
    },
}

impl SdoRequest {
    /// The object the request is about.
    #[must_use]
    pub const fn object(&self) -> (u16, u8) {
        match *self {
            Self::Upload { index, sub }
            | Self::Download { index, sub, .. }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }
}

impl SdoResponse {
    /// The object the response is about.
    #[must_use]
    pub const fn object(&self) -> (u16, u8) {
        match *self {
            Self::Uploaded { index, sub, .. }
            | Self::Downloaded { index, sub }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }

    /// Whether this is the answer to `request`: the same index and sub-index, and the
    /// server command that answers the client's (an upload by an upload response, a
    /// download by a download response; either by an abort). A response to another
    /// transfer on the same object, late or misrouted, is not.
    #[must_use]
    pub const fn answers(&self, request: &SdoRequest) -> bool {
        let (index, sub) = self.object();
        let (r_index, r_sub) = request.object();
        let command_fits = matches!(
            (self, request),
            (
                Self::Abort { .. },
                SdoRequest::Upload { .. } | SdoRequest::Download { .. }
            ) | (Self::Uploaded { .. }, SdoRequest::Upload { .. })
                | (Self::Downloaded { .. }, SdoRequest::Download { .. })
        );
        index == r_index && sub == r_sub && command_fits
    }
}

/// SDO abort codes (CiA 301 table 22) the master sends or acts on.
pub mod abort_code {
    /// SDO protocol timed out: the client gives a transfer up.
    pub const TIMEOUT: u32 = 0x0504_0000;
    /// Object does not exist in the object dictionary.
    pub const NO_OBJECT: u32 = 0x0602_0000;
    /// Sub-index does not exist.
    pub const NO_SUBINDEX: u32 = 0x0609_0011;
    /// Invalid value for parameter (value range exceeded).
    pub const INVALID_VALUE: u32 = 0x0609_0030;
}

/// A short description of an SDO abort code (CiA 301 table 22), for logs; `None` for codes
/// it does not list.
#[must_use]
pub const fn abort_text(code: u32) -> Option<&'static str> {
    Some(match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "command specifier not valid or unknown",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write only object",
        0x0601_0002 => "attempt to write a read only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => "the number and length of the objects to be mapped would exceed PDO length",
        0x0604_0043 => "general parameter incompatibility",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter",
        0x0609_0031 => "value of parameter written too high",
        0x0609_0032 => "value of parameter written too low",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => "data cannot be transferred because of local control",
        0x0800_0022 => "data cannot be transferred because of the present device state",
        _ => return None,
    })
}

/// An emergency message's contents.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Emcy {
    /// Error code (CiA 301 table 21, CiA 402 for drive errors); 0 = error reset.
    pub error_code: u16,
    /// The error register (object 0x1001).
    pub error_register: u8,
    /// Manufacturer-specific bytes 3-7.
    pub manufacturer: [u8; 5],
}

/// Any frame of the protocol.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Message {
    /// NMT node control; `node` `None` addresses every node.
    Nmt {
        /// The command.
        command: NmtCommand,
        /// The node addressed (`None`: all).
        node: Option<NodeId>,
    },
    /// SYNC, with its counter if it has one.
    Sync {
        /// The counter (DLC 1), `1..=240` (an encoder saturates others into the range).
        counter: Option<u8>,
    },
    /// An emergency message from `node`.
    Emcy {
        /// The sender.
        node: NodeId,
        /// Its contents.
        emcy: Emcy,
    },
    /// TPDO1 from `node`.
    Tpdo1 {
        /// The sender.
        node: NodeId,
        /// Object 0x6041.
        statusword: u16,
        /// Object 0x606C (sub 0 or 1), drive units.
        velocity: i32,
    },
    /// TPDO2 from `node` (dual-axis).
    Tpdo2 {
        /// The sender.
        node: NodeId,
        /// Object 0x606C sub 2, drive units.
        velocity: i32,
    },
    /// RPDO1 to `node`.
    Rpdo1 {
        /// The receiver.
        node: NodeId,
        /// Object 0x6040.
        controlword: u16,
        /// Object 0x60FF (sub 0 or 1), drive units.
        target: i32,
    },
    /// RPDO3 to `node` (dual-axis).
    Rpdo3 {
        /// The receiver.
        node: NodeId,
        /// Object 0x60FF sub 2, drive units.
        target: i32,
    },
    /// An SDO request to `node`.
    SdoRequest {
        /// The server.
        node: NodeId,
        /// The request.
        request: SdoRequest,
    },
    /// An SDO response from `node`.
    SdoResponse {
        /// The server.
        node: NodeId,
        /// The response.
        response: SdoResponse,
    },
    /// A heartbeat (or, with [`NmtState::BootUp`], the boot-up message) of `node`.
    Heartbeat {
        /// The sender.
        node: NodeId,
        /// Its NMT state.
        state: NmtState,
    },
}

/// The messages by the id's top four bits (`id >> 7`), for [`decode`]; `None` for the
/// function codes not used here (time stamp, RPDO2, TPDO3/4, RPDO4, LSS).
const FUNCTIONS: [Option<wire::MessageDef>; 16] = [
    // 0x000 is NMT (decoded before the table); 0x001..=0x07F are nothing.
    None,
    Some(layout::EMCY),
    None,
    Some(layout::TPDO1),
    Some(layout::RPDO1),
    Some(layout::TPDO2),
    None,
    None,
    Some(layout::RPDO3),
    None,
    None,
    Some(layout::SDO_RESPONSE),
    Some(layout::SDO_REQUEST),
    None,
    Some(layout::HEARTBEAT),
    None,
];

impl Message {
    /// The message's layout row (its function code and DLC).
    #[must_use]
    pub const fn def(&self) -> wire::MessageDef {
        match self {
            Self::Nmt { .. } => layout::NMT,
            Self::Sync { .. } => layout::SYNC,
            Self::Emcy { .. } => layout::EMCY,
            Self::Tpdo1 { .. } => layout::TPDO1,
            Self::Tpdo2 { .. } => layout::TPDO2,
            Self::Rpdo1 { .. } => layout::RPDO1,
            Self::Rpdo3 { .. } => layout::RPDO3,
            Self::SdoRequest { .. } => layout::SDO_REQUEST,
            Self::SdoResponse { .. } => layout::SDO_RESPONSE,
            Self::Heartbeat { .. } => layout::HEARTBEAT,
        }
    }

    /// The node a message comes from or goes to (`None` for SYNC and a broadcast NMT).
    #[must_use]
    pub const fn node(&self) -> Option<NodeId> {
        match *self {
            Self::Nmt { node, .. } => node,
            Self::Sync { .. } => None,
            Self::Emcy { node, .. }
            | Self::Tpdo1 { node, .. }
            | Self::Tpdo2 { node, .. }
            | Self::Rpdo1 { node, .. }
            | Self::Rpdo3 { node, .. }
            | Self::SdoRequest { node, .. }
            | Self::SdoResponse { node, .. }
            | Self::Heartbeat { node, .. } => Some(node),
        }
    }

    /// Encodes into a [`CanFrame`].
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        let def = self.def();
        let mut p = Payload::new();
        let mut dlc = def.dlc;
        let id = match *self {
            Self::Nmt { command, node } => {
                layout::NMT_COMMAND.put_raw(&mut p, command.raw().into());
                layout::NMT_NODE.put_raw(&mut p, node.map_or(0, NodeId::get).into());
                StandardId::ZERO
            }
            Self::Sync { counter } => {
                if let Some(c) = counter {
                    layout::SYNC_COUNTER.put_raw(&mut p, c.into());
                    dlc = 1;
                }
                NodeId(0).can_id(def)
            }
            Self::Emcy { node, emcy } => {
                layout::EMCY_ERROR_CODE.put_raw(&mut p, emcy.error_code.into());
                layout::EMCY_ERROR_REGISTER.put_raw(&mut p, emcy.error_register.into());
                let [m0, m1, m2, m3, m4] = emcy.manufacturer;
                layout::EMCY_MANUFACTURER_LOW.put_raw(&mut p, m0.into());
                layout::EMCY_MANUFACTURER_HIGH
                    .put_raw(&mut p, u32::from_le_bytes([m1, m2, m3, m4]).into());
                node.can_id(def)
            }
            Self::Tpdo1 {
                node,
                statusword,
                velocity,
            } => {
                layout::STATUSWORD.put_raw(&mut p, statusword.into());
                layout::VELOCITY_ACTUAL.put_raw(&mut p, velocity.into());
                node.can_id(def)
            }
            Self::Tpdo2 { node, velocity } => {
                layout::VELOCITY_ACTUAL_2.put_raw(&mut p, velocity.into());
                node.can_id(def)
            }
            Self::Rpdo1 {
                node,
                controlword,
                target,
            } => {
                layout::CONTROLWORD.put_raw(&mut p, controlword.into());
                layout::TARGET_VELOCITY.put_raw(&mut p, target.into());
                node.can_id(def)
            }
            Self::Rpdo3 { node, target } => {
                layout::TARGET_VELOCITY_2.put_raw(&mut p, target.into());
                node.can_id(def)
            }
            Self::SdoRequest { node, request } => {
                let (command, data) = match request {
                    SdoRequest::Upload { .. } => (layout::SDO_UPLOAD, 0),
                    SdoRequest::Download { value, size, .. } => {
                        let size = size.clamp(1, 4);
                        (layout::SDO_DOWNLOAD | (4 - size) << 2, mask(value, size))
                    }
                    SdoRequest::Abort { code, .. } => (layout::SDO_ABORT, code),
                };
                put_sdo(&mut p, command, request.object(), data);
                node.can_id(def)
            }
            Self::SdoResponse { node, response } => {
                let (command, data) = match response {
                    SdoResponse::Uploaded { value, size, .. } => {
                        let size = size.clamp(1, 4);
                        (layout::SDO_UPLOADED | (4 - size) << 2, mask(value, size))
                    }
                    SdoResponse::Downloaded { .. } => (layout::SDO_DOWNLOADED, 0),
                    SdoResponse::Abort { code, .. } => (layout::SDO_ABORT, code),
                };
                put_sdo(&mut p, command, response.object(), data);
                node.can_id(def)
            }
            Self::Heartbeat { node, state } => {
                layout::HEARTBEAT_STATE.put_raw(&mut p, state.raw().into());
                node.can_id(def)
            }
        };
        CanFrame::from_buffer(id, p.0, dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
    }
}

/// The `size` low bytes of `value`.
const fn mask(value: u32, size: u8) -> u32 {
    match size {
        1 => value & 0xFF,
        2 => value & 0xFFFF,
        3 => value & 0xFF_FFFF,
        _ => value,
    }
}

fn put_sdo(p: &mut Payload, command: u8, (index, sub): (u16, u8), data: u32) {
    layout::SDO_COMMAND.put_raw(p, command.into());
    layout::SDO_INDEX.put_raw(p, index.into());
    layout::SDO_SUBINDEX.put_raw(p, sub.into());
    layout::SDO_DATA.put_raw(p, data.into());
}

/// The object of an SDO frame's payload.
fn sdo_object(p: &Payload) -> (u16, u8) {
    // The fields are 16 and 8 bits wide.
    (
        layout::SDO_INDEX.raw(p) as u16,
        layout::SDO_SUBINDEX.raw(p) as u8,
    )
}

/// The data size of an expedited transfer's command byte: `n` in bits 2-3 counts the unused
/// bytes when bit 0 (size indicated) is set; without it the size is 4.
const fn expedited_size(command: u8) -> u8 {
    if command & 0x01 != 0 {
        4 - ((command >> 2) & 0x03)
    } else {
        4
    }
}

fn bad_command(command: u8) -> DecodeError {
    DecodeError::OutOfRange {
        field: layout::SDO_COMMAND.name,
        value: command.into(),
    }
}

/// Decodes any frame of the protocol.
///
/// # Errors
/// See [`DecodeError`]: `UnknownId` for ids of function codes not used here (time stamp,
/// RPDO2, TPDO3/4, RPDO4, LSS) and for node 0 where a node is needed; `OutOfRange` for
/// unknown NMT commands and states, and SDO command bytes other than the expedited
/// transfers and aborts.
pub fn decode<F: Frame>(frame: &F) -> Result<Message, DecodeError> {
    let raw = wire::standard_id(frame)?;
    let function = raw & 0x780;
    let node_raw = (raw & 0x7F) as u8;
    if raw == layout::NMT.id {
        let p = wire::data_payload(frame, raw, &[layout::NMT.dlc])?;
        let command = layout::NMT_COMMAND.raw(&p) as u8;
        let node = layout::NMT_NODE.checked(&p)? as u8;
        return Ok(Message::Nmt {
            command: NmtCommand::from_raw(command).ok_or(DecodeError::OutOfRange {
                field: layout::NMT_COMMAND.name,
                value: command.into(),
            })?,
            node: NodeId::new(node),
        });
    }
    if raw == layout::SYNC.id {
        let p = wire::data_payload(frame, raw, &layout::SYNC_DLCS)?;
        let counter = if frame.dlc() == 1 {
            Some(layout::SYNC_COUNTER.checked(&p)? as u8)
        } else {
            None
        };
        return Ok(Message::Sync { counter });
    }
    let def = FUNCTIONS.get(usize::from(raw >> 7)).copied().flatten();
    let (Some(node), Some(def)) = (NodeId::new(node_raw), def) else {
        return Err(wire::unknown(frame));
    };
    let p = wire::data_payload(frame, raw, &[def.dlc])?;
    Ok(match function {
        0x080 => Message::Emcy {
            node,
            emcy: Emcy {
                error_code: layout::EMCY_ERROR_CODE.raw(&p) as u16,
                error_register: layout::EMCY_ERROR_REGISTER.raw(&p) as u8,
                manufacturer: {
                    let low = layout::EMCY_MANUFACTURER_LOW.raw(&p) as u8;
                    let [a, b, c, d] =
                        (layout::EMCY_MANUFACTURER_HIGH.raw(&p) as u32).to_le_bytes();
                    [low, a, b, c, d]
                },
            },
        },
        0x180 => Message::Tpdo1 {
            node,
            statusword: layout::STATUSWORD.raw(&p) as u16,
            velocity: layout::VELOCITY_ACTUAL.raw(&p) as i32,
        },
        0x280 => Message::Tpdo2 {
            node,
            velocity: layout::VELOCITY_ACTUAL_2.raw(&p) as i32,
        },
        0x200 => Message::Rpdo1 {
            node,
            controlword: layout::CONTROLWORD.raw(&p) as u16,
            target: layout::TARGET_VELOCITY.raw(&p) as i32,
        },
        0x400 => Message::Rpdo3 {
            node,
            target: layout::TARGET_VELOCITY_2.raw(&p) as i32,
        },
        0x600 => {
            let command = layout::SDO_COMMAND.raw(&p) as u8;
            let (index, sub) = sdo_object(&p);
            let data = layout::SDO_DATA.raw(&p) as u32;
            let request = match command {
                layout::SDO_UPLOAD => SdoRequest::Upload { index, sub },
                layout::SDO_ABORT => SdoRequest::Abort {
                    index,
                    sub,
                    code: data,
                },
                // ccs 1, expedited (bit 1), bit 4 clear.
                c if c & 0xF2 == 0x22 => {
                    let size = expedited_size(c);
                    SdoRequest::Download {
                        index,
                        sub,
                        value: mask(data, size),
                        size,
                    }
                }
                c => return Err(bad_command(c)),
            };
            Message::SdoRequest { node, request }
        }
        0x580 => {
            let command = layout::SDO_COMMAND.raw(&p) as u8;
            let (index, sub) = sdo_object(&p);
            let data = layout::SDO_DATA.raw(&p) as u32;
            let response = match command {
                layout::SDO_DOWNLOADED => SdoResponse::Downloaded { index, sub },
                layout::SDO_ABORT => SdoResponse::Abort {
                    index,
                    sub,
                    code: data,
                },
                // scs 2, expedited (bit 1), bit 4 clear.
                c if c & 0xF2 == 0x42 => {
                    let size = expedited_size(c);
                    SdoResponse::Uploaded {
                        index,
                        sub,
                        value: mask(data, size),
                        size,
                    }
                }
                c => return Err(bad_command(c)),
            };
            Message::SdoResponse { node, response }
        }
        _ => {
            let state = layout::HEARTBEAT_STATE.raw(&p) as u8;
            Message::Heartbeat {
                node,
                state: NmtState::from_raw(state).ok_or(DecodeError::OutOfRange {
                    field: layout::HEARTBEAT_STATE.name,
                    value: state.into(),
                })?,
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    #[test]
    fn sdo_command_bytes_follow_cia301() {
        let node = NodeId::new(5).unwrap();
        for (size, byte) in [(1, 0x2F), (2, 0x2B), (3, 0x27), (4, 0x23)] {
            let m = Message::SdoRequest {
                node,
                request: SdoRequest::Download {
                    index: 0x6060,
                    sub: 0,
                    value: 0x0403_0203,
                    size,
                },
            };
            let f = m.to_can_frame();
            assert_eq!(f.data()[..4], [byte, 0x60, 0x60, 0x00]);
            assert_eq!(
                f.id(),
                embedded_can::Id::Standard(StandardId::new(0x605).unwrap())
            );
            let back = decode(&f).unwrap();
            let Message::SdoRequest {
                request: SdoRequest::Download { value, size: s, .. },
                ..
            } = back
            else {
                panic!("{back:?}");
            };
            assert_eq!((s, value), (size, mask(0x0403_0203, size)));
        }
        // An upload answered with 2 bytes, and one without a size (0x42) reads as 4 bytes.
        let r = decode(&frame(
            0x585,
            &[0x4B, 0x41, 0x60, 0, 0x27, 0x02, 0xAA, 0xBB],
        ))
        .unwrap();
        assert_eq!(
            r,
            Message::SdoResponse {
                node,
                response: SdoResponse::Uploaded {
                    index: 0x6041,
                    sub: 0,
                    value: 0x0227,
                    size: 2
                }
            }
        );
        let r = decode(&frame(0x585, &[0x42, 0, 0x10, 0, 0x92, 0x01, 0x02, 0])).unwrap();
        assert!(matches!(
            r,
            Message::SdoResponse {
                response: SdoResponse::Uploaded {
                    value: 0x0002_0192,
                    size: 4,
                    ..
                },
                ..
            }
        ));
        // A segmented upload's initiation is refused on its command byte.
        assert_eq!(
            decode(&frame(0x585, &[0x41, 0, 0x10, 0, 20, 0, 0, 0])),
            Err(DecodeError::OutOfRange {
                field: "command",
                value: 0x41
            })
        );
        let abort = decode(&frame(0x585, &[0x80, 0x60, 0x60, 0, 0x11, 0, 0x09, 0x06])).unwrap();
        assert_eq!(
            abort,
            Message::SdoResponse {
                node,
                response: SdoResponse::Abort {
                    index: 0x6060,
                    sub: 0,
                    code: 0x0609_0011
                }
            }
        );
        assert_eq!(abort_text(0x0609_0011), Some("sub-index does not exist"));
    }

    #[test]
    fn statusword_states_follow_cia402() {
        use DriveState402 as S;
        for (sw, state) in [
            (0x0000, S::NotReadyToSwitchOn),
            (0x0250, S::SwitchOnDisabled),
            (0x0231, S::ReadyToSwitchOn),
            (0x0233, S::SwitchedOn),
            (0x0637, S::OperationEnabled),
            (0x0217, S::QuickStopActive),
            (0x021F, S::FaultReactionActive),
            (0x0218, S::Fault),
        ] {
            assert_eq!(DriveState402::from_statusword(sw), Some(state), "{sw:#06x}");
        }
        assert_eq!(DriveState402::from_statusword(0x0001), None);
    }

    #[test]
    fn the_drive_side_machine_follows_cia402s_transitions() {
        use DriveState402 as S;
        let walk = |cws: &[u16], may_enable: bool| {
            let (mut s, mut prev) = (S::SwitchOnDisabled, 0);
            for &cw in cws {
                s = s.on_controlword(cw, prev, may_enable);
                prev = cw;
            }
            s
        };
        assert_eq!(walk(&[0x06, 0x07, 0x0F], true), S::OperationEnabled);
        assert_eq!(walk(&[0x06, 0x07, 0x0F], false), S::SwitchedOn);
        assert_eq!(
            walk(&[0x07, 0x0F], true),
            S::SwitchOnDisabled,
            "no skipping"
        );
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x02], true), S::QuickStopActive);
        assert_eq!(
            walk(&[0x06, 0x07, 0x0F, 0x02, 0x00], true),
            S::SwitchOnDisabled
        );
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x06], true), S::ReadyToSwitchOn);
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x07], true), S::SwitchedOn);
        // A fault leaves on the rising edge of bit 7 only.
        assert_eq!(S::Fault.on_controlword(0x80, 0x80, true), S::Fault);
        assert_eq!(S::Fault.on_controlword(0x06, 0x80, true), S::Fault);
        assert_eq!(
            S::Fault.on_controlword(0x80, 0x06, true),
            S::SwitchOnDisabled
        );
        for s in [
            S::NotReadyToSwitchOn,
            S::SwitchOnDisabled,
            S::ReadyToSwitchOn,
            S::SwitchedOn,
            S::OperationEnabled,
            S::QuickStopActive,
            S::FaultReactionActive,
            S::Fault,
        ] {
            assert_eq!(S::from_statusword(s.statusword()), Some(s));
        }
    }

    #[test]
    fn unused_functions_and_node_zero_are_unknown() {
        for id in [
            0x100, 0x301, 0x381, 0x481, 0x501, 0x681, 0x7E5, 0x180, 0x700,
        ] {
            assert!(
                matches!(
                    decode(&frame(id, &[0; 8])),
                    Err(DecodeError::UnknownId { .. })
                ),
                "{id:#x}"
            );
        }
        assert_eq!(
            decode(&frame(0x701, &[0x06])),
            Err(DecodeError::OutOfRange {
                field: "state",
                value: 6
            })
        );
        assert_eq!(
            decode(&frame(0x181, &[0; 8])),
            Err(DecodeError::WrongDlc {
                id: 0x181,
                expected: 6,
                got: 8
            })
        );
        assert_eq!(
            decode(&frame(0x080, &[1])),
            Ok(Message::Sync { counter: Some(1) })
        );
        assert_eq!(
            decode(&frame(0x080, &[])),
            Ok(Message::Sync { counter: None })
        );
    }

    #[test]
    fn every_message_round_trips() {
        let n = NodeId::new(127).unwrap();
        let messages = [
            Message::Nmt {
                command: NmtCommand::ResetCommunication,
                node: None,
            },
            Message::Nmt {
                command: NmtCommand::Start,
                node: Some(n),
            },
            Message::Sync { counter: Some(240) },
            Message::Emcy {
                node: n,
                emcy: Emcy {
                    error_code: 0x8130,
                    error_register: 0x11,
                    manufacturer: [1, 2, 3, 4, 5],
                },
            },
            Message::Tpdo1 {
                node: n,
                statusword: 0x0637,
                velocity: -123_456,
            },
            Message::Tpdo2 {
                node: n,
                velocity: i32::MIN,
            },
            Message::Rpdo1 {
                node: n,
                controlword: controlword::ENABLE_OPERATION,
                target: i32::MAX,
            },
            Message::Rpdo3 {
                node: n,
                target: -1,
            },
            Message::SdoRequest {
                node: n,
                request: SdoRequest::Upload {
                    index: 0x1000,
                    sub: 0,
                },
            },
            Message::SdoRequest {
                node: n,
                request: SdoRequest::Abort {
                    index: 0x1000,
                    sub: 0,
                    code: 0x0504_0000,
                },
            },
            Message::SdoResponse {
                node: n,
                response: SdoResponse::Downloaded {
                    index: 0x1A00,
                    sub: 2,
                },
            },
            Message::Heartbeat {
                node: n,
                state: NmtState::BootUp,
            },
        ];
        for m in messages {
            assert_eq!(decode(&m.to_can_frame()), Ok(m), "{m:?}");
        }
    }

    #[test]
    fn an_sdo_answer_matches_index_subindex_and_command() {
        let up = SdoRequest::Upload {
            index: 0x6061,
            sub: 0,
        };
        let down = SdoRequest::Download {
            index: 0x6061,
            sub: 0,
            value: 3,
            size: 1,
        };
        let uploaded = |index, sub| SdoResponse::Uploaded {
            index,
            sub,
            value: 3,
            size: 1,
        };
        let downloaded = SdoResponse::Downloaded {
            index: 0x6061,
            sub: 0,
        };
        let abort = SdoResponse::Abort {
            index: 0x6061,
            sub: 0,
            code: abort_code::NO_OBJECT,
        };
        assert!(uploaded(0x6061, 0).answers(&up));
        assert!(abort.answers(&up) && abort.answers(&down));
        assert!(downloaded.answers(&down));
        // The same object, the wrong command: the answer to another transfer.
        assert!(!downloaded.answers(&up));
        assert!(!uploaded(0x6061, 0).answers(&down));
        // The right command, another index or sub-index.
        assert!(!uploaded(0x6060, 0).answers(&up));
        assert!(!uploaded(0x6061, 1).answers(&up));
        // A client's abort is answered by nothing.
        let client_abort = SdoRequest::Abort {
            index: 0x6061,
            sub: 0,
            code: abort_code::TIMEOUT,
        };
        assert!(!abort.answers(&client_abort) && !downloaded.answers(&client_abort));
    }
}
