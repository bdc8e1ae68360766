//! The building blocks of the layout tables: a message ([`MessageDef`]) and a field
//! ([`Field`]: offset, type, byte order, scale, raw range), with the only code in the crate
//! that touches payload bytes. Every read and write goes through `get`/`get_mut` on a fixed
//! 8-byte buffer, so no input can make it panic.

use embedded_can::{Frame, Id};

use super::error::DecodeError;
use crate::frame::MAX_DLC;

/// A message of a protocol: its DBC name, base id and data length.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct MessageDef {
    /// Message name, as in the DBC file (without a per-node prefix).
    pub name: &'static str,
    /// The 11-bit id, or for per-device messages the command/offset part of it.
    pub id: u16,
    /// Data length code the message is sent with (as in the DBC file).
    pub dlc: u8,
}

impl MessageDef {
    /// The message `name` with base id `id`, sent with `dlc` bytes.
    #[must_use]
    pub const fn new(name: &'static str, id: u16, dlc: u8) -> Self {
        Self { name, id, dlc }
    }
}

/// Byte order of a multi-byte field.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum ByteOrder {
    /// Little-endian (DBC `@1`, "Intel").
    Little,
    /// Big-endian (DBC `@0`, "Motorola").
    Big,
}

/// Wire type of a field.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum WireType {
    /// Bit 0 of one byte (a flag).
    Bit0,
    /// `width` bits of one byte from bit `shift` (0 = least significant), unsigned: fields
    /// that share a byte (DBC signals such as `48|4@1+` and `52|4@1+`). `shift + width <= 8`.
    Bits {
        /// Lowest bit of the field in its byte, 0..=7.
        shift: u8,
        /// Number of bits, 1..=8.
        width: u8,
    },
    /// Unsigned 8 bits.
    U8,
    /// Unsigned 16 bits.
    U16,
    /// Signed 16 bits, two's complement.
    I16,
    /// Unsigned 32 bits.
    U32,
    /// Signed 32 bits, two's complement.
    I32,
    /// IEEE 754 single precision.
    F32,
}

impl WireType {
    /// Size in bytes.
    #[must_use]
    pub const fn size(self) -> usize {
        match self {
            Self::Bit0 | Self::Bits { .. } | Self::U8 => 1,
            Self::U16 | Self::I16 => 2,
            Self::U32 | Self::I32 | Self::F32 => 4,
        }
    }
}

/// One field of a message: one row of a layout table, mirroring one DBC signal.
///
/// For integer fields the physical value is `raw * scale`, and a decoder accepts raw values
/// in `min..=max` only. Floats (`F32`) are sent as they are; decoders reject NaN and infinity.
#[derive(Clone, Copy, PartialEq, Debug)]
pub struct Field {
    /// Signal name, as in the DBC file.
    pub name: &'static str,
    /// Offset of the first byte in the payload.
    pub offset: usize,
    /// Wire type.
    pub ty: WireType,
    /// Byte order.
    pub order: ByteOrder,
    /// Physical units per raw unit (DBC factor). 1 for plain integers. `f64` so that decimal
    /// factors such as 0.0001 scale 32-bit raw values as exactly as the DBC tools do.
    pub scale: f64,
    /// Smallest raw value a decoder accepts and an encoder emits.
    pub min: i64,
    /// Largest raw value a decoder accepts and an encoder emits.
    pub max: i64,
}

impl Field {
    /// An integer field accepting every value of its type, scale 1.
    #[must_use]
    pub const fn int(name: &'static str, offset: usize, ty: WireType, order: ByteOrder) -> Self {
        let (min, max) = match ty {
            WireType::Bit0 => (0, 1),
            WireType::Bits { width, .. } => (0, bits_mask(width) as i64),
            WireType::U8 => (0, u8::MAX as i64),
            WireType::U16 => (0, u16::MAX as i64),
            WireType::I16 => (i16::MIN as i64, i16::MAX as i64),
            WireType::U32 | WireType::F32 => (0, u32::MAX as i64),
            WireType::I32 => (i32::MIN as i64, i32::MAX as i64),
        };
        Self {
            name,
            offset,
            ty,
            order,
            scale: 1.0,
            min,
            max,
        }
    }

    /// The same field with a raw range.
    #[must_use]
    pub const fn range(self, min: i64, max: i64) -> Self {
        Self { min, max, ..self }
    }

    /// The same field with a scale.
    #[must_use]
    pub const fn scaled(self, scale: f64) -> Self {
        Self { scale, ..self }
    }

