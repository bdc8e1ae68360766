//! Host simulator of the mecanum drive.
//!
//! The real firmware core ([`firmware::control::Controller`], the same crate that runs on the
//! MCU) runs in lockstep with simulated nodes (drives on a mecanum chassis, an IMU, tracking
//! pods, a host) over a simulated CAN bus, in simulated time. Every frame and state is logged
//! to MCAP as ROS 2 messages ([`drivelog`]); a log can be replayed to check that the core
//! still produces the same frames, bit for bit.
//!
//! The modules are declared lowest first: each uses only those before it.

pub mod analysis;
pub mod bus;
pub mod cmd;
pub mod engine;
pub mod nodes;
pub mod realtime;
pub mod replay;
pub mod scenario;
