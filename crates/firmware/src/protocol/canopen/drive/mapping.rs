//! The node's PDOs as the master mapped them (`0x1600..`/`0x1A00..`), not the codec's fixed
//! layout: which RPDO a COB-ID is, which TPDOs a SYNC sends, and their entries packed and
//! unpacked.

use embedded_can::StandardId;

use super::dictionary::Dictionary;
use crate::CanFrame;

/// A PDO mapping entry: object index, sub-index, length in bits.
pub(super) type Entry = (u16, u8, u8);

/// The entries of one PDO (at most 8).
pub(super) type Entries = heapless::Vec<Entry, 8>;

/// A mapping entry's value (`index << 16 | sub << 8 | bits`) split.
pub(super) const fn entry(value: u32) -> Entry {
    // The three fields of the 32-bit value.
    #[allow(clippy::cast_possible_truncation)]
    ((value >> 16) as u16, (value >> 8) as u8, value as u8)
}

/// Whether `(index, sub)` may be mapped into an RPDO (`rx`) or a TPDO: the controlword and the
/// targets in, the statusword and the actual velocities out; an axis at sub-index 0 on a
/// single-axis node, 1 and 2 on a `dual` one.
pub(super) fn mappable((index, sub, _): Entry, rx: bool, dual: bool) -> bool {
    let axis_sub = if dual {
        (1..=2).contains(&sub)
    } else {
        sub == 0
    };
    match index {
        0x6040 => rx && sub == 0,
        0x60FF => rx && axis_sub,
        0x6041 => !rx && sub == 0,
        0x606C => !rx && axis_sub,
        _ => false,
    }
}

/// The entries of mapping object `map`, if its PDO is valid.
pub(super) fn entries(od: &Dictionary, map: u16) -> Option<Entries> {
    let comm = map - 0x200;
    if od.get(comm, 1) & 0x8000_0000 != 0 {
        return None;
    }
    let count = od.get(map, 0).min(8);
    let mut out = Entries::new();
    // At most 8 sub-indices.
    #[allow(clippy::cast_possible_truncation)]
    for s in 1..=count as u8 {
        // At most 8 entries: always room.
        let _ = out.push(entry(od.get(map, s)));
    }
    Some(out)
}

/// The RPDO (0..=3) received on `cob`, if one is valid on it.
pub(super) fn rpdo_with(od: &Dictionary, cob: u16) -> Option<u16> {
    (0..4u16).find(|k| {
        let c = od.get(0x1400 + k, 1);
        c & 0x8000_0000 == 0 && c & 0x7FF == u32::from(cob)
    })
}

/// TPDO `k`'s COB-ID and entries, if it is valid and sent on SYNC (transmission type 1..240).
pub(super) fn tpdo(od: &Dictionary, k: u16) -> Option<(u16, Entries)> {
    let kind = od.get(0x1800 + k, 2);
    if kind == 0 || kind > 240 {
        return None;
    }
    let entries = entries(od, 0x1A00 + k)?;
    // 11 bits.
    #[allow(clippy::cast_possible_truncation)]
    let cob = (od.get(0x1800 + k, 1) & 0x7FF) as u16;
    Some((cob, entries))
}

/// A TPDO on `cob` with `entries`, each value given by `value(index, sub)`.
pub(super) fn pack(
    cob: u16,
    entries: &[Entry],
    mut value: impl FnMut(u16, u8) -> u32,
) -> Option<CanFrame> {
    let mut data = [0u8; 8];
    let mut at = 0usize;
    for &(index, sub, bits) in entries {
        let bytes = usize::from(bits / 8);
        let field = data.get_mut(at..at + bytes)?;
        field.copy_from_slice(value(index, sub).to_le_bytes().get(..bytes)?);
        at += bytes;
    }
    CanFrame::standard(StandardId::new(cob)?, data.get(..at)?)
}

/// Unpacks an RPDO's `data` by its `entries`, giving each `(index, sub, value)` in order to
/// `take`; `false` if the frame is shorter than its mapping (a drive ignores such a frame).
pub(super) fn unpack(entries: &[Entry], data: &[u8], mut take: impl FnMut(u16, u8, u32)) -> bool {
    let mut at = 0usize;
    for &(index, sub, bits) in entries {
        let bytes = usize::from(bits / 8);
        let mut word = [0u8; 4];
        let (Some(field), Some(low)) = (data.get(at..at + bytes), word.get_mut(..bytes)) else {
            return false;
        };
        low.copy_from_slice(field);
        take(index, sub, u32::from_le_bytes(word));
        at += bytes;
    }
    true
}