    /// Where the field sits in the payload read as one little-endian `u64` (byte `i` is bits
    /// `8i..8i+8`): the shift of its lowest bit and the mask of its bits, or `None` if it does
    /// not fit the 8 bytes (no layout row does; such a field reads as 0 and writes nothing).
    ///
    /// A big-endian field is found in the payload read as a big-endian `u64` instead, where
    /// its bytes are in the order the field wants; `shift` is then counted from that end.
    #[inline]
    const fn placement(&self) -> Option<(u32, u64)> {
        let size = self.ty.size();
        if self.offset > MAX_DLC || size > MAX_DLC - self.offset {
            return None;
        }
        let low_byte = match self.order {
            ByteOrder::Little => self.offset,
            ByteOrder::Big => MAX_DLC - self.offset - size,
        };
        let (bit, mask) = match self.ty {
            WireType::Bit0 => (0, 1),
            WireType::Bits { shift, width } => {
                if shift as usize + width as usize > 8 {
                    return None;
                }
                (shift as u32, bits_mask(width))
            }
            // size <= 4, so the shift stays below 64.
            _ => (0, (1u64 << (8 * size)) - 1),
        };
        // low_byte <= 7, so the cast cannot truncate.
        Some((8 * low_byte as u32 + bit, mask))
    }

    /// The payload as one `u64` in this field's byte order.
    #[inline]
    const fn word(&self, payload: &Payload) -> u64 {
        match self.order {
            ByteOrder::Little => u64::from_le_bytes(payload.0),
            ByteOrder::Big => u64::from_be_bytes(payload.0),
        }
    }

    /// The field's bits as an unsigned number (zero-extended).
    #[inline]
    const fn bits(&self, payload: &Payload) -> u32 {
        match self.placement() {
            // The mask keeps at most 32 bits.
            Some((shift, mask)) => ((self.word(payload) >> shift) & mask) as u32,
            None => 0,
        }
    }

    /// The raw integer value (sign-extended for signed types). For `F32` fields: the bits.
    #[must_use]
    #[inline]
    pub fn raw(&self, payload: &Payload) -> i64 {
        let bits = self.bits(payload);
        match self.ty {
            // Reinterpreting the bits as two's complement is the point of these casts.
            WireType::I16 => i64::from(bits as u16 as i16),
            WireType::I32 => i64::from(bits as i32),
            _ => i64::from(bits),
        }
    }

    /// The raw value, checked against `min..=max`.
    ///
    /// # Errors
    /// [`DecodeError::OutOfRange`] with the raw value.
    #[inline]
    pub fn checked(&self, payload: &Payload) -> Result<i64, DecodeError> {
        let value = self.raw(payload);
        if (self.min..=self.max).contains(&value) {
            Ok(value)
        } else {
            Err(DecodeError::OutOfRange {
                field: self.name,
                value,
            })
        }
    }

    /// The physical value `raw * scale`, range-checked.
    ///
    /// # Errors
    /// [`DecodeError::OutOfRange`] with the raw value.
    #[inline]
    pub fn physical(&self, payload: &Payload) -> Result<f32, DecodeError> {
        // Raw values fit 32 bits, exact in f64; one rounding to f32 at the end.
        self.checked(payload)
            .map(|raw| (raw as f64 * self.scale) as f32)
    }

    /// A finite `F32` field.
    ///
    /// # Errors
    /// [`DecodeError::NonFinite`] for NaN and infinities.
    #[inline]
    pub fn finite(&self, payload: &Payload) -> Result<f32, DecodeError> {
        let bits = self.bits(payload);
        let value = f32::from_bits(bits);
        if value.is_finite() {
            Ok(value)
        } else {
            Err(DecodeError::NonFinite {
                field: self.name,
                bits,
            })
        }
    }

    /// Writes a raw value, clamped to `min..=max`. For `F32` fields this writes the bits.
    #[inline]
    pub fn put_raw(&self, payload: &mut Payload, raw: i64) {
        // `clamp` without its panic on `min > max` (no layout row has that).
        let clamped = raw.max(self.min).min(self.max);
        let Some((shift, mask)) = self.placement() else {
            return;
        };
        // Truncation to the field's width is intended; the range clamp above keeps it exact.
        let bits = u64::from(clamped as u32) & mask;
        let word = (self.word(payload) & !(mask << shift)) | (bits << shift);
        payload.0 = match self.order {
            ByteOrder::Little => word.to_le_bytes(),
            ByteOrder::Big => word.to_be_bytes(),
        };
    }

