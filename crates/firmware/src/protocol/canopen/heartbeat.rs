//! Heartbeat and boot-up (`0x700 + node`): a node's NMT state, sent periodically.

use super::layout;
use super::nmt::NmtState;
use crate::protocol::error::DecodeError;
use crate::protocol::wire::Payload;

/// Writes a heartbeat reporting `state` ([`NmtState::BootUp`]: the boot-up message).
pub(super) fn put(p: &mut Payload, state: NmtState) {
    layout::HEARTBEAT_STATE.put_raw(p, state.raw().into());
}

/// Reads a heartbeat's state.
pub(super) fn read(p: &Payload) -> Result<NmtState, DecodeError> {
    let state = layout::HEARTBEAT_STATE.raw(p) as u8;
    NmtState::from_raw(state).ok_or(DecodeError::OutOfRange {
        field: layout::HEARTBEAT_STATE.name,
        value: state.into(),
    })
}
