//! The one error type of every decoder, and counters for a control core.
//!
//! A decoder looks at a frame in a fixed order and reports the first problem it finds:
//!
//! 1. [`DecodeError::ExtendedId`]: all three protocols use 11-bit standard ids only.
//! 2. [`DecodeError::UnknownId`]: the id is not a message of this protocol (in the direction
//!    being decoded).
//! 3. [`DecodeError::Remote`]: a remote (RTR) frame where the message carries data.
//! 4. [`DecodeError::WrongDlc`]: the data length differs from the message's DLC in the DBC.
//! 5. [`DecodeError::NonFinite`] / [`DecodeError::OutOfRange`]: a field holds NaN or
//!    infinity, or a value outside its documented range (an unknown enum value, a reserved
//!    raw value, a rotor angle above 8191, ...).
//!
//! Every variant carries the rejected value so a log line can say what arrived. The field
//! names are the signal names of the DBC files in `dbc/`.

use core::fmt;

use embedded_can::Id;

/// Why a frame was rejected. Small and `Copy`: a no_std core can store and count it.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[non_exhaustive]
pub enum DecodeError {
    /// The id is not one this protocol (in this direction) carries.
    UnknownId {
        /// The id received.
        id: Id,
    },
    /// An extended (29-bit) id; the protocols here use standard ids only.
    ExtendedId {
        /// The raw 29-bit id received.
        id: u32,
    },
    /// A remote (RTR) frame where a data frame was expected.
    Remote {
        /// The raw 11-bit id received.
        id: u16,
    },
    /// The data length code differs from the message's.
    WrongDlc {
        /// The raw 11-bit id received.
        id: u16,
        /// The DLC of the message in its DBC.
        expected: u8,
        /// The DLC received.
        got: u8,
    },
    /// A floating-point field is NaN or infinite.
    NonFinite {
        /// The DBC signal name of the field.
        field: &'static str,
        /// The field's bits as received (IEEE 754 single precision), which tell a NaN's
        /// payload and an infinity's sign.
        bits: u32,
    },
    /// A field holds a value outside its range (or an unknown enum value).
    OutOfRange {
        /// The DBC signal name of the field.
        field: &'static str,
        /// The raw (unscaled) value received.
        value: i64,
    },
}

/// The kind of a [`DecodeError`], without its payload: what a core counts.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[non_exhaustive]
pub enum ErrorKind {
    /// [`DecodeError::UnknownId`].
    UnknownId,
    /// [`DecodeError::ExtendedId`].
    ExtendedId,
    /// [`DecodeError::Remote`].
    Remote,
    /// [`DecodeError::WrongDlc`].
    WrongDlc,
    /// [`DecodeError::NonFinite`].
    NonFinite,
    /// [`DecodeError::OutOfRange`].
    OutOfRange,
}

impl ErrorKind {
    /// A stable snake_case name (`"wrong_dlc"`, ...), used in logs and in the JSON of the
    /// `mecanum-codec` tool.
    #[must_use]
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::UnknownId => "unknown_id",
            Self::ExtendedId => "extended_id",
            Self::Remote => "remote",
            Self::WrongDlc => "wrong_dlc",
            Self::NonFinite => "non_finite",
            Self::OutOfRange => "out_of_range",
        }
    }
}

impl fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl DecodeError {
    /// The kind of this error.
    #[must_use]
    pub const fn kind(&self) -> ErrorKind {
        match self {
            Self::UnknownId { .. } => ErrorKind::UnknownId,
            Self::ExtendedId { .. } => ErrorKind::ExtendedId,
            Self::Remote { .. } => ErrorKind::Remote,
            Self::WrongDlc { .. } => ErrorKind::WrongDlc,
            Self::NonFinite { .. } => ErrorKind::NonFinite,
            Self::OutOfRange { .. } => ErrorKind::OutOfRange,
        }
    }
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::UnknownId {
                id: Id::Standard(id),
            } => {
                write!(f, "unknown CAN id {:#05x}", id.as_raw())
            }
            Self::UnknownId {
                id: Id::Extended(id),
            } => {
                write!(f, "unknown extended CAN id {:#010x}", id.as_raw())
            }
            Self::ExtendedId { id } => {
                write!(
                    f,
                    "extended CAN id {id:#010x} where a standard id was expected"
                )
            }
            Self::Remote { id } => write!(f, "remote frame on id {id:#05x}, which carries data"),
            Self::WrongDlc { id, expected, got } => {
                write!(f, "id {id:#05x}: DLC {got}, expected {expected}")
            }
            Self::NonFinite { field, bits } => {
                write!(
                    f,
                    "field {field} is {} (bits {bits:#010x})",
                    non_finite_name(bits)
                )
            }
            Self::OutOfRange { field, value } => {
                write!(f, "field {field} out of range: raw value {value}")
            }
        }
    }
}

