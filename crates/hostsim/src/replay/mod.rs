//! Replay and what-if: a log's frames through the core again, from MCAP or candump.
//!
//! Replay runs the firmware core again on a log's inbound frames and checks that it sends the
//! same frames, bit for bit; what-if ([`whatif`]) runs them through a core of another
//! configuration.
//!
//! [`replay_mcap`] replays an MCAP log ([`drivelog`]) through a fresh [`Controller`](firmware::control::Controller) built
//! from the logged configuration and returns a [`ReplayReport`] with the first difference, if
//! any; [`replay_frames`] and [`replay_at_steps`] do the same on frames already read. A
//! candump log ([`replay_candump`]) is split into the two directions with [`split_candump`]
//! and replayed with [`replay_split`], which also compares the odometry ([`CandumpReplay`]).
//! [`check_time_gaps`] bounds the work.
//!
//! How frames and steps are ordered, how a `mecanum-runner` log and a candump log replay,
//! what of a damaged log is replayed and why gaps are refused: `docs/simulator.md`, section
//! "Replay".

mod candump;
mod engine;
mod input;
pub mod whatif;

pub use self::candump::*;
pub use self::engine::*;
pub use self::input::*;
