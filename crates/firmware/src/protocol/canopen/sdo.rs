//! SDO (`0x600 + node` requests, `0x580 + node` responses): expedited reads and writes of a
//! node's object dictionary, and aborts.
//!
//! Only expedited transfers (1-4 data bytes) are implemented: the initiation of a segmented
//! or block transfer decodes as [`DecodeError::OutOfRange`] on the command byte.

use super::layout;
use crate::protocol::error::DecodeError;
use crate::protocol::wire::Payload;

/// An SDO request, client (master) → server (drive).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SdoRequest {
    /// Read an object.
    Upload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Write an object of `size` bytes (1..=4), expedited.
    Download {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value, little-endian in the `size` low bytes.
        value: u32,
        /// Data bytes, 1..=4.
        size: u8,
    },
    /// Abort a transfer.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code (CiA 301 table 22).
        code: u32,
    },
}

/// An SDO response, server (drive) → client (master).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum SdoResponse {
    /// The value of an object read (expedited).
    Uploaded {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The value (bytes beyond `size` zero).
        value: u32,
        /// Data bytes, 1..=4.
        size: u8,
    },
    /// A write was done.
    Downloaded {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// The transfer was refused.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code (CiA 301 table 22).
        code: u32,
    },
}

impl SdoRequest {
    /// The object the request is about.
    #[must_use]
    pub const fn object(&self) -> (u16, u8) {
        match *self {
            Self::Upload { index, sub }
            | Self::Download { index, sub, .. }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }
}

impl SdoResponse {
    /// The object the response is about.
    #[must_use]
    pub const fn object(&self) -> (u16, u8) {
        match *self {
            Self::Uploaded { index, sub, .. }
            | Self::Downloaded { index, sub }
            | Self::Abort { index, sub, .. } => (index, sub),
        }
    }

    /// Whether this is the answer to `request`: the same index and sub-index, and the
    /// server command that answers the client's (an upload by an upload response, a
    /// download by a download response; either by an abort). A response to another
    /// transfer on the same object, late or misrouted, is not.
    #[must_use]
    pub const fn answers(&self, request: &SdoRequest) -> bool {
        let (index, sub) = self.object();
        let (r_index, r_sub) = request.object();
        let command_fits = matches!(
            (self, request),
            (
                Self::Abort { .. },
                SdoRequest::Upload { .. } | SdoRequest::Download { .. }
            ) | (Self::Uploaded { .. }, SdoRequest::Upload { .. })
                | (Self::Downloaded { .. }, SdoRequest::Download { .. })
        );
        index == r_index && sub == r_sub && command_fits
    }
}

/// SDO abort codes (CiA 301 table 22) the master sends or acts on.
pub mod abort_code {
    /// SDO protocol timed out: the client gives a transfer up.
    pub const TIMEOUT: u32 = 0x0504_0000;
    /// Attempt to write a read only object.
    pub const READ_ONLY: u32 = 0x0601_0002;
    /// Object does not exist in the object dictionary.
    pub const NO_OBJECT: u32 = 0x0602_0000;
    /// The object cannot be mapped to the PDO.
    pub const CANNOT_MAP: u32 = 0x0604_0041;
    /// General parameter incompatibility.
    pub const INCOMPATIBLE: u32 = 0x0604_0043;
    /// Access failed due to a hardware error.
    pub const HARDWARE: u32 = 0x0606_0000;
    /// Data type does not match: the length of the service parameter does not.
    pub const WRONG_LENGTH: u32 = 0x0607_0010;
    /// Sub-index does not exist.
    pub const NO_SUBINDEX: u32 = 0x0609_0011;
    /// Invalid value for parameter (value range exceeded).
    pub const INVALID_VALUE: u32 = 0x0609_0030;
    /// Value of parameter written too high.
    pub const TOO_HIGH: u32 = 0x0609_0031;
    /// Value of parameter written too low.
    pub const TOO_LOW: u32 = 0x0609_0032;
    /// Data cannot be transferred or stored to the application.
    pub const NOT_STORED: u32 = 0x0800_0020;
    /// Data cannot be transferred because of the present device state.
    pub const DEVICE_STATE: u32 = 0x0800_0022;
}

/// A short description of an SDO abort code (CiA 301 table 22), for logs; `None` for codes
/// it does not list.
#[must_use]
pub const fn abort_text(code: u32) -> Option<&'static str> {
    Some(match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "command specifier not valid or unknown",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write only object",
        0x0601_0002 => "attempt to write a read only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => "the number and length of the objects to be mapped would exceed PDO length",
        0x0604_0043 => "general parameter incompatibility",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter",
        0x0609_0031 => "value of parameter written too high",
        0x0609_0032 => "value of parameter written too low",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => "data cannot be transferred because of local control",
        0x0800_0022 => "data cannot be transferred because of the present device state",
        _ => return None,
    })
}

