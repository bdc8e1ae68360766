//! A concrete, heap-free CAN 2.0 frame.
//!
//! The codecs are generic over [`embedded_can::Frame`], so they work with any driver's frame
//! type (`socketcan::CanFrame`, an MCU HAL's frame, ...). They still need one concrete type to
//! build frames in, and a control core needs one to store frames in fixed-size buffers:
//! [`CanFrame`] is that type. It is `Copy`, compares by value, and cannot hold an invalid id
//! (every constructor takes an [`embedded_can::Id`] or a [`StandardId`]) or more than 8 data
//! bytes.

use core::fmt;
use core::hash::{Hash, Hasher};

use embedded_can::{ExtendedId, Frame, Id, StandardId};

/// Maximum number of data bytes of a classic CAN frame.
pub const MAX_DLC: usize = 8;

/// Bit of the packed id that marks an extended (29-bit) id; ids themselves use bits 0..=28.
const EXTENDED: u32 = 1 << 31;
/// The bits of a standard (11-bit) id.
const STANDARD_MASK: u32 = 0x7FF;
/// The bits of an extended (29-bit) id.
const EXTENDED_MASK: u32 = 0x1FFF_FFFF;

/// An [`Id`] as one `u32`: the raw id, with [`EXTENDED`] set for a 29-bit one.
#[inline]
fn pack(id: Id) -> u32 {
    match id {
        Id::Standard(id) => u32::from(id.as_raw()),
        Id::Extended(id) => id.as_raw() | EXTENDED,
    }
}

/// A classic CAN 2.0 frame: an id, a remote flag, a data length code and up to 8 bytes.
///
/// Invariants (kept by every constructor): `dlc <= 8`; bytes past `dlc` are zero; a remote
/// frame has all-zero data. Two frames are equal when they would look the same on the bus.
///
/// The id is kept packed in one `u32` (see [`Frame::id`] for the [`Id`]): a frame is 16 bytes,
/// and its id is written and read in one access.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct CanFrame {
    /// The packed id ([`pack`]): always a valid standard or extended id.
    id: u32,
    remote: bool,
    dlc: u8,
    data: [u8; MAX_DLC],
}

impl CanFrame {
    /// A data frame with a standard id and the given payload; `None` if `data` is longer than
    /// 8 bytes.
    #[must_use]
    pub fn standard(id: StandardId, data: &[u8]) -> Option<Self> {
        Self::data_frame(Id::Standard(id), data)
    }

    /// A data frame with a standard id from a payload buffer of which the first `dlc` bytes are
    /// sent; `dlc` is capped at 8 and the bytes past it are cleared. Infallible, for encoders.
    #[must_use]
    #[inline]
    pub fn from_buffer(id: StandardId, buffer: [u8; MAX_DLC], dlc: u8) -> Self {
        let dlc = dlc.min(MAX_DLC as u8);
        // Byte i of the little-endian word is bits 8i..8i+8: keep the low `dlc` bytes.
        let keep = match dlc {
            8 => u64::MAX,
            n => (1u64 << (8 * n)) - 1,
        };
        Self {
            id: pack(Id::Standard(id)),
            remote: false,
            dlc,
            data: (u64::from_le_bytes(buffer) & keep).to_le_bytes(),
        }
    }

    /// A remote (RTR) frame with a standard id; `dlc` is capped at 8.
    #[must_use]
    pub fn remote(id: StandardId, dlc: u8) -> Self {
        let dlc = if dlc as usize > MAX_DLC {
            MAX_DLC as u8
        } else {
            dlc
        };
        Self {
            id: pack(Id::Standard(id)),
            remote: true,
            dlc,
            data: [0; MAX_DLC],
        }
    }

    fn data_frame(id: Id, data: &[u8]) -> Option<Self> {
        if data.len() > MAX_DLC {
            return None;
        }
        let mut buffer = [0u8; MAX_DLC];
        for (dst, src) in buffer.iter_mut().zip(data) {
            *dst = *src;
        }
        Some(Self {
            id: pack(id),
            remote: false,
            // len <= 8 checked above, so this cast cannot truncate.
            dlc: data.len() as u8,
            data: buffer,
        })
    }