    /// Writes a physical value: rounded to the nearest raw value (ties to even),
    /// saturated to `min..=max`; NaN is written as the raw value nearest to 0.
    #[inline]
    pub fn put_physical(&self, payload: &mut Payload, value: f32) {
        self.put_raw(payload, to_raw(value, self.scale, self.min, self.max));
    }

    /// Writes an `F32` field as is (callers sanitise non-finite values first).
    #[inline]
    pub fn put_f32(&self, payload: &mut Payload, value: f32) {
        self.put_raw(payload, i64::from(value.to_bits()));
    }
}

/// The mask of `width` low bits (at most 8: a [`WireType::Bits`] field lies in one byte).
const fn bits_mask(width: u8) -> u64 {
    let width = if width > 8 { 8 } else { width };
    (1u64 << width) - 1
}

/// `value / scale` rounded to the nearest integer, ties to even (as cantools encodes: Python's
/// `round`), and saturated to `min..=max`; NaN maps to the
/// raw value nearest 0. Computed in f64 (exact for 32-bit raw values). Exposed for encoders
/// that need the raw number itself.
#[must_use]
#[inline]
pub fn to_raw(value: f32, scale: f64, min: i64, max: i64) -> i64 {
    let r = f64::from(value) / scale;
    if r.is_nan() {
        return 0i64.clamp(min, max);
    }
    // The bounds used here are 32-bit values, exact in f64.
    if r <= min as f64 {
        return min;
    }
    if r >= max as f64 {
        return max;
    }
    // min < r < max, so the truncating cast is exact, and so is `t as f64` (|t| < 2^32).
    let t = r as i64;
    let frac = r - t as f64;
    // The nearest raw value, ties to even as cantools rounds (Python's `round`): one step up
    // or down, which cannot overflow.
    let odd = t & 1 != 0;
    let up = (frac > 0.5) | ((frac == 0.5) & odd);
    let down = (frac < -0.5) | ((frac == -0.5) & odd);
    let n = t + i64::from(up) - i64::from(down);
    n.clamp(min, max)
}

/// Replaces non-finite floats for the wire: NaN becomes 0, infinities the largest finite
/// value of the same sign. Encoders never emit NaN or infinity.
#[must_use]
pub const fn saturate_f32(value: f32) -> f32 {
    if value.is_nan() {
        0.0
    } else if value == f32::INFINITY {
        f32::MAX
    } else if value == f32::NEG_INFINITY {
        f32::MIN
    } else {
        value
    }
}

/// A frame's 8-byte payload buffer (bytes past the DLC are zero).
#[derive(Clone, Copy, PartialEq, Eq, Default, Debug)]
pub struct Payload(pub [u8; MAX_DLC]);

impl Payload {
    /// An all-zero payload.
    #[must_use]
    pub const fn new() -> Self {
        Self([0; MAX_DLC])
    }

    /// Copies up to 8 bytes of `data`.
    #[must_use]
    #[inline]
    pub fn from_slice(data: &[u8]) -> Self {
        if let Ok(full) = <[u8; MAX_DLC]>::try_from(data) {
            return Self(full);
        }
        let mut p = Self::new();
        for (dst, src) in p.0.iter_mut().zip(data) {
            *dst = *src;
        }
        p
    }
}

/// The raw 11-bit id of a frame.
///
/// # Errors
/// [`DecodeError::ExtendedId`] for a 29-bit id.
#[inline]
pub fn standard_id<F: Frame>(frame: &F) -> Result<u16, DecodeError> {
    match frame.id() {
        Id::Standard(id) => Ok(id.as_raw()),
        Id::Extended(id) => Err(DecodeError::ExtendedId { id: id.as_raw() }),
    }
}

/// The `UnknownId` error for a frame.
#[inline]
pub(crate) fn unknown<F: Frame>(frame: &F) -> DecodeError {
    DecodeError::UnknownId { id: frame.id() }
}