impl SdoRequest {
    /// Writes the request's payload.
    pub(super) fn put(&self, p: &mut Payload) {
        let transfer = match *self {
            Self::Upload { .. } => Transfer::Plain,
            Self::Download { value, size, .. } => Transfer::Expedited { value, size },
            Self::Abort { code, .. } => Transfer::Abort(code),
        };
        transfer.put(p, REQUEST, self.object());
    }

    /// Reads a request's payload.
    pub(super) fn read(p: &Payload) -> Result<Self, DecodeError> {
        let ((index, sub), transfer) = Transfer::read(p, REQUEST)?;
        Ok(match transfer {
            Transfer::Plain => Self::Upload { index, sub },
            Transfer::Expedited { value, size } => Self::Download {
                index,
                sub,
                value,
                size,
            },
            Transfer::Abort(code) => Self::Abort { index, sub, code },
        })
    }
}

impl SdoResponse {
    /// Writes the response's payload.
    pub(super) fn put(&self, p: &mut Payload) {
        let transfer = match *self {
            Self::Uploaded { value, size, .. } => Transfer::Expedited { value, size },
            Self::Downloaded { .. } => Transfer::Plain,
            Self::Abort { code, .. } => Transfer::Abort(code),
        };
        transfer.put(p, RESPONSE, self.object());
    }

    /// Reads a response's payload.
    pub(super) fn read(p: &Payload) -> Result<Self, DecodeError> {
        let ((index, sub), transfer) = Transfer::read(p, RESPONSE)?;
        Ok(match transfer {
            Transfer::Plain => Self::Downloaded { index, sub },
            Transfer::Expedited { value, size } => Self::Uploaded {
                index,
                sub,
                value,
                size,
            },
            Transfer::Abort(code) => Self::Abort { index, sub, code },
        })
    }
}

/// The command bytes of one direction: the one without data (an upload request, a download
/// response) and the expedited transfer's (a download request, an upload response), whose
/// size bits [`Transfer::put`] sets.
struct Commands {
    plain: u8,
    expedited: u8,
}

/// Client → server: ccs 2 (upload) and 1 (download).
const REQUEST: Commands = Commands {
    plain: layout::SDO_UPLOAD,
    expedited: layout::SDO_DOWNLOAD,
};
/// Server → client: scs 3 (download done) and 2 (upload).
const RESPONSE: Commands = Commands {
    plain: layout::SDO_DOWNLOADED,
    expedited: layout::SDO_UPLOADED,
};

/// What an SDO payload carries besides the object, in either direction.
enum Transfer {
    /// The command alone.
    Plain,
    /// An expedited value of `size` bytes (1..=4).
    Expedited { value: u32, size: u8 },
    /// An abort code.
    Abort(u32),
}

impl Transfer {
    fn put(self, p: &mut Payload, commands: Commands, (index, sub): (u16, u8)) {
        let (command, data) = match self {
            Self::Plain => (commands.plain, 0),
            Self::Expedited { value, size } => {
                let size = size.clamp(1, 4);
                (commands.expedited | (4 - size) << 2, mask(value, size))
            }
            Self::Abort(code) => (layout::SDO_ABORT, code),
        };
        layout::SDO_COMMAND.put_raw(p, command.into());
        layout::SDO_INDEX.put_raw(p, index.into());
        layout::SDO_SUBINDEX.put_raw(p, sub.into());
        layout::SDO_DATA.put_raw(p, data.into());
    }

    fn read(p: &Payload, commands: Commands) -> Result<((u16, u8), Self), DecodeError> {
        let command = layout::SDO_COMMAND.raw(p) as u8;
        // The fields are 16 and 8 bits wide.
        let object = (
            layout::SDO_INDEX.raw(p) as u16,
            layout::SDO_SUBINDEX.raw(p) as u8,
        );
        let data = layout::SDO_DATA.raw(p) as u32;
        let transfer = match command {
            c if c == commands.plain => Self::Plain,
            layout::SDO_ABORT => Self::Abort(data),
            // The direction's expedited command specifier: bits 5-7 as it, expedited (bit 1)
            // and bit 4 clear, whatever the size bits (0, 2-3).
            c if c & 0xF2 == commands.expedited & 0xF2 => {
                let size = expedited_size(c);
                Self::Expedited {
                    value: mask(data, size),
                    size,
                }
            }
            c => {
                return Err(DecodeError::OutOfRange {
                    field: layout::SDO_COMMAND.name,
                    value: c.into(),
                });
            }
        };
        Ok((object, transfer))
    }
}

