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

pub mod canopen;
pub mod dji;
pub mod error;
pub mod odrive;
pub mod robot;
pub mod wire;

pub use error::{DecodeError, ErrorKind, RxErrorCounters, non_finite_name};
