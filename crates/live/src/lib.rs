//! Watch the mecanum drive live: every channel of its log, served to Foxglove and
//! Lichtblick over the Foxglove WebSocket protocol while the log is written.
//!
//! Every log the project writes is a ROS 2 bag in MCAP (`drivelog`): CDR messages whose
//! schemas are `ros2msg` text. A [`LiveServer`] serves the same channels, with the same
//! schemas and the very same bytes, to WebSocket clients (`foxglove.sdk.v1`, and the same
//! protocol under its old name `foxglove.websocket.v1` for older Lichtblick), each message at
//! its log time: Foxglove and Lichtblick decode them as they decode the file after the run.
//!
//! # How a program uses it
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use std::collections::BTreeMap;
//! let server = live::LiveServer::start(live::DEFAULT_ADDR, live::LiveOptions::default())?;
//! eprintln!("live: {} ({})", server.url(), live::SUBPROTOCOL);
//! let mut log = drivelog::McapLog::create("run.mcap".as_ref(), &BTreeMap::new())?;
//! log.set_tap(Box::new(server.tap()));
//! log.set_flush_interval(live::FLUSH_INTERVAL);
//! // ... the run logs as usual ...
//! log.finish()?;
//! let report = server.stop();
//! eprintln!("live: {report}");
//! # Ok(()) }
//! ```
//!
//! A program's `--live [ADDR]` and `--live-can-hz` are `LiveArgs` (feature `cli`); a log
//! that starts new files (the runner's rotation) takes a tap per file from
//! [`LiveServer::tap_maker`].
//!
//! The tap ([`LiveTap`], a [`drivelog::MessageTap`]) runs on the log's writing thread, after
//! each message is in the file's writer: the control loop or simulation never waits on it,
//! and the tap itself never waits on a client (it queues, and drops the oldest of a full
//! queue). The server runs on a thread of its own.
//!
//! # What clients get, and lose
//!
//! - Every channel of the log is advertised: topic, encoding `cdr`, schema name (the ROS 2
//!   type, `nav_msgs/msg/Odometry`), schema encoding `ros2msg`, schema text as in the file's
//!   Schema record. A subscribed client gets each message with its log time.
//! - `/can/rx`, `/can/tx` and `/can/faults` are thinned for live clients: per channel and per
//!   CAN id, [`LiveOptions::can_hz`] frames a second of log time on average, jitter tolerated
//!   (100 by default; 0 forwards every frame; docs/live.md). The log keeps every frame. [`LiveStats::thinned`] counts the
//!   frames not forwarded.
//! - A client that reads slower than the messages come has a queue of its own of
//!   [`LiveOptions::backlog`] messages; when it is full the oldest message is dropped, and
//!   counted ([`ClientReport::dropped`]). The count is on `/diagnostics` (a second status,
//!   [`STATUS_NAME`], after the firmware's), in the log too, and in the [`LiveReport`] at the
//!   end.
//! - A client never holds up the run, however it behaves: [`LiveOptions::max_clients`] at
//!   once, [`LiveOptions::max_subscriptions`] each (one per channel, no duplicates), and
//!   [`LiveOptions::queue_bytes`] queued each; a client beyond a cap gets a `status` error
//!   naming it and is disconnected, and counted ([`LiveStats::refused`], [`LiveStats::cut_off`]).
//! - The protocol has no authentication: anyone who reaches the address can watch. Serve on
//!   loopback ([`DEFAULT_ADDR`]) unless the network is trusted; [`is_exposed`] tells a program
//!   when to warn.
//!
//! - A program that serves the robot's parameters ([`LiveServer::start_with`], a
//!   [`ParamLink`] to the robot's parameter service) declares the `parameters` capability:
//!   Lichtblick's Parameters panel reads and edits them, each change sent to the robot as
//!   any host's (see the `params` module).
//!
//! The rest (connecting Foxglove and Lichtblick, the figures) is `docs/live.md`.

