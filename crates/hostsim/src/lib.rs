//! Host simulator of the mecanum drive.
//!
//! The real firmware core ([`firmware::control::Controller`], the same crate that runs on the
//! MCU) runs in lockstep with a simulated plant (motors, drives, a chassis on mecanum rollers)
//! over a simulated CAN bus, in simulated time. Every frame and state is logged to MCAP as ROS 2
//! messages ([`log`]); a log can be replayed to check that the core still produces the same frames, bit for bit.

pub mod bringup;
pub mod bus;
pub mod calibrate;
pub mod canopen_drive;
pub mod cmd;
pub mod drives;
pub mod engine;
pub mod host;
pub mod imu;
pub mod kin;
/// The logs: ROS 2 messages in MCAP (the `drivelog` crate, shared with the firmware's runner).
pub use drivelog as log;
pub mod plant;
pub mod plot;
pub mod pods;
pub mod realtime;
pub mod replay;
pub mod scenario;
pub mod sensor;
pub mod sim;
pub mod summary;
pub mod sweep;
pub mod whatif;
