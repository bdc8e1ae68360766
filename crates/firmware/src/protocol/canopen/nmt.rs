//! NMT: the master's node control (`0x000`) and the states a node reports.

use embedded_can::Frame;

use super::{Message, NodeId, layout};
use crate::protocol::error::DecodeError;
use crate::protocol::wire::{self, Payload};

u8_enum!(
    /// An NMT command (`NMT.command`).
    NmtCommand {
        /// Enter operational: PDOs flow.
        Start = 0x01 => "START",
        /// Enter stopped.
        Stop = 0x02 => "STOP",
        /// Enter pre-operational: SDOs only.
        EnterPreOperational = 0x80 => "PRE_OPERATIONAL",
        /// Reset the application (and the communication).
        ResetNode = 0x81 => "RESET_NODE",
        /// Reset the communication objects (PDO configuration) to their defaults.
        ResetCommunication = 0x82 => "RESET_COMMUNICATION",
    }
);

u8_enum!(
    /// A node's NMT state, as its heartbeat reports it.
    NmtState {
        /// The boot-up message: the node has (re)started and is pre-operational.
        BootUp = 0x00 => "BOOT_UP",
        /// Stopped.
        Stopped = 0x04 => "STOPPED",
        /// Operational.
        Operational = 0x05 => "OPERATIONAL",
        /// Pre-operational.
        PreOperational = 0x7F => "PRE_OPERATIONAL",
    }
);

/// Writes an NMT command for `node` (`None`: every node).
pub(super) fn put(p: &mut Payload, command: NmtCommand, node: Option<NodeId>) {
    layout::NMT_COMMAND.put_raw(p, command.raw().into());
    layout::NMT_NODE.put_raw(p, node.map_or(0, NodeId::get).into());
}

/// Reads an NMT frame (id `raw`, which is `0x000`).
pub(super) fn decode<F: Frame>(frame: &F, raw: u16) -> Result<Message, DecodeError> {
    let p = wire::data_payload(frame, raw, &[layout::NMT.dlc])?;
    let command = layout::NMT_COMMAND.raw(&p) as u8;
    let node = layout::NMT_NODE.checked(&p)? as u8;
    Ok(Message::Nmt {
        command: NmtCommand::from_raw(command).ok_or(DecodeError::OutOfRange {
            field: layout::NMT_COMMAND.name,
            value: command.into(),
        })?,
        node: NodeId::new(node),
    })
}
