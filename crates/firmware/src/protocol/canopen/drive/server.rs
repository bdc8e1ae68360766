//! The node's SDO server: uploads and downloads of its dictionary, with the abort code a drive
//! gives for what it refuses (CiA 301's PDO rules: a mapping changes only while its PDO is
//! off, its entries only while its count is 0, a valid PDO's COB-ID only through invalid).

use super::dictionary::Dictionary;
use super::mapping;
use crate::protocol::canopen::{SdoRequest, SdoResponse};

/// SDO abort codes the nodes give (CiA 301 table 22): the codec's.
pub use crate::protocol::canopen::abort_code as abort;

/// Answers one SDO request: an upload reads the dictionary (4 bytes), a download writes it
/// if [`check_write`] allows, unless `refused` names the object (then its abort code). A
/// write of the mode (0x6060) takes effect at once: its display (0x6061) shows it.
pub(super) fn answer(
    od: &mut Dictionary,
    request: SdoRequest,
    refused: Option<((u16, u8), u32)>,
    dual: bool,
) -> SdoResponse {
    let (index, sub) = request.object();
    let refuse = |code| SdoResponse::Abort { index, sub, code };
    match request {
        SdoRequest::Abort { .. } => refuse(abort::INCOMPATIBLE),
        SdoRequest::Upload { .. } => match od.entry(index, sub) {
            Some(value) => SdoResponse::Uploaded {
                index,
                sub,
                value,
                size: 4,
            },
            None => refuse(missing(od, index)),
        },
        SdoRequest::Download { value, .. } => {
            if let Some((object, code)) = refused
                && object == (index, sub)
            {
                return refuse(code);
            }
            match check_write(od, index, sub, value, dual) {
                Ok(()) => {
                    od.set(index, sub, value);
                    if (index, sub) == (0x6060, 0) {
                        od.set(0x6061, 0, value);
                    }
                    SdoResponse::Downloaded { index, sub }
                }
                Err(code) => refuse(code),
            }
        }
    }
}

/// The abort code for an object the node does not have: its index exists or not.
fn missing(od: &Dictionary, index: u16) -> u32 {
    if od.has_index(index) {
        abort::NO_SUBINDEX
    } else {
        abort::NO_OBJECT
    }
}

/// Whether writing `value` to `(index, sub)` is allowed now; else the abort code.
pub(super) fn check_write(
    od: &Dictionary,
    index: u16,
    sub: u8,
    value: u32,
    dual: bool,
) -> Result<(), u32> {
    if od.entry(index, sub).is_none() {
        return Err(missing(od, index));
    }
    match index {
        0x1000 | 0x1001 | 0x6061 => Err(abort::READ_ONLY),
        0x6060 if value != 3 => Err(abort::INVALID_VALUE),
        0x605B | 0x605C if value > 1 => Err(abort::INVALID_VALUE),
        // Mapping: only while the PDO is off; entries only while the count is 0.
        0x1600..=0x1603 | 0x1A00..=0x1A03 => {
            let comm = index - 0x200;
            if od.get(comm, 1) & 0x8000_0000 == 0 {
                return Err(abort::DEVICE_STATE);
            }
            let rx = index < 0x1A00;
            if sub == 0 {
                check_count(od, index, value, rx, dual)
            } else if od.get(index, 0) != 0 {
                Err(abort::DEVICE_STATE)
            } else if mapping::mappable(mapping::entry(value), rx, dual)
                && matches!(value & 0xFF, 16 | 32)
            {
                Ok(())
            } else {
                Err(abort::CANNOT_MAP)
            }
        }
        // A valid PDO's COB-ID changes only through invalid.
        0x1400..=0x1403 | 0x1800..=0x1803 if sub == 1 => {
            let now = od.get(index, 1);
            let both_valid = now & 0x8000_0000 == 0 && value & 0x8000_0000 == 0;
            if both_valid && now & 0x7FF != value & 0x7FF {
                Err(abort::INVALID_VALUE)
            } else {
                Ok(())
            }
        }
        _ => Ok(()),
    }
}

/// A mapping count `count` for mapping object `map`: at most 8 entries, at most 64 bits, each
/// of its entries mappable.
fn check_count(od: &Dictionary, map: u16, count: u32, rx: bool, dual: bool) -> Result<(), u32> {
    let mut bits = 0;
    let mut ok = count <= 8;
    // At most 8 sub-indices.
    #[allow(clippy::cast_possible_truncation)]
    for s in 1..=count.min(8) as u8 {
        let e = od.get(map, s);
        bits += e & 0xFF;
        ok &= mapping::mappable(mapping::entry(e), rx, dual);
    }
    if ok && bits <= 64 {
        Ok(())
    } else {
        Err(abort::CANNOT_MAP)
    }
}
