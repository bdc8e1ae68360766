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
//! client: a full queue drops its oldest message and counts it; the task that sends blocks on
//! a slow socket while its queue fills.

use std::collections::hash_map::Entry;
use std::collections::{HashMap, VecDeque};
use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use drivelog::Channel;
use drivelog::msg::{DiagnosticStatus, KeyValue};
use foxglove::websocket::ws_protocol::client::ClientMessage;
use foxglove::websocket::ws_protocol::schema::Schema;
use foxglove::websocket::ws_protocol::server::{self as proto, MessageData, ServerInfo, Status};
use foxglove::websocket::ws_protocol::{BinaryMessage as _, JsonMessage as _};
use futures_util::stream::SplitSink;
use futures_util::{SinkExt as _, StreamExt as _};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::Notify;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;

use crate::{LiveOptions, LiveTap, STATUS_NAME, SUBPROTOCOL, SUBPROTOCOL_LEGACY};

/// A client that has not completed the WebSocket handshake by then is let go.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The largest message a client may send, bytes.
const MAX_CLIENT_MESSAGE: usize = 1 << 20;

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
    /// Subscription id → channel id.
    subscriptions: Mutex<HashMap<u32, u64>>,
    queue: Mutex<Queue>,
    wake: Notify,
    queued: AtomicU64,
    sent: AtomicU64,
    dropped: AtomicU64,
}

#[derive(Default)]
struct Queue {
    control: VecDeque<Message>,
    data: VecDeque<Message>,
    /// Set when the client is to be disconnected.
    closed: bool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Client {
    fn push_control(&self, text: String) {
        let mut q = lock(&self.queue);
        if q.control.len() >= MAX_CONTROL {
            q.closed = true;
        } else {
            q.control.push_back(Message::text(text));
        }
        drop(q);
        self.wake.notify_one();
    }

    /// Queues a data message; drops the oldest if the queue holds `backlog`.
    fn push_data(&self, bytes: Vec<u8>, backlog: usize) {
        let mut q = lock(&self.queue);
        if q.closed {
            return;
        }
        self.queued.fetch_add(1, Ordering::Relaxed);
        if q.data.len() >= backlog.max(1) {
            q.data.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        q.data.push_back(Message::binary(bytes));
    }

    fn status(&self, status: &Status) {
        self.push_control(status.to_string());
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

    /// A message of the log, from the tap: queued for every subscription to its channel.
    pub(crate) fn publish(&self, channel: Channel, log_ns: u64, cdr: &[u8]) {
        let id = u64::from(channel.id());
        let state = lock(&self.state);
        for c in &state.clients {
            let subscriptions = lock(&c.subscriptions);
            for (&sub, &ch) in subscriptions.iter() {
                if ch == id {
                    let bytes = MessageData::new(sub, log_ns, cdr).to_bytes();
                    c.push_data(bytes, self.options.backlog);
                }
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

    /// The server's status on `/diagnostics`: OK, or WARN once a client has lost messages.
    pub(crate) fn status(&self) -> DiagnosticStatus {
        let s = self.stats();
        let mut message = format!("{} clients on {}", s.clients, self.url);
        if s.dropped > 0 {
            message.push_str(&format!(
                "; {} messages dropped for slow clients",
                s.dropped
            ));
        }
        let kv = |key: &str, value: String| KeyValue {
            key: key.to_string(),
            value,
        };
        DiagnosticStatus {
            level: if s.dropped > 0 {
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
        }
    }

    /// A client whose handshake is done: queued `serverInfo` and, once known, `advertise`.
    fn register(&self, addr: SocketAddr, subprotocol: &'static str) -> Arc<Client> {
        let client = Arc::new(Client {
            addr,
            subprotocol,
            since: Instant::now(),
            subscriptions: Mutex::default(),
            queue: Mutex::default(),
            wake: Notify::new(),
            queued: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
        });
        let info = ServerInfo::new(self.options.name.clone()).with_session_id(&self.session_id);
        client.push_control(info.to_string());
        let mut state = lock(&self.state);
        if !state.channels.is_empty() {
            client.push_control(advertise(&state.channels));
        }
        state.clients.push(Arc::clone(&client));
        self.clients_seen.fetch_add(1, Ordering::Relaxed);
        client
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
            Ok(ClientMessage::Subscribe(s)) => {
                let channels: Vec<u64> = lock(&self.state)
                    .channels
                    .iter()
                    .map(|c| u64::from(c.id()))
                    .collect();
                let mut subscriptions = lock(&client.subscriptions);
                for sub in s.subscriptions {
                    if !channels.contains(&sub.channel_id) {
                        client.status(&Status::error(format!(
                            "subscription {}: no channel {}",
                            sub.id, sub.channel_id
                        )));
                        continue;
                    }
                    match subscriptions.entry(sub.id) {
                        Entry::Occupied(_) => client.status(&Status::error(format!(
                            "subscription {}: the id is in use",
                            sub.id
                        ))),
                        Entry::Vacant(v) => {
                            v.insert(sub.channel_id);
                        }
                    }
                }
            }
            Ok(ClientMessage::Unsubscribe(u)) => {
                let mut subscriptions = lock(&client.subscriptions);
                for id in u.subscription_ids {
                    subscriptions.remove(&id);
                }
            }
            Ok(other) => client.status(&Status::warning(format!(
                "not supported by this server (it serves a log, read-only): {}",
                op_name(&other)
            ))),
            Err(e) => client.status(&Status::error(format!("invalid message: {e}"))),
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
    loop {
        tokio::select! {
            () = stop.notified() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, addr)) => {
                    tasks.spawn(client_task(stream, addr, Arc::clone(&shared)));
                }
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

type Sink = SplitSink<WebSocketStream<TcpStream>, Message>;

async fn client_task(stream: TcpStream, addr: SocketAddr, shared: Arc<Shared>) {
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
    // A client sends subscriptions, a few hundred bytes: nothing near tungstenite's default
    // limits (64 MiB) is needed.
    let config = WebSocketConfig::default()
        .max_message_size(Some(MAX_CLIENT_MESSAGE))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE));
    let handshake =
        tokio_tungstenite::accept_hdr_async_with_config(stream, negotiate, Some(config));
    let Ok(Ok(ws)) = tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake).await else {
        return;
    };
    let Some(subprotocol) = chosen else {
        return;
    };
    if shared.stopping.load(Ordering::Relaxed) {
        return;
    }
    let client = shared.register(addr, subprotocol);
    let (mut sink, mut source) = ws.split();
    let read = async {
        while let Some(Ok(message)) = source.next().await {
            match message {
                Message::Text(text) => shared.on_text(&client, text.as_str()),
                Message::Binary(_) => client.status(&Status::warning(
                    "not supported by this server (it serves a log, read-only): binary messages",
                )),
                Message::Close(_) => break,
                _ => {}
            }
        }
    };
    tokio::select! {
        () = read => {}
        () = write(&client, &mut sink, &shared) => {}
    }
    shared.unregister(&client);
}

/// Sends what is queued for `client`, control messages first, until the client is closed or
/// the server stops (then with a close frame).
async fn write(client: &Client, sink: &mut Sink, shared: &Shared) {
    loop {
        let (control, data, closed) = {
            let mut q = lock(&client.queue);
            (
                std::mem::take(&mut q.control),
                std::mem::take(&mut q.data),
                q.closed,
            )
        };
        if control.is_empty() && data.is_empty() {
            if closed || shared.stopping.load(Ordering::Relaxed) {
                let _ = sink.send(Message::Close(None)).await;
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
