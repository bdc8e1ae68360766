//! Firmware core of the mecanum drive: the CAN codecs and the control loop that the MCU
//! boards, the Linux runner and the simulator share.
//!
//! This crate is `no_std`, allocation-free and free of `unsafe`; it builds for
//! `thumbv7em-none-eabihf`. It talks four CAN protocols, each in its own module under
//! [`protocol`]:
//!
//! - [`protocol::dji`]: DJI RoboMaster C620/C610 ESCs (current commands, rotor feedback);
//! - [`protocol::odrive`]: ODrive CAN Simple, firmware 0.6 (velocity setpoints, estimates);
//! - [`protocol::canopen`]: CANopen (CiA 301) and the CiA 402 drive profile, as the master;
//! - [`protocol::robot`]: the robot's own protocol (twist in; odometry, status out).
//!
//! The frame layouts are specified by the DBC files in the repository's `dbc/` folder; each
//! module's `layout` table mirrors its DBC, and the Python tests check the two against each
//! other through the `mecanum-codec` tool (feature `std`).
//!
//! Frames are any [`embedded_can::Frame`]; [`CanFrame`] is the crate's own `Copy` frame type.
//!
//! # Example
//!
//! ```
//! use embedded_can::Frame;
//! use firmware::protocol::robot::{self, Command, TwistCmd};
//! use firmware::protocol::{DecodeError, ErrorKind, RxErrorCounters};
//! use firmware::CanFrame;
//!
//! // The host sends a twist command...
//! let cmd = Command::Twist(TwistCmd { vx: 0.5, vy: -0.25, wz: 1.0, seq: 7 });
//! let frame: CanFrame = cmd.to_can_frame();
//! assert_eq!(frame.data(), &[0xF4, 0x01, 0x06, 0xFF, 0xE8, 0x03, 0x07, 0x00]);
//!
//! // ...and the robot decodes it, counting what it rejects.
//! let mut errors = RxErrorCounters::new();
//! assert_eq!(Command::decode(&frame), Ok(cmd));
//! let id = embedded_can::StandardId::new(robot::layout::TWIST_CMD.id).unwrap();
//! let short = CanFrame::standard(id, &[0; 7]).unwrap();
//! let err = Command::decode(&short).unwrap_err();
//! assert_eq!(err, DecodeError::WrongDlc { id: 0x301, expected: 8, got: 7 });
//! errors.record(&err);
//! assert_eq!(errors.get(ErrorKind::WrongDlc), 1);
//! ```

#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

#[cfg(any(test, feature = "std"))]
extern crate std;

pub mod config;
pub mod control;
pub mod frame;
#[cfg(feature = "std")]
pub mod input;
pub mod params;
pub mod protocol;
pub mod rng;
pub mod storage;
pub mod stream_hash;

pub use config::Config;
pub use control::{Controller, Instant, Outbox};

pub use frame::CanFrame;
pub use stream_hash::StreamHash;