/// Checks that `frame` is a data frame whose DLC is one of `accepted`, and returns its
/// payload. `accepted[0]` is the DLC reported as expected.
///
/// The DLC is checked before the data is touched: a classic frame may carry a DLC of 9-15
/// (8 data bytes), and a driver that reports it unchanged can panic in `data()` (embassy-stm32
/// 0.6 slices its 8-byte buffer by the DLC).
///
/// # Errors
/// [`DecodeError::Remote`] or [`DecodeError::WrongDlc`].
#[inline]
pub fn data_payload<F: Frame>(frame: &F, id: u16, accepted: &[u8]) -> Result<Payload, DecodeError> {
    if frame.is_remote_frame() {
        return Err(DecodeError::Remote { id });
    }
    if frame.dlc() > MAX_DLC {
        return Err(DecodeError::WrongDlc {
            id,
            expected: accepted.first().copied().unwrap_or(0),
            got: u8::try_from(frame.dlc()).unwrap_or(u8::MAX),
        });
    }
    let data = frame.data();
    let got = u8::try_from(data.len()).unwrap_or(u8::MAX);
    if accepted.contains(&got) {
        Ok(Payload::from_slice(data))
    } else {
        Err(DecodeError::WrongDlc {
            id,
            expected: accepted.first().copied().unwrap_or(0),
            got,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn to_raw_rounds_ties_to_even_and_saturates() {
        // Exact ties (binary fractions): to the even neighbour, as Python's round.
        for (value, raw) in [
            (0.5, 0),
            (1.5, 2),
            (2.5, 2),
            (3.5, 4),
            (-0.5, 0),
            (-1.5, -2),
            (-2.5, -2),
            (-3.5, -4),
        ] {
            assert_eq!(to_raw(value, 1.0, -10, 10), raw, "{value}");
        }
        // A robot-protocol speed (scale 0.001) whose quotient is a tie in f64.
        assert_eq!(to_raw(-32.5625, 0.001, -32768, 32767), -32562);
        assert_eq!(to_raw(2.5000002, 1.0, -10, 10), 3);
        assert_eq!(to_raw(0.0015, 0.001, -10, 10), 2);
        assert_eq!(to_raw(-0.0015, 0.001, -10, 10), -2);
        assert_eq!(to_raw(0.0014, 0.001, -10, 10), 1);
        assert_eq!(to_raw(0.49999997, 1.0, -10, 10), 0);
        assert_eq!(to_raw(1e9, 0.001, -32767, 32767), 32767);
        assert_eq!(to_raw(f32::NEG_INFINITY, 0.001, -32767, 32767), -32767);
        assert_eq!(to_raw(f32::NAN, 0.001, -32767, 32767), 0);
        assert_eq!(to_raw(f32::NAN, 1.0, 5, 9), 5);
    }

    #[test]
    fn big_and_little_endian_fields() {
        let le = Field::int("a", 1, WireType::I16, ByteOrder::Little);
        let be = Field::int("b", 4, WireType::I16, ByteOrder::Big);
        let mut p = Payload::new();
        le.put_raw(&mut p, -2);
        be.put_raw(&mut p, 0x1234);
        assert_eq!(p.0, [0, 0xFE, 0xFF, 0, 0x12, 0x34, 0, 0]);
        assert_eq!(le.raw(&p), -2);
        assert_eq!(be.raw(&p), 0x1234);
    }

    #[test]
    fn fields_sharing_a_byte_keep_each_others_bits() {
        let low = Field::int(
            "low",
            6,
            WireType::Bits { shift: 0, width: 4 },
            ByteOrder::Little,
        );
        let high = Field::int(
            "high",
            6,
            WireType::Bits { shift: 4, width: 4 },
            ByteOrder::Little,
        );
        assert_eq!((low.min, low.max, high.max), (0, 15, 15));
        let mut p = Payload([0xFF, 0, 0, 0, 0, 0, 0, 0xFF]);
        low.put_raw(&mut p, 0b1011);
        high.put_raw(&mut p, 2);
        assert_eq!(p.0, [0xFF, 0, 0, 0, 0, 0, 0x2B, 0xFF]);
        assert_eq!((low.raw(&p), high.raw(&p)), (0b1011, 2));
        // Clamped to the field's range: the neighbour is untouched.
        high.put_raw(&mut p, 99);
        assert_eq!(p.0[6], 0xFB);
        // A field that does not fit its byte reads as 0 and writes nothing.
        let bad = Field::int(
            "bad",
            0,
            WireType::Bits { shift: 6, width: 4 },
            ByteOrder::Little,
        );
        bad.put_raw(&mut p, 3);
        assert_eq!((bad.raw(&p), p.0[0]), (0, 0xFF));
    }

    #[test]
    fn bit_field_keeps_other_bits() {
        let f = Field::int("flag", 6, WireType::Bit0, ByteOrder::Little);
        let mut p = Payload([0, 0, 0, 0, 0, 0, 0xF0, 0]);
        f.put_raw(&mut p, 1);
        assert_eq!(p.0[6], 0xF1);
        assert_eq!(f.raw(&p), 1);
    }
}
