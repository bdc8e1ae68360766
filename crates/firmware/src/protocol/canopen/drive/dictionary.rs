//! The node's object dictionary: a fixed set of objects, each value a `u32`, at their
//! defaults after a reset node; the communication area (0x1000-0x1FFF) alone after a reset
//! communication.

use super::DEVICE_TYPE;
use crate::protocol::canopen::NodeId;

/// The error register (0x1001): a state of the node, not a parameter, so kept by reset
/// communication.
pub(super) const ERROR_REGISTER: (u16, u8) = (0x1001, 0);

/// The communication area (CiA 301): what reset communication sets back to its defaults.
const COMMUNICATION_AREA: core::ops::RangeInclusive<u16> = 0x1000..=0x1FFF;

/// Objects in the dictionary: eight single ones, the four RPDO and TPDO communication
/// objects (sub-indices 1 and 2) and their mappings (0 to 8).
const LEN: usize = 8 + 2 * 4 * 2 + 2 * 4 * 9;

/// The single objects, in slot order.
const SINGLE: [(u16, u8); 8] = [
    (0x1000, 0),
    ERROR_REGISTER,
    (0x1016, 1),
    (0x1017, 0),
    (0x605B, 0),
    (0x605C, 0),
    (0x6060, 0),
    (0x6061, 0),
];

/// First slots of the RPDO and TPDO communication objects and of their mappings.
const RPDO_COMM: usize = 8;
const TPDO_COMM: usize = RPDO_COMM + 8;
const RPDO_MAP: usize = TPDO_COMM + 8;
const TPDO_MAP: usize = RPDO_MAP + 36;

/// The slot of `(index, sub)` in a dictionary with every object (0x605B / 0x605C included).
const fn slot(index: u16, sub: u8) -> Option<usize> {
    let sub_us = sub as usize;
    let k = (index & 0x3) as usize;
    Some(match index {
        0x1400..=0x1403 if matches!(sub, 1 | 2) => RPDO_COMM + 2 * k + sub_us - 1,
        0x1800..=0x1803 if matches!(sub, 1 | 2) => TPDO_COMM + 2 * k + sub_us - 1,
        0x1600..=0x1603 if sub <= 8 => RPDO_MAP + 9 * k + sub_us,
        0x1A00..=0x1A03 if sub <= 8 => TPDO_MAP + 9 * k + sub_us,
        _ => {
            let mut i = 0;
            while i < SINGLE.len() {
                if SINGLE[i].0 == index && SINGLE[i].1 == sub {
                    return Some(i);
                }
                i += 1;
            }
            return None;
        }
    })
}

/// The `(index, sub)` of slot `s` (`s < LEN`).
const fn key(s: usize) -> (u16, u8) {
    // Slots are below LEN (96): the casts keep every value.
    #[allow(clippy::cast_possible_truncation)]
    match s {
        RPDO_COMM..TPDO_COMM => {
            let i = s - RPDO_COMM;
            (0x1400 + (i / 2) as u16, (i % 2) as u8 + 1)
        }
        TPDO_COMM..RPDO_MAP => {
            let i = s - TPDO_COMM;
            (0x1800 + (i / 2) as u16, (i % 2) as u8 + 1)
        }
        RPDO_MAP..TPDO_MAP => {
            let i = s - RPDO_MAP;
            (0x1600 + (i / 9) as u16, (i % 9) as u8)
        }
        TPDO_MAP.. => {
            let i = s - TPDO_MAP;
            (0x1A00 + (i / 9) as u16, (i % 9) as u8)
        }
        _ => SINGLE[s],
    }
}

/// A node's object dictionary.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Dictionary {
    values: [u32; LEN],
    /// The node has 0x605B and 0x605C.
    option_codes: bool,
}

