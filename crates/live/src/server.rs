//! The WebSocket server: a thread with a current-thread tokio runtime, a task per client.
//!
//! The Foxglove SDK's own `WebSocketServer` is not used, only its protocol messages
//! (`foxglove::websocket::ws_protocol`): its per-client queue drops the oldest message when a
//! client falls behind but keeps no count of them (the count is discarded inside the SDK),
//! and it refuses clients that offer the protocol's former name, `foxglove.websocket.v1`
//! (Lichtblick before late 2025). This server does the part of protocol version 1 a log needs:
//! `serverInfo`, `advertise`, `subscribe`/`unsubscribe`, `messageData` and `status`; and, for
//! a program that serves the robot's parameters, `getParameters`/`setParameters` answered
//! with `parameterValues` (crate::params).
//!
//! Each client has a queue of its own, filled by the log's writing thread ([`crate::LiveTap`])
//! and emptied by the client's task into its socket. The writing thread never waits on a
//! client: a full queue (in messages or in bytes) drops its oldest message and counts it; the
//! task that sends blocks on a slow socket while its queue fills. Per message, the writing
//! thread does one look-up per client (a client holds one subscription per channel at most),
//! whatever a client asked for.
//!
//! Caps ([`LiveOptions`]): clients at once, subscriptions per client, bytes queued per client,
//! handshakes in progress, and the size of a client's message. A client that breaks one gets
//! a `status` error naming it, then a close frame, and is no longer read.

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use tokio::net::TcpSocket;
use tokio::sync::Notify;

use crate::params::{ParamLink, ParamService};
use crate::{LiveOptions, LiveTap, SUBPROTOCOL};

mod client;
mod connection;
mod report;
mod shared;

pub use report::{ClientReport, LiveReport, LiveStats};
pub(crate) use shared::Shared;
use shared::State;

/// A client that has not completed the WebSocket handshake by then is let go.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Handshakes in progress at most: a connection beyond them is closed at once, before its
/// handshake (and counted with the refused ones). Each holds a task and a few KiB for up to
/// [`HANDSHAKE_TIMEOUT`].
const MAX_HANDSHAKES: usize = 64;

/// The largest message a client may send, bytes: a subscription is some 30 bytes, so the cap
/// on subscriptions is met long before this; it bounds what parsing one message allocates.
const MAX_CLIENT_MESSAGE: usize = 1 << 20;

/// What tungstenite reads from a client's socket at once, bytes. Its default, 128 KiB, is
/// zero-filled on the first read: resident for every client, even one that sends nothing.
/// A larger message grows the buffer up to [`MAX_CLIENT_MESSAGE`].
const READ_BUFFER: usize = 4 << 10;

/// What tungstenite gathers before it writes to a client's socket, bytes (its default is
/// 128 KiB): it holds up to this and one message more for a client that reads nothing.
const WRITE_BUFFER: usize = 32 << 10;

/// What a client's task takes from its queue at once, bytes (and one message more): the
/// rest stays in the queue, where it is counted, and dropped when the queue is full.
const WRITE_BATCH: usize = 32 << 10;

/// Control messages (`serverInfo`, `advertise`, `status`) queued for a client at most: one
/// that lets more pile up (it sends bad requests and reads nothing) is disconnected.
const MAX_CONTROL: usize = 256;

/// A live server: serves the channels of a log as its [`LiveTap`] receives them. See the
/// [crate documentation](crate).
pub struct LiveServer {
    shared: Arc<Shared>,
    addr: SocketAddr,
    stop: Arc<Notify>,
    thread: Option<JoinHandle<()>>,
}

impl LiveServer {
    /// Listens on `addr` (port 0: a free port, [`local_addr`](Self::local_addr) tells which)
    /// and serves from a thread of its own until [`stop`](Self::stop).
    ///
    /// # Errors
    /// The address cannot be bound (in use, not this machine's), naming it; or the thread or
    /// runtime could not be started.
    pub fn start(addr: SocketAddr, options: LiveOptions) -> io::Result<Self> {
        Self::start_with(addr, options, None)
    }

