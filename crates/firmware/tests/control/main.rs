//! The control core on a scripted bus: motor feedback is fed at the drives' real rates, robot
//! commands at chosen times, and the frames the core emits are decoded with the same codecs
//! the rest of the stack uses. One file a feature, around the shared rig (`rig.rs`).

// The scripted drives walk several per-wheel arrays in step.
#![allow(clippy::needless_range_loop)]

mod canopen_bus;
mod rig;

mod cia402;
mod drives;
mod fight;
mod gyro;
mod odometry;
mod odrive;
mod params;
mod pods;
mod rejection;
mod spec;
mod states;
mod stuck_encoder;
mod watchdog;
mod wheel_test;
