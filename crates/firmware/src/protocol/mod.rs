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

/// Declares a `#[repr(u8)]` enum whose values are a DBC value table, each variant with its raw
/// value and its name in the table written once (`Fault { None = 0 => "NONE", ... }`, docs and
/// attributes before the type and each variant), and gives it `from_raw`, `raw`, `as_str`
/// and `Display`.
macro_rules! u8_enum {
    (
        $(#[$meta:meta])*
        $ty:ident {
            $($(#[$vmeta:meta])* $variant:ident = $raw:literal => $name:literal),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
        #[repr(u8)]
        pub enum $ty {
            $($(#[$vmeta])* $variant = $raw,)+
        }

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

/// Declares a validated `u8` id: `new` accepts exactly the raw values that match the pattern
/// given (`EscId(1..=8)`), `get` returns the raw value.
macro_rules! u8_id {
    ($(#[$meta:meta])* $ty:ident($valid:pat)) => {
        $(#[$meta])*
        #[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
        pub struct $ty(u8);

        impl $ty {
            /// The id `raw`; `None` outside the range the type's doc gives.
            #[must_use]
            #[inline]
            pub const fn new(raw: u8) -> Option<Self> {
                if matches!(raw, $valid) {
                    Some(Self(raw))
                } else {
                    None
                }
            }

            /// The raw id.
            #[must_use]
            pub const fn get(self) -> u8 {
                self.0
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