    /// [`start`](Self::start), serving the robot's parameters over `params` too: the server
    /// declares the Foxglove `parameters` capability and answers `getParameters` and
    /// `setParameters` through it ([`ParamLink`]).
    ///
    /// # Errors
    /// As [`start`](Self::start).
    pub fn start_with(
        addr: SocketAddr,
        options: LiveOptions,
        params: Option<Box<dyn ParamLink>>,
    ) -> io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()?;
        let listener = {
            let _entered = runtime.enter();
            let socket = if addr.is_ipv4() {
                TcpSocket::new_v4()
            } else {
                TcpSocket::new_v6()
            }?;
            socket.set_reuseaddr(true)?;
            // Accepted sockets inherit it (Linux): what waits in the kernel for a slow
            // client, neither counted nor dropped, stays small; the client's queue here
            // takes the rest, and counts what it drops.
            socket.set_send_buffer_size(options.send_buffer)?;
            socket
                .bind(addr)
                .and_then(|()| socket.listen(64))
                .map_err(|e| io::Error::new(e.kind(), format!("cannot serve on {addr}: {e}")))?
        };
        let local = listener.local_addr()?;
        let session_id = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_millis())
            .to_string();
        let shared = Arc::new(Shared {
            url: format!("ws://{local}"),
            options,
            session_id,
            state: Mutex::new(State::default()),
            stopping: AtomicBool::new(false),
            thinned: AtomicU64::new(0),
            clients_seen: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            cut_off: AtomicU64::new(0),
            params: params.map(|link| Arc::new(ParamService::new(link))),
        });
        let stop = Arc::new(Notify::new());
        let thread = {
            let (shared, stop) = (Arc::clone(&shared), Arc::clone(&stop));
            std::thread::Builder::new()
                .name("live-server".to_string())
                .spawn(move || {
                    // Out of a real-time class inherited from a runner started with `chrt`:
                    // sending to clients never holds up the control loop's thread.
                    drivelog::step_aside();
                    runtime.block_on(connection::serve(listener, shared, stop));
                })?
        };
        Ok(Self {
            shared,
            addr: local,
            stop,
            thread: Some(thread),
        })
    }

    /// The address the server listens on.
    #[must_use]
    pub const fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// `ws://ADDR:PORT`, what a client opens.
    #[must_use]
    pub fn url(&self) -> String {
        self.shared.url.clone()
    }

    /// What a program prints on stderr when it starts serving, one line: the URL and the
    /// subprotocol, as `live: ws://127.0.0.1:8765 (foxglove.sdk.v1)` (scripts read it).
    #[must_use]
    pub fn banner(&self) -> String {
        format!("live: {} ({SUBPROTOCOL})", self.shared.url)
    }

    /// The warning a program prints when the server can be reached from other machines
    /// ([`is_exposed`](crate::is_exposed)): the protocol has no authentication.
    #[must_use]
    pub fn exposure_warning(&self) -> Option<String> {
        crate::is_exposed(self.addr).then(|| {
            format!(
                "warning: live: serving on {}, beyond this machine: the Foxglove WebSocket \
                 protocol has no authentication, anyone who reaches the address can watch",
                self.addr
            )
        })
    }

    /// The tap to install on the log ([`drivelog::McapLog::set_tap`]): what it receives, the
    /// server serves.
    #[must_use]
    pub fn tap(&self) -> LiveTap {
        LiveTap::new(Arc::clone(&self.shared))
    }

    /// Makes a [`tap`](Self::tap) each time it is called, from any thread: for a log that
    /// starts new files (a runner's rotated log), each of which needs a tap of its own.
    pub fn tap_maker(&self) -> impl Fn() -> LiveTap + Send + Sync + 'static {
        let shared = Arc::clone(&self.shared);
        move || LiveTap::new(Arc::clone(&shared))
    }

    /// The figures so far.
    #[must_use]
    pub fn stats(&self) -> LiveStats {
        self.shared.stats()
    }

    /// Stops listening (the port is closed when this returns), gives each client what is
    /// queued for it and a close frame, within [`LiveOptions::close_grace`], cuts off the
    /// clients that have not taken them by then, and reports. Call it after the log is
    /// finished, so that its last messages are queued.
    #[must_use]
    pub fn stop(mut self) -> LiveReport {
        self.shutdown();
        self.shared.report()
    }

    fn shutdown(&mut self) {
        if let Some(thread) = self.thread.take() {
            self.stop.notify_one();
            let _ = thread.join();
        }
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.shutdown();
    }
}
