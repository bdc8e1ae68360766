//! The Linux edge of the mecanum drive: the control core at a fixed rate on a SocketCAN
//! interface.
//!
//! The [`Controller`](firmware::Controller) is a pure state machine: it reads no clock and does
//! no I/O. A runner owns both. [`run`] is the runner's whole loop, written against two small
//! traits so that it can be tested without a CAN interface or real time:
//!
//! - a [`Bus`]: non-blocking receive, send; [`SocketCanBus`] is the SocketCAN one;
//! - a [`Clock`]: microseconds since an arbitrary epoch and "sleep until";
//!   [`MonotonicClock`] is `CLOCK_MONOTONIC` (through [`std::time::Instant`]).
//!
//! The `mecanum-runner` binary is [`SocketCanBus`] + [`MonotonicClock`] + [`run_recorded`] +
//! a command line, signal handling ([`stop_on_signals`]) and its log (a [`Recorder`]);
//! `hostsim plant` and `hostsim replay --iface` use the same bus and clock. How the loop
//! schedules, sends, handles a lost link, stops and measures its jitter is on
//! [`run_recorded`]; what it reports, on [`Report`]. The loop itself is [`run_node`], over
//! one [`Node`]: the core here, the simulated drives in `hostsim plant`.

mod bus;
mod cli;
mod clock;
mod node;
mod report;
mod run;
mod schedule;
mod sdo;
mod signals;
mod socketcan;
pub mod testing;
#[cfg(test)]
mod tests;

pub use bus::{Bus, BusErrorFrame, ErrorKind, classify, is_bus_error_frame, is_busy};
pub use cli::{error_line, parse_seconds, write_stats_json};
pub use clock::{Clock, MAX_SPIN_US, MonotonicClock};
pub use node::{Node, run_node};
pub use report::{
    ControllerReport, CoreFigures, ErrorCounts, ErrorLog, LatencyHistogram, LatencySummary,
    LinkReport, LoopReport, Report, ShutdownReport, StopReason,
};
pub use run::{
    LinkEvent, ParamStore, Recorder, RunOptions, id_text, run, run_recorded, send_with_retry,
};
pub use schedule::Schedule;
pub use sdo::{FramePort, SdoClient};
pub use signals::{stop_on_signals, stop_requested};
pub use socketcan::{OpenError, SocketCanBus};