    /// Copies any [`Frame`] into a `CanFrame`; `None` if the other type reports more than 8
    /// data bytes or a DLC above 8 (CAN FD frames).
    #[must_use]
    pub fn from_frame<F: Frame>(frame: &F) -> Option<Self> {
        if frame.is_remote_frame() {
            let dlc = u8::try_from(frame.dlc())
                .ok()
                .filter(|d| usize::from(*d) <= MAX_DLC)?;
            Some(Self {
                id: pack(frame.id()),
                remote: true,
                dlc,
                data: [0; MAX_DLC],
            })
        } else if frame.dlc() > MAX_DLC {
            // Before `data()`, which a driver reporting a DLC of 9-15 may panic in.
            None
        } else {
            Self::data_frame(frame.id(), frame.data())
        }
    }

    /// Converts into another [`Frame`] type through its `new`/`new_remote` constructors.
    /// `None` only if that type rejects a valid classic frame (a correct implementation
    /// never does).
    #[must_use]
    pub fn convert<F: Frame>(&self) -> Option<F> {
        if self.remote {
            F::new_remote(self.id(), usize::from(self.dlc))
        } else {
            F::new(self.id(), self.data())
        }
    }

    /// The whole 8-byte buffer; bytes past [`Frame::dlc`] are zero.
    #[must_use]
    pub const fn buffer(&self) -> [u8; MAX_DLC] {
        self.data
    }

    /// The 11-bit id of a standard frame; `None` for an extended one.
    #[must_use]
    pub const fn standard_id(&self) -> Option<u16> {
        if self.id & EXTENDED == 0 {
            // A standard id is 11 bits: the cast cannot truncate.
            Some((self.id & STANDARD_MASK) as u16)
        } else {
            None
        }
    }
}

impl Frame for CanFrame {
    fn new(id: impl Into<Id>, data: &[u8]) -> Option<Self> {
        Self::data_frame(id.into(), data)
    }

    fn new_remote(id: impl Into<Id>, dlc: usize) -> Option<Self> {
        let dlc = u8::try_from(dlc)
            .ok()
            .filter(|d| usize::from(*d) <= MAX_DLC)?;
        Some(Self {
            id: pack(id.into()),
            remote: true,
            dlc,
            data: [0; MAX_DLC],
        })
    }

    #[inline]
    fn is_extended(&self) -> bool {
        self.id & EXTENDED != 0
    }

    #[inline]
    fn is_remote_frame(&self) -> bool {
        self.remote
    }

    #[inline]
    fn id(&self) -> Id {
        // Every constructor packs a valid id, so the masks change nothing; they let the
        // compiler see that `new` succeeds, and the fallbacks are never taken.
        if self.is_extended() {
            Id::Extended(ExtendedId::new(self.id & EXTENDED_MASK).unwrap_or(ExtendedId::ZERO))
        } else {
            // Masked to 11 bits, so the cast cannot truncate.
            Id::Standard(
                StandardId::new((self.id & STANDARD_MASK) as u16).unwrap_or(StandardId::ZERO),
            )
        }
    }

    #[inline]
    fn dlc(&self) -> usize {
        usize::from(self.dlc)
    }

    #[inline]
    fn data(&self) -> &[u8] {
        if self.remote {
            &[]
        } else {
            self.data.get(..usize::from(self.dlc)).unwrap_or(&[])
        }
    }
}

/// The same fields, in the same order, as a derived `Debug` on a frame holding an [`Id`].
impl fmt::Debug for CanFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CanFrame")
            .field("id", &self.id())
            .field("remote", &self.remote)
            .field("dlc", &self.dlc)
            .field("data", &self.data)
            .finish()
    }
}

