//! What a server did: [`LiveStats`] so far, a [`ClientReport`] per client and the
//! [`LiveReport`] at the end.

use std::net::SocketAddr;
use std::time::Duration;

#[cfg(doc)]
use super::LiveServer;
#[cfg(doc)]
use crate::LiveOptions;

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