impl core::error::Error for DecodeError {}

/// `"NaN"`, `"inf"` or `"-inf"` for the bits of a non-finite `f32` (without formatting a
/// float, which would pull float printing into an MCU build).
#[must_use]
pub const fn non_finite_name(bits: u32) -> &'static str {
    if bits & 0x007F_FFFF != 0 {
        "NaN"
    } else if bits >> 31 == 1 {
        "-inf"
    } else {
        "inf"
    }
}

/// Per-kind counts of rejected frames, saturating at `u32::MAX`.
///
/// A core calls [`RxErrorCounters::record`] for every error a decoder returns and reports
/// the totals (the robot protocol's `STATUS` frame carries `rx_errors` and `unknown_ids`).
/// With the `serde` feature it serializes as an object of the six counts (the runner's
/// `--stats-json` report).
#[derive(Clone, Copy, PartialEq, Eq, Default, Debug)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct RxErrorCounters {
    /// Frames with an id no protocol carries.
    pub unknown_id: u32,
    /// Frames with an extended id.
    pub extended_id: u32,
    /// Remote frames where data was expected.
    pub remote: u32,
    /// Frames with a wrong DLC.
    pub wrong_dlc: u32,
    /// Frames with a NaN or infinite float.
    pub non_finite: u32,
    /// Frames with an out-of-range field.
    pub out_of_range: u32,
}

impl RxErrorCounters {
    /// All counters at zero.
    #[must_use]
    pub const fn new() -> Self {
        Self {
            unknown_id: 0,
            extended_id: 0,
            remote: 0,
            wrong_dlc: 0,
            non_finite: 0,
            out_of_range: 0,
        }
    }

    /// Counts one error under its kind (saturating).
    pub fn record(&mut self, error: &DecodeError) {
        let counter = match error.kind() {
            ErrorKind::UnknownId => &mut self.unknown_id,
            ErrorKind::ExtendedId => &mut self.extended_id,
            ErrorKind::Remote => &mut self.remote,
            ErrorKind::WrongDlc => &mut self.wrong_dlc,
            ErrorKind::NonFinite => &mut self.non_finite,
            ErrorKind::OutOfRange => &mut self.out_of_range,
        };
        *counter = counter.saturating_add(1);
    }

    /// The count for one kind.
    #[must_use]
    pub const fn get(&self, kind: ErrorKind) -> u32 {
        match kind {
            ErrorKind::UnknownId => self.unknown_id,
            ErrorKind::ExtendedId => self.extended_id,
            ErrorKind::Remote => self.remote,
            ErrorKind::WrongDlc => self.wrong_dlc,
            ErrorKind::NonFinite => self.non_finite,
            ErrorKind::OutOfRange => self.out_of_range,
        }
    }

    /// All rejected frames, saturating.
    #[must_use]
    pub const fn total(&self) -> u32 {
        self.unknown_id
            .saturating_add(self.extended_id)
            .saturating_add(self.remote)
            .saturating_add(self.wrong_dlc)
            .saturating_add(self.non_finite)
            .saturating_add(self.out_of_range)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::StandardId;

    #[test]
    fn counters_count_per_kind_and_saturate() {
        let mut c = RxErrorCounters::new();
        c.record(&DecodeError::WrongDlc {
            id: 0x301,
            expected: 8,
            got: 7,
        });
        c.record(&DecodeError::UnknownId {
            id: Id::Standard(StandardId::new(0x123).unwrap()),
        });
        c.record(&DecodeError::OutOfRange {
            field: "vx",
            value: -32768,
        });
        assert_eq!(c.wrong_dlc, 1);
        assert_eq!(c.get(ErrorKind::UnknownId), 1);
        assert_eq!(c.out_of_range, 1);
        assert_eq!(c.total(), 3);
        c.non_finite = u32::MAX;
        c.record(&DecodeError::NonFinite {
            field: "Input_Vel",
            bits: 0x7FC0_0000,
        });
        assert_eq!(c.non_finite, u32::MAX);
        assert_eq!(c.total(), u32::MAX);
    }

    #[test]
    fn display_names_the_values() {
        extern crate std;
        use std::string::ToString;
        let e = DecodeError::WrongDlc {
            id: 0x301,
            expected: 8,
            got: 7,
        };
        assert_eq!(e.to_string(), "id 0x301: DLC 7, expected 8");
        assert_eq!(e.kind().as_str(), "wrong_dlc");
        let e = DecodeError::OutOfRange {
            field: "rotor_angle",
            value: 8192,
        };
        assert_eq!(
            e.to_string(),
            "field rotor_angle out of range: raw value 8192"
        );
    }
}