impl Dictionary {
    /// The defaults of node `id`: the device type, heartbeats off, mode 0, option codes 0,
    /// the predefined connection set (PDOs valid as a drive ships them, mappings empty).
    pub(super) fn new(id: NodeId, option_codes: bool) -> Self {
        let node = u32::from(id.get());
        let mut values = [0; LEN];
        values[0] = DEVICE_TYPE;
        for k in 0..4 {
            let cob = 0x100 * k as u32;
            values[RPDO_COMM + 2 * k] = 0x200 + cob + node;
            values[RPDO_COMM + 2 * k + 1] = 0xFF;
            values[TPDO_COMM + 2 * k] = 0x180 + cob + node;
            values[TPDO_COMM + 2 * k + 1] = 0xFF;
        }
        Self {
            values,
            option_codes,
        }
    }

    /// Whether the node has 0x605B and 0x605C from now on.
    pub(super) fn set_option_codes(&mut self, present: bool) {
        self.option_codes = present;
    }

    /// The slot of `(index, sub)` if the node has that object.
    fn slot(&self, index: u16, sub: u8) -> Option<usize> {
        if !self.option_codes && matches!(index, 0x605B | 0x605C) {
            return None;
        }
        slot(index, sub)
    }

    /// The value of `(index, sub)`, if the node has it.
    pub(super) fn entry(&self, index: u16, sub: u8) -> Option<u32> {
        self.slot(index, sub).map(|s| self.values[s])
    }

    /// Whether the node has object `index` (any of its sub-indices).
    pub(super) fn has_index(&self, index: u16) -> bool {
        (0..=8).any(|sub| self.slot(index, sub).is_some())
    }

    /// The value of `(index, sub)`; 0 for an object the node does not have.
    pub(super) fn get(&self, index: u16, sub: u8) -> u32 {
        self.entry(index, sub).unwrap_or(0)
    }

    /// Sets `(index, sub)` (nothing for an object the node does not have).
    pub(super) fn set(&mut self, index: u16, sub: u8, value: u32) {
        if let Some(s) = self.slot(index, sub) {
            self.values[s] = value;
        }
    }

    /// Reset communication: the communication area at its defaults but the error register.
    pub(super) fn reset_communication(&mut self, id: NodeId) {
        let fresh = Self::new(id, self.option_codes);
        for (s, value) in self.values.iter_mut().enumerate() {
            let k = key(s);
            if COMMUNICATION_AREA.contains(&k.0) && k != ERROR_REGISTER {
                *value = fresh.values[s];
            }
        }
    }

    /// The heartbeat producer's period (0x1017), ns; `None` when off.
    pub(super) fn heartbeat_period_ns(&self) -> Option<u64> {
        let ms = self.get(0x1017, 0);
        (ms > 0).then(|| u64::from(ms) * 1_000_000)
    }

    /// The consumer entry (0x1016:01): the producer's node and the time, ms.
    pub(super) fn consumer(&self) -> Option<(u8, u16)> {
        let v = self.get(0x1016, 1);
        // Masked to 7 and 16 bits.
        #[allow(clippy::cast_possible_truncation)]
        let (node, ms) = (((v >> 16) & 0x7F) as u8, (v & 0xFFFF) as u16);
        (node != 0 && ms != 0).then_some((node, ms))
    }

    /// The error register (0x1001).
    pub(super) fn error_register(&self) -> u8 {
        // 0x1001 holds a byte.
        #[allow(clippy::cast_possible_truncation)]
        let register = self.get(ERROR_REGISTER.0, ERROR_REGISTER.1) as u8;
        register
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_slot_has_one_key_and_back() {
        for s in 0..LEN {
            let (index, sub) = key(s);
            assert_eq!(slot(index, sub), Some(s), "{index:04X}:{sub:02X}");
        }
        assert_eq!(slot(0x1016, 0), None);
        assert_eq!(slot(0x1400, 0), None);
        assert_eq!(slot(0x1600, 9), None);
        assert_eq!(slot(0x1404, 1), None);
    }
}
