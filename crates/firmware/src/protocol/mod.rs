//! CAN protocols: one module per protocol, one error type for all of them.
//!
//! Each protocol module has the same shape:
//!
//! - a `layout` module: the message table (ids, DLCs) and one [`wire::Field`] row per signal
//!   (offset, type, byte order, scale, raw range). It mirrors the protocol's DBC file in
//!   `dbc/`; no offset or scale appears anywhere else in the code.
//! - one enum (or struct) of messages per direction, with `decode` taking any
//!   [`embedded_can::Frame`] and `to_can_frame` / `to_frame` building frames.
//! - a `decode` function for either direction (for sniffers and tests), returning a
//!   `Message` enum.
//!
//! The codecs are sans-IO: no bus access, no clock, no allocation, no panics on any input.
//! Decoders return [`DecodeError`] for anything they do not accept; encoders always succeed,
//! saturating values that do not fit.

/// `from_raw`, `raw`, `as_str` and `Display` for a `#[repr(u8)]` enum whose values are a
/// DBC value table: `u8_enum!(Fault { None = 0 => "NONE", ... })`.
macro_rules! u8_enum {
    ($ty:ident { $($variant:ident = $raw:literal => $name:literal),+ $(,)? }) => {
        impl $ty {
            /// The enum value for a raw byte; `None` for values not defined.
            #[must_use]
            pub const fn from_raw(raw: u8) -> Option<Self> {
                match raw {
                    $($raw => Some(Self::$variant),)+
                    _ => None,
                }
            }

            /// The raw byte.
            #[must_use]
            pub const fn raw(self) -> u8 {
                self as u8
            }

            /// The name in the DBC's value table: the name every log and printout uses,
            /// stable when the Rust variant is renamed.
            #[must_use]
            pub const fn as_str(self) -> &'static str {
                match self {
                    $(Self::$variant => $name,)+
                }
            }
        }

        impl core::fmt::Display for $ty {
            fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                f.write_str(self.as_str())
            }
        }
    };
}

pub mod canopen;
pub mod dji;
pub mod error;
pub mod odrive;
pub mod robot;
pub mod wire;

pub use error::{DecodeError, ErrorKind, RxErrorCounters, non_finite_name};
