//! The WebSocket server: a thread with a current-thread tokio runtime, a task per client.
//!
//! The Foxglove SDK's own `WebSocketServer` is not used, only its protocol messages
//! (`foxglove::websocket::ws_protocol`): its per-client queue drops the oldest message when a
//! client falls behind but keeps no count of them (the count is discarded inside the SDK),
//! and it refuses clients that offer the protocol's former name, `foxglove.websocket.v1`
//! (Lichtblick before late 2025). This server does the part of protocol version 1 a log needs:
//! `serverInfo`, `advertise`, `subscribe`/`unsubscribe`, `messageData` and `status`.
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

use std::collections::{HashMap, VecDeque};
use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use drivelog::Channel;
use drivelog::msg::{DiagnosticStatus, KeyValue};
use foxglove::websocket::ws_protocol::client::{ClientMessage, Subscription};
use foxglove::websocket::ws_protocol::schema::Schema;
use foxglove::websocket::ws_protocol::server::{self as proto, MessageData, ServerInfo, Status};
use foxglove::websocket::ws_protocol::{BinaryMessage as _, JsonMessage as _};
use futures_util::stream::SplitSink;
use futures_util::{SinkExt as _, StreamExt as _};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{Notify, Semaphore};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

use crate::{LiveOptions, LiveTap, STATUS_NAME, SUBPROTOCOL, SUBPROTOCOL_LEGACY};

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

/// What a live server has done so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LiveStats {
    /// Clients connected now (handshake done).
    pub clients: usize,
    /// Clients that have connected since the start.
    pub clients_seen: u64,
    /// Messages queued for clients (each client's subscriptions count).
    pub queued: u64,
    /// Messages written to clients' sockets.
    pub sent: u64,
    /// Messages dropped from full queues (slow clients).
    pub dropped: u64,
    /// `/can/*` frames not forwarded to live clients ([`LiveOptions::can_hz`]).
    pub thinned: u64,
    /// Connections refused: beyond [`LiveOptions::max_clients`] (after a `status` error) or
    /// beyond the handshakes in progress (closed before the handshake).
    pub refused: u64,
    /// Clients disconnected for breaking a cap: too many subscriptions, a duplicate, or
    /// too many replies left unread.
    pub cut_off: u64,
}

/// One client, at the end ([`LiveServer::stop`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClientReport {
    /// The client's address.
    pub addr: SocketAddr,
    /// The subprotocol it spoke.
    pub subprotocol: &'static str,
    /// How long it was connected.
    pub connected: Duration,
    /// Messages queued for it.
    pub queued: u64,
    /// Messages written to its socket.
    pub sent: u64,
    /// Messages it lost: dropped from its full queue, or still queued when it left or the
    /// server stopped (`queued - sent`).
    pub dropped: u64,
    /// Why the server disconnected it, when it did: the `status` error it was sent.
    pub cut_off: Option<String>,
}

/// What a live server did: [`LiveServer::stop`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LiveReport {
    /// The server's address.
    pub url: String,
    /// Every client that connected, in order.
    pub clients: Vec<ClientReport>,
    /// `/can/*` frames not forwarded ([`LiveOptions::can_hz`]).
    pub thinned: u64,
    /// Connections refused ([`LiveStats::refused`]); they are not in `clients`.
    pub refused: u64,
}

impl LiveReport {
    /// Messages lost by all clients.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.clients.iter().map(|c| c.dropped).sum()
    }

    /// Messages written to all clients.
    #[must_use]
    pub fn sent(&self) -> u64 {
        self.clients.iter().map(|c| c.sent).sum()
    }
}

impl std::fmt::Display for LiveReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} clients, {} messages sent, {} dropped for slow clients, {} CAN frames thinned",
            self.url,
            self.clients.len(),
            self.sent(),
            self.dropped(),
            self.thinned
        )?;
        if self.refused > 0 {
            write!(f, ", {} connections refused", self.refused)?;
        }
        for c in &self.clients {
            write!(
                f,
                "\n  {} ({}, {:.1} s): {} sent, {} dropped",
                c.addr,
                c.subprotocol,
                c.connected.as_secs_f64(),
                c.sent,
                c.dropped
            )?;
            if let Some(why) = &c.cut_off {
                write!(f, "; cut off: {why}")?;
            }
        }
        Ok(())
    }
}

