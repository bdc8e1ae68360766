//! The PDOs as this project maps them (TPDO1/2 from a drive, RPDO1/3 to it) and the SYNC
//! that clocks them. The mapping is the one the master writes into each drive, so a frame on
//! a PDO id decodes as that mapping.

use embedded_can::Frame;

use super::{Message, NodeId, layout};
use crate::protocol::error::DecodeError;
use crate::protocol::wire::{self, Payload};

/// Writes a SYNC's payload; returns its DLC (1 with a counter, else 0).
pub(super) fn put_sync(p: &mut Payload, counter: Option<u8>) -> u8 {
    match counter {
        Some(c) => {
            layout::SYNC_COUNTER.put_raw(p, c.into());
            1
        }
        None => layout::SYNC.dlc,
    }
}

/// Reads a SYNC frame (id `raw`, which is `0x080`).
pub(super) fn decode_sync<F: Frame>(frame: &F, raw: u16) -> Result<Message, DecodeError> {
    let p = wire::data_payload(frame, raw, &layout::SYNC_DLCS)?;
    let counter = if frame.dlc() == 1 {
        Some(layout::SYNC_COUNTER.checked(&p)? as u8)
    } else {
        None
    };
    Ok(Message::Sync { counter })
}

/// Writes a PDO's payload; other messages write nothing.
pub(super) fn put(message: &Message, p: &mut Payload) {
    match *message {
        Message::Tpdo1 {
            statusword,
            velocity,
            ..
        } => {
            layout::STATUSWORD.put_raw(p, statusword.into());
            layout::VELOCITY_ACTUAL.put_raw(p, velocity.into());
        }
        Message::Tpdo2 { velocity, .. } => layout::VELOCITY_ACTUAL_2.put_raw(p, velocity.into()),
        Message::Rpdo1 {
            controlword,
            target,
            ..
        } => {
            layout::CONTROLWORD.put_raw(p, controlword.into());
            layout::TARGET_VELOCITY.put_raw(p, target.into());
        }
        Message::Rpdo3 { target, .. } => layout::TARGET_VELOCITY_2.put_raw(p, target.into()),
        _ => {}
    }
}

/// Reads the PDO of function code `function` from `node`; `None` for other functions.
pub(super) fn read(function: u16, node: NodeId, p: &Payload) -> Option<Message> {
    Some(match function {
        0x180 => Message::Tpdo1 {
            node,
            statusword: layout::STATUSWORD.raw(p) as u16,
            velocity: layout::VELOCITY_ACTUAL.raw(p) as i32,
        },
        0x280 => Message::Tpdo2 {
            node,
            velocity: layout::VELOCITY_ACTUAL_2.raw(p) as i32,
        },
        0x200 => Message::Rpdo1 {
            node,
            controlword: layout::CONTROLWORD.raw(p) as u16,
            target: layout::TARGET_VELOCITY.raw(p) as i32,
        },
        0x400 => Message::Rpdo3 {
            node,
            target: layout::TARGET_VELOCITY_2.raw(p) as i32,
        },
        _ => return None,
    })
}
