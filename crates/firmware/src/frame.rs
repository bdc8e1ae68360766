//! A concrete, heap-free CAN 2.0 frame.
//!
//! The codecs are generic over [`embedded_can::Frame`], so they work with any driver's frame
//! type (`socketcan::CanFrame`, an MCU HAL's frame, ...). They still need one concrete type to
//! build frames in, and a control core needs one to store frames in fixed-size buffers:
//! [`CanFrame`] is that type. It is `Copy`, compares by value, and cannot hold an invalid id
//! (the id is an [`embedded_can::Id`]) or more than 8 data bytes.

use core::fmt;

use embedded_can::{Frame, Id, StandardId};

/// Maximum number of data bytes of a classic CAN frame.
pub const MAX_DLC: usize = 8;

/// A classic CAN 2.0 frame: an id, a remote flag, a data length code and up to 8 bytes.
///
/// Invariants (kept by every constructor): `dlc <= 8`; bytes past `dlc` are zero; a remote
/// frame has all-zero data. Two frames are equal when they would look the same on the bus.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct CanFrame {
    id: Id,
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
            id: Id::Standard(id),
            remote: false,
            dlc,
            data: (u64::from_le_bytes(buffer) & keep).to_le_bytes(),
        }
    }

    /// A remote (RTR) frame with a standard id; `dlc` is capped at 8.
    #[must_use]
    pub const fn remote(id: StandardId, dlc: u8) -> Self {
        let dlc = if dlc as usize > MAX_DLC {
            MAX_DLC as u8
        } else {
            dlc
        };
        Self {
            id: Id::Standard(id),
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
            id,
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
                id: frame.id(),
                remote: true,
                dlc,
                data: [0; MAX_DLC],
            })
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
            F::new_remote(self.id, usize::from(self.dlc))
        } else {
            F::new(self.id, self.data())
        }
    }

    /// The whole 8-byte buffer; bytes past [`Frame::dlc`] are zero.
    #[must_use]
    pub const fn buffer(&self) -> [u8; MAX_DLC] {
        self.data
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
            id: id.into(),
            remote: true,
            dlc,
            data: [0; MAX_DLC],
        })
    }

    #[inline]
    fn is_extended(&self) -> bool {
        matches!(self.id, Id::Extended(_))
    }

    #[inline]
    fn is_remote_frame(&self) -> bool {
        self.remote
    }

    #[inline]
    fn id(&self) -> Id {
        self.id
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
    fn extended_and_conversion_round_trip() {
        let id = ExtendedId::new(0x1234_5678).unwrap();
        let f = <CanFrame as Frame>::new(id, &[0xAA]).unwrap();
        assert!(f.is_extended());
        let g: CanFrame = f.convert().unwrap();
        assert_eq!(f, g);
        assert_eq!(CanFrame::from_frame(&g), Some(f));
    }
}