mod addr;
#[cfg(any(feature = "cli", test))]
mod cli;
mod pace;
mod params;
mod server;
mod tap;

pub use addr::{DEFAULT_ADDR, DEFAULT_PORT, is_exposed, parse_addr};
#[cfg(any(feature = "cli", test))]
pub use cli::LiveArgs;
pub use pace::{Pacer, PacingReport};
pub use params::{PARAM_TIMEOUT, ParamLink};
pub use server::{ClientReport, LiveReport, LiveServer, LiveStats};
pub use tap::LiveTap;

use std::time::Duration;

/// The WebSocket subprotocol the server prefers: the Foxglove SDK's name of the Foxglove
/// WebSocket protocol, version 1.
pub const SUBPROTOCOL: &str = "foxglove.sdk.v1";

/// The same protocol under its former name, which Lichtblick before late 2025 and older
/// Foxglove Studio offer; accepted when a client offers no [`SUBPROTOCOL`].
pub const SUBPROTOCOL_LEGACY: &str = "foxglove.websocket.v1";

/// The name of the live server's status on `/diagnostics` (after the firmware's).
pub const STATUS_NAME: &str = "mecanum_drive: live";

/// The log's hand-over interval for a live run ([`drivelog::McapLog::set_flush_interval`]):
/// what the writing thread (and so the tap) receives at once, and so how late a message
/// reaches a client at most, besides the network.
pub const FLUSH_INTERVAL: Duration = Duration::from_millis(50);

/// How a [`LiveServer`] serves.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LiveOptions {
    /// The server's name in `serverInfo` (Foxglove shows it): the program and its run.
    pub name: String,
    /// Messages queued for one client at most; a full queue drops its oldest.
    pub backlog: usize,
    /// Bytes of messages queued for one client at most (1 MiB): beyond them the oldest are
    /// dropped and counted, as beyond [`backlog`](Self::backlog). With the write batch and
    /// the WebSocket's buffers, what a client that reads nothing costs the server (about
    /// 1.3 MB measured with the defaults; docs/live.md, "Limits").
    pub queue_bytes: usize,
    /// Clients served at once (32): a connection beyond them gets a `status` error naming
    /// the cap and is closed, and counted ([`LiveStats::refused`]). A viewer is one client
    /// (Foxglove and Lichtblick open one connection per window); the cap keeps a flood of
    /// connections from costing each a queue (`--live-max-clients`).
    pub max_clients: usize,
    /// Subscriptions one client may hold (64). The log advertises 12 channels, and Foxglove
    /// and Lichtblick subscribe once per channel; a client may not subscribe a channel twice
    /// or reuse an id, so 64 leaves room for more channels. A client that asks for more, or
    /// for a duplicate, gets a `status` error naming it and is disconnected
    /// (`--live-max-subscriptions`).
    pub max_subscriptions: usize,
    /// `/can/*` frames forwarded per channel and CAN id, per second of log time (0: all).
    pub can_hz: u32,
    /// How long [`LiveServer::stop`] lets clients take what is queued for them and the close
    /// frame, before it cuts them off.
    pub close_grace: Duration,
    /// The kernel's send buffer of each client's socket, bytes (`SO_SNDBUF`; Linux doubles
    /// it). What waits there is neither counted nor dropped, and a loopback socket left to
    /// itself grows to megabytes (seconds of a run): kept small, a slow client's losses show
    /// in its queue, counted, and what it does get is recent.
    pub send_buffer: u32,
}

impl Default for LiveOptions {
    fn default() -> Self {
        Self {
            name: "mecanum drive".to_string(),
            backlog: 4096,
            queue_bytes: 1 << 20,
            max_clients: 32,
            max_subscriptions: 64,
            can_hz: 100,
            close_grace: Duration::from_millis(500),
            send_buffer: 256 << 10,
        }
    }
}