impl LiveServer {
    /// Listens on `addr` (port 0: a free port, [`local_addr`](Self::local_addr) tells which)
    /// and serves from a thread of its own until [`stop`](Self::stop).
    ///
    /// # Errors
    /// The address cannot be bound (in use, not this machine's), naming it; or the thread or
    /// runtime could not be started.
    pub fn start(addr: SocketAddr, options: LiveOptions) -> io::Result<Self> {
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
                    runtime.block_on(serve(listener, shared, stop));
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

/// What the server's thread and the log's tap share.
pub(crate) struct Shared {
    pub(crate) options: LiveOptions,
    url: String,
    session_id: String,
    state: Mutex<State>,
    stopping: AtomicBool,
    pub(crate) thinned: AtomicU64,
    clients_seen: AtomicU64,
    refused: AtomicU64,
    cut_off: AtomicU64,
}

/// The channels (once the tap has them) and the clients: one lock, so that a client that
/// connects while the channels arrive is advertised them once.
#[derive(Default)]
struct State {
    channels: Vec<Channel>,
    clients: Vec<Arc<Client>>,
    gone: Vec<ClientReport>,
}

struct Client {
    addr: SocketAddr,
    subprotocol: &'static str,
    since: Instant,
    subscriptions: Mutex<Subscriptions>,
    queue: Mutex<Queue>,
    wake: Notify,
    queued: AtomicU64,
    sent: AtomicU64,
    dropped: AtomicU64,
}

/// A client's subscriptions, both ways: one per channel at most, so that a message costs the
/// writing thread one look-up per client.
#[derive(Default)]
struct Subscriptions {
    /// Subscription id → channel id.
    by_id: HashMap<u32, u64>,
    /// Channel id → subscription id.
    by_channel: HashMap<u64, u32>,
}

#[derive(Default)]
struct Queue {
    control: VecDeque<Message>,
    data: VecDeque<Message>,
    /// The bytes of the messages in `data`.
    data_bytes: usize,
    /// Set when the client is to be disconnected.
    closed: bool,
    /// Why the server disconnects it, if it does (the status it is sent).
    cut_off: Option<String>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Client {
    /// A client just connected: nothing subscribed, nothing queued.
    fn new(addr: SocketAddr, subprotocol: &'static str) -> Self {
        Self {
            addr,
            subprotocol,
            since: Instant::now(),
            subscriptions: Mutex::default(),
            queue: Mutex::default(),
            wake: Notify::new(),
            queued: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
        }
    }

    /// Queues a control message; a client that lets [`MAX_CONTROL`] pile up is cut off.
    /// Whether it was cut off now.
    fn push_control(&self, text: String) -> bool {
        let mut q = lock(&self.queue);
        if q.closed {
            return false;
        }
        let cut = q.control.len() >= MAX_CONTROL;
        if cut {
            q.closed = true;
            q.cut_off = Some(format!(
                "{MAX_CONTROL} replies left unread (statuses to its requests)"
            ));
        } else {
            q.control.push_back(Message::text(text));
        }
        drop(q);
        self.wake.notify_one();
        cut
    }

    /// Queues a data message; drops the oldest while the queue holds `backlog` messages or
    /// more than `max_bytes` with it (a message larger than that is queued alone).
    fn push_data(&self, bytes: Vec<u8>, backlog: usize, max_bytes: usize) {
        let mut q = lock(&self.queue);
        if q.closed {
            return;
        }
        self.queued.fetch_add(1, Ordering::Relaxed);
        let len = bytes.len();
        while !q.data.is_empty()
            && (q.data.len() >= backlog.max(1) || q.data_bytes + len > max_bytes)
        {
            if let Some(oldest) = q.data.pop_front() {
                q.data_bytes -= oldest.len();
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
        q.data_bytes += len;
        q.data.push_back(Message::binary(bytes));
    }

    /// Answers a request with a status (an error the client can live with).
    fn status(&self, status: &Status) -> bool {
        self.push_control(status.to_string())
    }

    /// Disconnects the client for `why`: a `status` error saying so is the last message it
    /// gets (what was queued for it is dropped), then a close frame; it is no longer read.
    /// Whether it was cut off now (not before).
    fn cut_off(&self, why: String) -> bool {
        let mut q = lock(&self.queue);
        if q.closed {
            return false;
        }
        q.control
            .push_back(Message::text(Status::error(why.clone()).to_string()));
        q.data.clear();
        q.data_bytes = 0;
        q.closed = true;
        q.cut_off = Some(why);
        drop(q);
        self.wake.notify_one();
        true
    }

    fn is_closed(&self) -> bool {
        lock(&self.queue).closed
    }

    /// Control messages and at most [`WRITE_BATCH`] bytes of data (at least one message)
    /// to send now, and whether the client is closed.
    fn take_batch(&self) -> (VecDeque<Message>, Vec<Message>, bool) {
        let mut q = lock(&self.queue);
        let control = std::mem::take(&mut q.control);
        let mut bytes = 0;
        let n = q
            .data
            .iter()
            .take_while(|m| {
                let first = bytes == 0;
                bytes += m.len().max(1);
                first || bytes <= WRITE_BATCH
            })
            .count();
        let data: Vec<Message> = q.data.drain(..n).collect();
        q.data_bytes -= data.iter().map(Message::len).sum::<usize>();
        (control, data, q.closed)
    }

    fn report(&self) -> ClientReport {
        let queued = self.queued.load(Ordering::Relaxed);
        let sent = self.sent.load(Ordering::Relaxed);
        ClientReport {
            addr: self.addr,
            subprotocol: self.subprotocol,
            connected: self.since.elapsed(),
            queued,
            sent,
            dropped: queued.saturating_sub(sent),
            cut_off: lock(&self.queue).cut_off.clone(),
        }
    }
}

impl Shared {
    /// The log's channels, from the tap: advertised to every client, now and later.
    /// The log's channels, advertised to the clients when they differ from those advertised
    /// before: a runner's rotated log installs a new tap on each file, with the same channels,
    /// and its clients keep their subscriptions.
    pub(crate) fn set_channels(&self, channels: &[Channel]) {
        let mut state = lock(&self.state);
        if state.channels == channels {
            return;
        }
        state.channels = channels.to_vec();
        let text = advertise(channels);
        for c in &state.clients {
            c.push_control(text.clone());
        }
    }

    /// A message of the log, from the tap: queued for each client subscribed to its channel
    /// (one look-up per client: a client holds one subscription per channel at most).
    pub(crate) fn publish(&self, channel: Channel, log_ns: u64, cdr: &[u8]) {
        let id = u64::from(channel.id());
        let state = lock(&self.state);
        for c in &state.clients {
            let sub = lock(&c.subscriptions).by_channel.get(&id).copied();
            if let Some(sub) = sub {
                let bytes = MessageData::new(sub, log_ns, cdr).to_bytes();
                c.push_data(bytes, self.options.backlog, self.options.queue_bytes);
            }
        }
    }

    /// Wakes the clients' tasks to send what was queued (at the end of each of the log's
    /// hand-overs: a wake-up per batch, not per message).
    pub(crate) fn wake_all(&self) {
        for c in &lock(&self.state).clients {
            c.wake.notify_one();
        }
    }

    fn stats(&self) -> LiveStats {
        let state = lock(&self.state);
        let mut stats = LiveStats {
            clients: state.clients.len(),
            clients_seen: self.clients_seen.load(Ordering::Relaxed),
            thinned: self.thinned.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
            cut_off: self.cut_off.load(Ordering::Relaxed),
            ..LiveStats::default()
        };
        for c in &state.clients {
            stats.queued += c.queued.load(Ordering::Relaxed);
            stats.sent += c.sent.load(Ordering::Relaxed);
            stats.dropped += c.dropped.load(Ordering::Relaxed);
        }
        for c in &state.gone {
            stats.queued += c.queued;
            stats.sent += c.sent;
            stats.dropped += c.dropped;
        }
        stats
    }

    /// The server's status on `/diagnostics`: OK, or WARN once a client has lost messages,
    /// or a connection was refused or cut off.
    pub(crate) fn status(&self) -> DiagnosticStatus {
        let s = self.stats();
        let mut message = format!("{} clients on {}", s.clients, self.url);
        if s.dropped > 0 {
            message.push_str(&format!(
                "; {} messages dropped for slow clients",
                s.dropped
            ));
        }
        if s.refused > 0 {
            message.push_str(&format!(
                "; {} connections refused (at most {} clients)",
                s.refused, self.options.max_clients
            ));
        }
        if s.cut_off > 0 {
            message.push_str(&format!("; {} clients cut off", s.cut_off));
        }
        let warn = s.dropped > 0 || s.refused > 0 || s.cut_off > 0;
        let kv = |key: &str, value: String| KeyValue {
            key: key.to_string(),
            value,
        };
        DiagnosticStatus {
            level: if warn {
                DiagnosticStatus::WARN
            } else {
                DiagnosticStatus::OK
            },
            name: STATUS_NAME.to_string(),
            message,
            hardware_id: String::new(),
            values: vec![
                kv("url", self.url.clone()),
                kv("clients", s.clients.to_string()),
                kv("clients_seen", s.clients_seen.to_string()),
                kv("dropped", s.dropped.to_string()),
                kv("thinned", s.thinned.to_string()),
                kv("can_hz", self.options.can_hz.to_string()),
                kv("backlog", self.options.backlog.to_string()),
                kv("refused", s.refused.to_string()),
                kv("cut_off", s.cut_off.to_string()),
                kv("max_clients", self.options.max_clients.to_string()),
                kv(
                    "max_subscriptions",
                    self.options.max_subscriptions.to_string(),
                ),
            ],
        }
    }

    fn report(&self) -> LiveReport {
        let state = lock(&self.state);
        let mut clients = state.gone.clone();
        clients.extend(state.clients.iter().map(|c| c.report()));
        clients.sort_by_key(|c| std::cmp::Reverse(c.connected));
        LiveReport {
            url: self.url.clone(),
            clients,
            thinned: self.thinned.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
        }
    }

    /// A client whose handshake is done: queued `serverInfo` and, once known, `advertise`;
    /// `None` (counted) when [`LiveOptions::max_clients`] are connected.
    fn register(&self, addr: SocketAddr, subprotocol: &'static str) -> Option<Arc<Client>> {
        let mut state = lock(&self.state);
        if state.clients.len() >= self.options.max_clients {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        let client = Arc::new(Client::new(addr, subprotocol));
        let info = ServerInfo::new(self.options.name.clone()).with_session_id(&self.session_id);
        client.push_control(info.to_string());
        if !state.channels.is_empty() {
            client.push_control(advertise(&state.channels));
        }
        state.clients.push(Arc::clone(&client));
        self.clients_seen.fetch_add(1, Ordering::Relaxed);
        Some(client)
    }

    /// The `status` a connection beyond [`LiveOptions::max_clients`] gets before the close.
    fn refusal(&self) -> String {
        let max = self.options.max_clients;
        Status::error(format!(
            "too many clients: this server serves {max} at once (--live-max-clients {max}); \
             try again when one leaves, or restart it with a larger --live-max-clients"
        ))
        .to_string()
    }

    fn cut_off(&self, client: &Client, why: String) {
        if client.cut_off(why) {
            self.cut_off.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Counts a client that [`Client::push_control`] cut off.
    fn count_cut(&self, cut: bool) {
        if cut {
            self.cut_off.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn unregister(&self, client: &Arc<Client>) {
        let mut state = lock(&self.state);
        if let Some(i) = state.clients.iter().position(|c| Arc::ptr_eq(c, client)) {
            state.clients.remove(i);
            state.gone.push(client.report());
        }
    }

    /// A text message from a client: subscriptions; anything else is answered with a status.
    fn on_text(&self, client: &Client, text: &str) {
        match ClientMessage::parse_json(text) {
            Ok(ClientMessage::Subscribe(s)) => self.subscribe(client, &s.subscriptions),
            Ok(ClientMessage::Unsubscribe(u)) => {
                let mut subscriptions = lock(&client.subscriptions);
                for id in u.subscription_ids {
                    if let Some(channel) = subscriptions.by_id.remove(&id) {
                        subscriptions.by_channel.remove(&channel);
                    }
                }
            }
            Ok(other) => self.count_cut(client.status(&Status::warning(format!(
                "not supported by this server (it serves a log, read-only): {}",
                op_name(&other)
            )))),
            Err(e) => {
                self.count_cut(client.status(&Status::error(format!("invalid message: {e}"))));
            }
        }
    }

    /// A `subscribe`: a subscription to an unknown channel is answered with an error; more
    /// than [`LiveOptions::max_subscriptions`] in all, an id in use or a channel subscribed
    /// already cut the client off. The work is at most one step per subscription allowed.
    fn subscribe(&self, client: &Client, asked: &[Subscription]) {
        let max = self.options.max_subscriptions;
        // Let go before the subscriptions are taken: `publish` takes the state first.
        let channels: Vec<u64> = lock(&self.state)
            .channels
            .iter()
            .map(|c| u64::from(c.id()))
            .collect();
        let mut subscriptions = lock(&client.subscriptions);
        let held = subscriptions.by_id.len();
        if held.saturating_add(asked.len()) > max {
            drop(subscriptions);
            return self.cut_off(
                client,
                format!(
                    "subscribe: {} subscriptions more than the {held} held exceed the cap of \
                     {max} per client (--live-max-subscriptions {max}); disconnected",
                    asked.len()
                ),
            );
        }
        for sub in asked {
            if !channels.contains(&sub.channel_id) {
                let cut = client.status(&Status::error(format!(
                    "subscription {}: no channel {}",
                    sub.id, sub.channel_id
                )));
                self.count_cut(cut);
                continue;
            }
            let why = if let Some(channel) = subscriptions.by_id.get(&sub.id) {
                format!(
                    "subscription {}: the id is in use (channel {channel}); a duplicate \
                     subscription is refused; disconnected",
                    sub.id
                )
            } else if let Some(other) = subscriptions.by_channel.get(&sub.channel_id) {
                format!(
                    "subscription {}: channel {} is subscribed already (subscription {other}); \
                     one subscription per channel, a duplicate is refused; disconnected",
                    sub.id, sub.channel_id
                )
            } else {
                subscriptions.by_id.insert(sub.id, sub.channel_id);
                subscriptions.by_channel.insert(sub.channel_id, sub.id);
                continue;
            };
            drop(subscriptions);
            return self.cut_off(client, why);
        }
    }
}

fn op_name(m: &ClientMessage<'_>) -> &'static str {
    match m {
        ClientMessage::Subscribe(_) => "subscribe",
        ClientMessage::Unsubscribe(_) => "unsubscribe",
        ClientMessage::Advertise(_) => "advertise",
        ClientMessage::Unadvertise(_) => "unadvertise",
        ClientMessage::MessageData(_) => "messageData",
        ClientMessage::GetParameters(_) => "getParameters",
        ClientMessage::SetParameters(_) => "setParameters",
        ClientMessage::SubscribeParameterUpdates(_) => "subscribeParameterUpdates",
        ClientMessage::UnsubscribeParameterUpdates(_) => "unsubscribeParameterUpdates",
        ClientMessage::ServiceCallRequest(_) => "serviceCallRequest",
        ClientMessage::SubscribeConnectionGraph => "subscribeConnectionGraph",
        ClientMessage::UnsubscribeConnectionGraph => "unsubscribeConnectionGraph",
        ClientMessage::FetchAsset(_) => "fetchAsset",
        ClientMessage::PlaybackControlRequest(_) => "playbackControlRequest",
    }
}

/// The `advertise` message of the log's channels: each as the file's Channel and Schema
/// records have it.
fn advertise(channels: &[Channel]) -> String {
    let channels = channels.iter().filter_map(|c| {
        let def = c.def();
        proto::Channel::builder(u64::from(c.id()), c.topic(), "cdr")
            .with_schema(Schema::new(
                def.name,
                "ros2msg",
                def.schema_text().into_bytes(),
            ))
            .build()
            .ok()
    });
    proto::Advertise::new(channels).to_string()
}

/// Accepts clients until told to stop; then closes the port and lets the clients go.
async fn serve(listener: TcpListener, shared: Arc<Shared>, stop: Arc<Notify>) {
    let mut tasks = tokio::task::JoinSet::new();
    let handshakes = Arc::new(Semaphore::new(MAX_HANDSHAKES));
    loop {
        tokio::select! {
            () = stop.notified() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, addr)) => match Arc::clone(&handshakes).try_acquire_owned() {
                    Ok(permit) => {
                        tasks.spawn(client_task(stream, addr, Arc::clone(&shared), permit));
                    }
                    // Too many handshakes under way: closed at once, nothing allocated.
                    Err(_) => {
                        shared.refused.fetch_add(1, Ordering::Relaxed);
                        drop(stream);
                    }
                },
                // Out of file descriptors, say: try again shortly.
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            },
            Some(_) = tasks.join_next(), if !tasks.is_empty() => {}
        }
    }
    drop(listener);
    shared.stopping.store(true, Ordering::Relaxed);
    shared.wake_all();
    let grace = shared.options.close_grace;
    let _ = tokio::time::timeout(grace, async { while tasks.join_next().await.is_some() {} }).await;
    // The clients still sending (stalled) are cut off: their tasks end with the runtime.
}

type Ws = WebSocketStream<TcpStream>;
type Sink = SplitSink<Ws, Message>;

async fn client_task(
    stream: TcpStream,
    addr: SocketAddr,
    shared: Arc<Shared>,
    handshaking: tokio::sync::OwnedSemaphorePermit,
) {
    let _ = stream.set_nodelay(true);
    let mut chosen = None;
    // The refusal is tungstenite's own type (the `Callback` trait's), however large.
    #[allow(clippy::result_large_err)]
    let negotiate = |request: &Request, mut response: Response| {
        let offered: Vec<&str> = request
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .flat_map(|h| h.to_str().unwrap_or_default().split(','))
            .map(str::trim)
            .collect();
        let Some(protocol) = [SUBPROTOCOL, SUBPROTOCOL_LEGACY]
            .into_iter()
            .find(|p| offered.contains(p))
        else {
            let mut refusal = ErrorResponse::new(Some(format!(
                "expected the WebSocket subprotocol {SUBPROTOCOL} (or {SUBPROTOCOL_LEGACY})"
            )));
            *refusal.status_mut() = StatusCode::BAD_REQUEST;
            return Err(refusal);
        };
        response
            .headers_mut()
            .insert("sec-websocket-protocol", HeaderValue::from_static(protocol));
        chosen = Some(protocol);
        Ok(response)
    };
    // A client sends subscriptions, a few KiB at most: nothing near tungstenite's default
    // limits (64 MiB) is needed, nor its 128 KiB buffers for every client.
    let config = WebSocketConfig::default()
        .max_message_size(Some(MAX_CLIENT_MESSAGE))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE))
        .read_buffer_size(READ_BUFFER)
        .write_buffer_size(WRITE_BUFFER);
    let handshake =
        tokio_tungstenite::accept_hdr_async_with_config(stream, negotiate, Some(config));
    let Ok(Ok(mut ws)) = tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake).await else {
        return;
    };
    drop(handshaking);
    let Some(subprotocol) = chosen else {
        return;
    };
    if shared.stopping.load(Ordering::Relaxed) {
        return;
    }
    let Some(client) = shared.register(addr, subprotocol) else {
        // Over the cap: told why, then closed, within the grace of a stop.
        let refusal = Message::text(shared.refusal());
        let _ = tokio::time::timeout(shared.options.close_grace, async {
            ws.send(refusal).await?;
            ws.close(Some(close_frame(CloseCode::Again))).await
        })
        .await;
        return;
    };
    let (mut sink, mut source) = ws.split();
    let read = async {
        while let Some(message) = source.next().await {
            match message {
                Ok(Message::Text(text)) => shared.on_text(&client, text.as_str()),
                Ok(Message::Binary(_)) => shared.count_cut(client.status(&Status::warning(
                    "not supported by this server (it serves a log, read-only): binary messages",
                ))),
                Ok(Message::Close(_)) => return false,
                Ok(_) => {}
                Err(WsError::Capacity(e)) => shared.cut_off(
                    &client,
                    format!(
                        "{e}: a client's message is at most {MAX_CLIENT_MESSAGE} bytes; \
                         disconnected"
                    ),
                ),
                Err(_) => return false,
            }
            if client.is_closed() {
                return true;
            }
        }
        false
    };
    let write = write(&client, &mut sink, &shared);
    tokio::pin!(write);
    tokio::select! {
        cut = read => {
            if cut {
                // Cut off: no longer read; its status and the close frame, if it takes them.
                let _ = tokio::time::timeout(shared.options.close_grace, &mut write).await;
            }
        }
        () = &mut write => {}
    }
    shared.unregister(&client);
}

/// The close frame of a client the server lets go for breaking a cap (`Policy`) or refuses
/// for now (`Again`): the `status` before it says why.
fn close_frame(code: CloseCode) -> CloseFrame {
    CloseFrame {
        code,
        reason: "see the status message before this close".into(),
    }
}

/// Sends what is queued for `client`, control messages first, until the client is closed or
/// the server stops (then with a close frame).
async fn write(client: &Client, sink: &mut Sink, shared: &Shared) {
    loop {
        let (control, data, closed) = client.take_batch();
        if control.is_empty() && data.is_empty() {
            if closed || shared.stopping.load(Ordering::Relaxed) {
                let cut = lock(&client.queue).cut_off.is_some();
                let frame = cut.then(|| close_frame(CloseCode::Policy));
                let _ = sink.send(Message::Close(frame)).await;
                return;
            }
            client.wake.notified().await;
            continue;
        }
        for m in control {
            if sink.feed(m).await.is_err() {
                return;
            }
        }
        let n = data.len() as u64;
        for m in data {
            if sink.feed(m).await.is_err() {
                return;
            }
        }
        if sink.flush().await.is_err() {
            return;
        }
        client.sent.fetch_add(n, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn client() -> Client {
        Client::new("127.0.0.1:1".parse().unwrap(), SUBPROTOCOL)
    }

    fn queued(c: &Client) -> (usize, usize) {
        let q = lock(&c.queue);
        (q.data.len(), q.data_bytes)
    }

    #[test]
    fn a_queue_is_bounded_in_messages_and_in_bytes_dropping_its_oldest() {
        let c = client();
        // 100 messages of 100 bytes into 1,000 bytes: the last 10 stay, 90 dropped.
        for i in 0..100u8 {
            c.push_data(vec![i; 100], 4096, 1000);
        }
        assert_eq!(queued(&c), (10, 1000));
        assert_eq!(c.dropped.load(Ordering::Relaxed), 90);
        assert_eq!(lock(&c.queue).data[0].clone().into_data()[0], 90);
        // In messages: a backlog of 4 keeps 4.
        for _ in 0..10 {
            c.push_data(vec![0; 10], 4, 1000);
        }
        assert_eq!(queued(&c), (4, 40));
        // A message larger than the cap is queued alone.
        c.push_data(vec![0; 5000], 4096, 1000);
        assert_eq!(queued(&c), (1, 5000));
        assert_eq!(c.queued.load(Ordering::Relaxed), 111);
        assert_eq!(c.dropped.load(Ordering::Relaxed), 110);
    }

    #[test]
    fn a_batch_takes_the_control_messages_and_a_bounded_share_of_data() {
        let c = client();
        c.push_control("hello".to_string());
        for _ in 0..100 {
            c.push_data(vec![0; 1000], 4096, 1 << 20);
        }
        let (control, data, closed) = c.take_batch();
        assert_eq!(
            (control.len(), data.len(), closed),
            (1, WRITE_BATCH / 1000, false)
        );
        assert_eq!(
            queued(&c),
            (100 - WRITE_BATCH / 1000, (100 - WRITE_BATCH / 1000) * 1000)
        );
        // One message larger than a batch goes alone.
        let big = client();
        big.push_data(vec![0; 2 * WRITE_BATCH], 4096, 1 << 20);
        big.push_data(vec![0; 10], 4096, 1 << 20);
        assert_eq!(big.take_batch().1.len(), 1);
        assert_eq!(queued(&big), (1, 10));
    }

    #[test]
    fn a_cut_off_client_gets_its_status_first_and_nothing_more() {
        let c = client();
        c.push_data(vec![0; 10], 4096, 1 << 20);
        assert!(c.cut_off("why".to_string()));
        assert!(!c.cut_off("again".to_string()), "counted once");
        c.push_data(vec![0; 10], 4096, 1 << 20);
        let (control, data, closed) = c.take_batch();
        assert!(closed && data.is_empty());
        let status = control[0].to_text().unwrap();
        assert!(
            status.contains(r#""level":2"#) && status.contains("why"),
            "{status}"
        );
        assert_eq!(c.report().cut_off.as_deref(), Some("why"));
        // Replies left unread: cut off at the cap.
        let deaf = client();
        let cuts: Vec<bool> = (0..=MAX_CONTROL)
            .map(|_| deaf.push_control("x".into()))
            .collect();
        assert_eq!(cuts.iter().filter(|c| **c).count(), 1);
        assert!(cuts[MAX_CONTROL]);
    }
}