/// The `size` low bytes of `value`.
const fn mask(value: u32, size: u8) -> u32 {
    match size {
        1 => value & 0xFF,
        2 => value & 0xFFFF,
        3 => value & 0xFF_FFFF,
        _ => value,
    }
}

/// The data size of an expedited transfer's command byte: `n` in bits 2-3 counts the unused
/// bytes when bit 0 (size indicated) is set; without it the size is 4.
const fn expedited_size(command: u8) -> u8 {
    if command & 0x01 != 0 {
        4 - ((command >> 2) & 0x03)
    } else {
        4
    }
}

#[cfg(test)]
mod tests {
    use embedded_can::{Frame, StandardId};

    use super::*;
    use crate::frame::CanFrame;
    use crate::protocol::canopen::{Message, NodeId, decode};

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    #[test]
    fn sdo_command_bytes_follow_cia301() {
        let node = NodeId::new(5).unwrap();
        for (size, byte) in [(1, 0x2F), (2, 0x2B), (3, 0x27), (4, 0x23)] {
            let m = Message::SdoRequest {
                node,
                request: SdoRequest::Download {
                    index: 0x6060,
                    sub: 0,
                    value: 0x0403_0203,
                    size,
                },
            };
            let f = m.to_can_frame();
            assert_eq!(f.data()[..4], [byte, 0x60, 0x60, 0x00]);
            assert_eq!(
                f.id(),
                embedded_can::Id::Standard(StandardId::new(0x605).unwrap())
            );
            let back = decode(&f).unwrap();
            let Message::SdoRequest {
                request: SdoRequest::Download { value, size: s, .. },
                ..
            } = back
            else {
                panic!("{back:?}");
            };
            assert_eq!((s, value), (size, mask(0x0403_0203, size)));
        }
        // An upload answered with 2 bytes, and one without a size (0x42) reads as 4 bytes.
        let r = decode(&frame(
            0x585,
            &[0x4B, 0x41, 0x60, 0, 0x27, 0x02, 0xAA, 0xBB],
        ))
        .unwrap();
        assert_eq!(
            r,
            Message::SdoResponse {
                node,
                response: SdoResponse::Uploaded {
                    index: 0x6041,
                    sub: 0,
                    value: 0x0227,
                    size: 2
                }
            }
        );
        let r = decode(&frame(0x585, &[0x42, 0, 0x10, 0, 0x92, 0x01, 0x02, 0])).unwrap();
        assert!(matches!(
            r,
            Message::SdoResponse {
                response: SdoResponse::Uploaded {
                    value: 0x0002_0192,
                    size: 4,
                    ..
                },
                ..
            }
        ));
        // A segmented upload's initiation is refused on its command byte.
        assert_eq!(
            decode(&frame(0x585, &[0x41, 0, 0x10, 0, 20, 0, 0, 0])),
            Err(DecodeError::OutOfRange {
                field: "command",
                value: 0x41
            })
        );
        let abort = decode(&frame(0x585, &[0x80, 0x60, 0x60, 0, 0x11, 0, 0x09, 0x06])).unwrap();
        assert_eq!(
            abort,
            Message::SdoResponse {
                node,
                response: SdoResponse::Abort {
                    index: 0x6060,
                    sub: 0,
                    code: 0x0609_0011
                }
            }
        );
        assert_eq!(abort_text(0x0609_0011), Some("sub-index does not exist"));
    }

    #[test]
    fn an_sdo_answer_matches_index_subindex_and_command() {
        let up = SdoRequest::Upload {
            index: 0x6061,
            sub: 0,
        };
        let down = SdoRequest::Download {
            index: 0x6061,
            sub: 0,
            value: 3,
            size: 1,
        };
        let uploaded = |index, sub| SdoResponse::Uploaded {
            index,
            sub,
            value: 3,
            size: 1,
        };
        let downloaded = SdoResponse::Downloaded {
            index: 0x6061,
            sub: 0,
        };
        let abort = SdoResponse::Abort {
            index: 0x6061,
            sub: 0,
            code: abort_code::NO_OBJECT,
        };
        assert!(uploaded(0x6061, 0).answers(&up));
        assert!(abort.answers(&up) && abort.answers(&down));
        assert!(downloaded.answers(&down));
        // The same object, the wrong command: the answer to another transfer.
        assert!(!downloaded.answers(&up));
        assert!(!uploaded(0x6061, 0).answers(&down));
        // The right command, another index or sub-index.
        assert!(!uploaded(0x6060, 0).answers(&up));
        assert!(!uploaded(0x6061, 1).answers(&up));
        // A client's abort is answered by nothing.
        let client_abort = SdoRequest::Abort {
            index: 0x6061,
            sub: 0,
            code: abort_code::TIMEOUT,
        };
        assert!(!abort.answers(&client_abort) && !downloaded.answers(&client_abort));
    }
}
