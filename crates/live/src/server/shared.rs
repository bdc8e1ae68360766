//! What the server's thread and the log's tap share: the channels, the clients and the
//! counts; publishing a message, and a client's requests.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use drivelog::Channel;
use drivelog::msg::{DiagnosticStatus, KeyValue};
use foxglove::websocket::ws_protocol::client::{ClientMessage, Subscription};
use foxglove::websocket::ws_protocol::parameter::Parameter;
use foxglove::websocket::ws_protocol::schema::Schema;
use foxglove::websocket::ws_protocol::server::server_info::Capability;
use foxglove::websocket::ws_protocol::server::{
    self as proto, MessageData, ParameterValues, ServerInfo, Status,
};
use foxglove::websocket::ws_protocol::{BinaryMessage as _, JsonMessage as _};

use super::client::{Client, lock};
use super::{ClientReport, LiveReport, LiveStats};
use crate::params::{Answer, ParamService};
use crate::{LiveOptions, STATUS_NAME};

/// What the server's thread and the log's tap share.
pub(crate) struct Shared {
    pub(crate) options: LiveOptions,
    pub(super) url: String,
    pub(super) session_id: String,
    pub(super) state: Mutex<State>,
    pub(super) stopping: AtomicBool,
    pub(crate) thinned: AtomicU64,
    pub(super) clients_seen: AtomicU64,
    pub(super) refused: AtomicU64,
    pub(super) cut_off: AtomicU64,
    /// The robot's parameters, when the program serves them.
    pub(super) params: Option<Arc<ParamService>>,
}

/// A client's request the robot's parameter service answers (off the server's thread: it
/// waits on the bus).
pub(super) enum ParamRequest {
    Get(Vec<String>, Option<String>),
    Set(Vec<Parameter>, Option<String>),
}

/// The channels (once the tap has them) and the clients: one lock, so that a client that
/// connects while the channels arrive is advertised them once.
#[derive(Default)]
pub(super) struct State {
    pub(super) channels: Vec<Channel>,
    pub(super) clients: Vec<Arc<Client>>,
    pub(super) gone: Vec<ClientReport>,
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

    pub(super) fn stats(&self) -> LiveStats {
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

    pub(super) fn report(&self) -> LiveReport {
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
    pub(super) fn register(
        &self,
        addr: SocketAddr,
        subprotocol: &'static str,
    ) -> Option<Arc<Client>> {
        let mut state = lock(&self.state);
        if state.clients.len() >= self.options.max_clients {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        let client = Arc::new(Client::new(addr, subprotocol));
        let mut info = ServerInfo::new(self.options.name.clone()).with_session_id(&self.session_id);
        if self.params.is_some() {
            info = info.with_capabilities([Capability::Parameters]);
        }
        client.push_control(info.to_string());
        if !state.channels.is_empty() {
            client.push_control(advertise(&state.channels));
        }
        state.clients.push(Arc::clone(&client));
        self.clients_seen.fetch_add(1, Ordering::Relaxed);
        Some(client)
    }

    /// The `status` a connection beyond [`LiveOptions::max_clients`] gets before the close.
    pub(super) fn refusal(&self) -> String {
        let max = self.options.max_clients;
        Status::error(format!(
            "too many clients: this server serves {max} at once (--live-max-clients {max}); \
             try again when one leaves, or restart it with a larger --live-max-clients"
        ))
        .to_string()
    }

    pub(super) fn cut_off(&self, client: &Client, why: String) {
        if client.cut_off(why) {
            self.cut_off.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Counts a client that [`Client::push_control`] cut off.
    pub(super) fn count_cut(&self, cut: bool) {
        if cut {
            self.cut_off.fetch_add(1, Ordering::Relaxed);
        }
    }

    pub(super) fn unregister(&self, client: &Arc<Client>) {
        let mut state = lock(&self.state);
        if let Some(i) = state.clients.iter().position(|c| Arc::ptr_eq(c, client)) {
            state.clients.remove(i);
            state.gone.push(client.report());
        }
    }

    /// A text message from a client: subscriptions, and the parameters' requests when the
    /// server has them (returned: the caller has them answered off this thread); anything
    /// else is answered with a status.
    pub(super) fn on_text(&self, client: &Client, text: &str) -> Option<ParamRequest> {
        match ClientMessage::parse_json(text) {
            Ok(ClientMessage::GetParameters(g)) if self.params.is_some() => {
                return Some(ParamRequest::Get(g.parameter_names, g.id));
            }
            Ok(ClientMessage::SetParameters(s)) if self.params.is_some() => {
                return Some(ParamRequest::Set(s.parameters, s.id));
            }
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
                "not supported by this server (it serves a log{}): {}",
                if self.params.is_some() {
                    " and the robot's parameters"
                } else {
                    ", read-only"
                },
                op_name(&other)
            )))),
            Err(e) => {
                self.count_cut(client.status(&Status::error(format!("invalid message: {e}"))));
            }
        }
        None
    }

    /// Answers a parameters' request: waits (on a thread of the runtime's blocking pool, not
    /// the server's) for the robot, then queues a `status` error per refusal or failure and
    /// `parameterValues` (with the request's id), in that order.
    pub(super) async fn answer(&self, client: &Client, request: ParamRequest) {
        let Some(service) = self.params.clone() else {
            return;
        };
        let (answer, id) = match tokio::task::spawn_blocking(move || match request {
            ParamRequest::Get(names, id) => (service.get(&names), id),
            ParamRequest::Set(values, id) => (service.set(&values), id),
        })
        .await
        {
            Ok(done) => done,
            Err(e) => (
                Answer {
                    values: Vec::new(),
                    errors: vec![format!("the parameters' request failed: {e}")],
                },
                None,
            ),
        };
        // The statuses first: a client that reads up to the answer has them all.
        let mut cut = false;
        for error in answer.errors {
            cut |= client.status(&Status::error(error));
        }
        let mut values = ParameterValues::new(answer.values);
        values.id = id;
        cut |= client.push_control(values.to_string());
        self.count_cut(cut);
    }

    /// A `subscribe`: a subscription to an unknown channel is answered with an error; more
    /// than [`LiveOptions::max_subscriptions`] in all, an id in use or a channel subscribed
    /// already cut the client off. The work is at most one step per subscription allowed.
    pub(super) fn subscribe(&self, client: &Client, asked: &[Subscription]) {
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