/// Hashes what a derived `Hash` on a frame holding an [`Id`] would (equal frames hash alike).
impl Hash for CanFrame {
    fn hash<H: Hasher>(&self, state: &mut H) {
        self.id().hash(state);
        self.remote.hash(state);
        self.dlc.hash(state);
        self.data.hash(state);
    }
}

/// Candump notation (can-utils `candump -L`, `cansend`): `123#DEADBEEF`, `123#R` or `123#R4`
/// for a remote frame; 3 hex digits for a standard id, 8 for an extended one.
impl fmt::Display for CanFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.id() {
            Id::Standard(id) => write!(f, "{:03X}#", id.as_raw())?,
            Id::Extended(id) => write!(f, "{:08X}#", id.as_raw())?,
        }
        if self.is_remote_frame() {
            f.write_str("R")?;
            if self.dlc() > 0 {
                write!(f, "{}", self.dlc())?;
            }
            Ok(())
        } else {
            self.data().iter().try_for_each(|b| write!(f, "{b:02X}"))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::ExtendedId;

    fn sid(raw: u16) -> StandardId {
        StandardId::new(raw).unwrap()
    }

    #[test]
    fn data_returns_only_dlc_bytes() {
        let f = CanFrame::standard(sid(0x123), &[1, 2, 3]).unwrap();
        assert_eq!(f.data(), &[1, 2, 3]);
        assert_eq!(f.dlc(), 3);
        assert_eq!(f.buffer(), [1, 2, 3, 0, 0, 0, 0, 0]);
        assert!(!f.is_extended());
        assert!(!f.is_remote_frame());
        assert!(f.is_standard());
    }

    #[test]
    fn rejects_more_than_eight_bytes() {
        assert!(CanFrame::standard(sid(1), &[0; 9]).is_none());
        assert!(<CanFrame as Frame>::new_remote(sid(1), 9).is_none());
    }

    #[test]
    fn from_buffer_clears_bytes_past_dlc_and_caps_dlc() {
        let f = CanFrame::from_buffer(sid(7), [9; 8], 2);
        assert_eq!(f, CanFrame::standard(sid(7), &[9, 9]).unwrap());
        assert_eq!(CanFrame::from_buffer(sid(7), [9; 8], 200).dlc(), 8);
    }

    #[test]
    fn remote_frame_has_no_data() {
        let f = CanFrame::remote(sid(0x23), 8);
        assert!(f.is_remote_frame());
        assert_eq!(f.dlc(), 8);
        assert!(f.data().is_empty());
    }

    #[test]
    fn packed_id_keeps_standard_and_extended_apart() {
        let std = CanFrame::standard(sid(0x123), &[1]).unwrap();
        let ext = <CanFrame as Frame>::new(ExtendedId::new(0x123).unwrap(), &[1]).unwrap();
        assert_ne!(std, ext);
        assert_eq!(std.id(), Id::Standard(sid(0x123)));
        assert_eq!(ext.id(), Id::Extended(ExtendedId::new(0x123).unwrap()));
        let max = <CanFrame as Frame>::new(ExtendedId::MAX, &[]).unwrap();
        assert_eq!(max.id(), Id::Extended(ExtendedId::MAX));
        assert_eq!(core::mem::size_of::<CanFrame>(), 16);
    }

    #[test]
    fn debug_shows_the_id() {
        extern crate std;
        let f = CanFrame::standard(sid(0x201), &[1, 2]).unwrap();
        assert_eq!(
            std::format!("{f:?}"),
            "CanFrame { id: Standard(StandardId(513)), remote: false, dlc: 2, \
             data: [1, 2, 0, 0, 0, 0, 0, 0] }"
        );
    }

    #[test]
    fn extended_and_conversion_round_trip() {
        let id = ExtendedId::new(0x1234_5678).unwrap();
        let f = <CanFrame as Frame>::new(id, &[0xAA]).unwrap();
        assert!(f.is_extended());
        let g: CanFrame = f.convert().unwrap();
        assert_eq!(f, g);
        assert_eq!(CanFrame::from_frame(&g), Some(f));
    }
}
