//! One client: its subscriptions, and its queue, filled by the log's thread and emptied by its
//! task, bounded in messages and bytes, dropping (and counting) its oldest.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Instant;

use foxglove::websocket::ws_protocol::JsonMessage as _;
use foxglove::websocket::ws_protocol::server::Status;
use tokio::sync::Notify;
use tokio_tungstenite::tungstenite::Message;

use super::{ClientReport, MAX_CONTROL, WRITE_BATCH};

pub(super) struct Client {
    pub(super) addr: SocketAddr,
    pub(super) subprotocol: &'static str,
    pub(super) since: Instant,
    pub(super) subscriptions: Mutex<Subscriptions>,
    pub(super) queue: Mutex<Queue>,
    pub(super) wake: Notify,
    pub(super) queued: AtomicU64,
    pub(super) sent: AtomicU64,
    pub(super) dropped: AtomicU64,
}

/// A client's subscriptions, both ways: one per channel at most, so that a message costs the
/// writing thread one look-up per client.
#[derive(Default)]
pub(super) struct Subscriptions {
    /// Subscription id → channel id.
    pub(super) by_id: HashMap<u32, u64>,
    /// Channel id → subscription id.
    pub(super) by_channel: HashMap<u64, u32>,
}

#[derive(Default)]
pub(super) struct Queue {
    pub(super) control: VecDeque<Message>,
    pub(super) data: VecDeque<Message>,
    /// The bytes of the messages in `data`.
    pub(super) data_bytes: usize,
    /// Set when the client is to be disconnected.
    pub(super) closed: bool,
    /// Why the server disconnects it, if it does (the status it is sent).
    pub(super) cut_off: Option<String>,
}

pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Client {
    /// A client just connected: nothing subscribed, nothing queued.
    pub(super) fn new(addr: SocketAddr, subprotocol: &'static str) -> Self {
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
    pub(super) fn push_control(&self, text: String) -> bool {
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
    pub(super) fn push_data(&self, bytes: Vec<u8>, backlog: usize, max_bytes: usize) {
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
    pub(super) fn status(&self, status: &Status) -> bool {
        self.push_control(status.to_string())
    }

    /// Disconnects the client for `why`: a `status` error saying so is the last message it
    /// gets (what was queued for it is dropped), then a close frame; it is no longer read.
    /// Whether it was cut off now (not before).
    pub(super) fn cut_off(&self, why: String) -> bool {
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

    pub(super) fn is_closed(&self) -> bool {
        lock(&self.queue).closed
    }

    /// Control messages and at most [`WRITE_BATCH`] bytes of data (at least one message)
    /// to send now, and whether the client is closed.
    pub(super) fn take_batch(&self) -> (VecDeque<Message>, Vec<Message>, bool) {
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

    pub(super) fn report(&self) -> ClientReport {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SUBPROTOCOL;

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
