//! CANopen (CiA 301) frames as a CiA 402 velocity drive's master needs them: NMT, SYNC,
//! expedited SDO, EMCY, heartbeat and boot-up, and the PDOs as this project maps them.
//!
//! Every id is a function code plus a [`NodeId`] (`1..=127`). [`layout`] mirrors
//! `dbc/cia402.dbc` (which spells the frames out for nodes 1 and 2); [`Message`] is any frame
//! of the protocol, in either direction, [`decode`] reads one and
//! [`Message::to_can_frame`] writes one. Each service has its file: `nmt`, `sdo`, `pdo` (with
//! SYNC), `emcy`, `heartbeat`, and `cia402` for the drive profile's states and controlwords;
//! this one holds the ids and the dispatch. The PDO mapping, the configuration sequence and
//! the drive states are specified in `docs/protocol.md`, section "CANopen CiA 402".
//!
//! Only expedited SDO transfers (1-4 data bytes) are implemented: the initiation of a
//! segmented or block transfer decodes as [`DecodeError::OutOfRange`] on the command byte,
//! which a master then treats as a failed transfer.

use embedded_can::{Frame, StandardId};

use super::error::DecodeError;
use super::wire::{self, Payload};
use crate::frame::CanFrame;

mod cia402;
pub mod drive;
mod emcy;
mod heartbeat;
pub mod layout;
mod nmt;
mod pdo;
mod sdo;

pub use cia402::{DriveState402, STATUSWORD_FAULT, controlword};
pub use emcy::Emcy;
pub use nmt::{NmtCommand, NmtState};
pub use sdo::{SdoRequest, SdoResponse, abort_code, abort_text};

u8_id!(
    /// A CANopen node id, `1..=127`.
    NodeId(1..=layout::NODE_MAX)
);

impl NodeId {
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
        match *self {
            Self::Nmt { command, node } => nmt::put(&mut p, command, node),
            Self::Sync { counter } => dlc = pdo::put_sync(&mut p, counter),
            Self::Emcy { emcy, .. } => emcy.put(&mut p),
            Self::Tpdo1 { .. } | Self::Tpdo2 { .. } | Self::Rpdo1 { .. } | Self::Rpdo3 { .. } => {
                pdo::put(self, &mut p);
            }
            Self::SdoRequest { request, .. } => request.put(&mut p),
            Self::SdoResponse { response, .. } => response.put(&mut p),
            Self::Heartbeat { state, .. } => heartbeat::put(&mut p, state),
        }
        // NMT and SYNC go to every node: their ids are the bare function codes (an NMT's
        // node is in its payload).
        let id = match self {
            Self::Nmt { .. } | Self::Sync { .. } => NodeId(0).can_id(def),
            _ => self.node().unwrap_or(NodeId(0)).can_id(def),
        };
        CanFrame::from_buffer(id, p.0, dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
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
        return nmt::decode(frame, raw);
    }
    if raw == layout::SYNC.id {
        return pdo::decode_sync(frame, raw);
    }
    let def = FUNCTIONS.get(usize::from(raw >> 7)).copied().flatten();
    let (Some(node), Some(def)) = (NodeId::new(node_raw), def) else {
        return Err(wire::unknown(frame));
    };
    let p = wire::data_payload(frame, raw, &[def.dlc])?;
    Ok(match function {
        0x080 => Message::Emcy {
            node,
            emcy: Emcy::read(&p),
        },
        0x600 => Message::SdoRequest {
            node,
            request: SdoRequest::read(&p)?,
        },
        0x580 => Message::SdoResponse {
            node,
            response: SdoResponse::read(&p)?,
        },
        0x700 => Message::Heartbeat {
            node,
            state: heartbeat::read(&p)?,
        },
        _ => pdo::read(function, node, &p).ok_or_else(|| wire::unknown(frame))?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
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
}
