//! The tap on the log's writing thread: thins `/can/*` and hands each message to the server.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use drivelog::msg::{self, DiagnosticStatus};
use drivelog::{Channel, MessageTap};

use crate::server::Shared;

/// The [`MessageTap`] of a [`LiveServer`](crate::LiveServer) ([`LiveServer::tap`]): install
/// it on the log with [`drivelog::McapLog::set_tap`]. It runs on the log's writing thread and
/// never waits: it queues each message for the clients subscribed to its channel (a full
/// queue drops its oldest), and wakes their tasks at the end of each batch.
///
/// [`LiveServer::tap`]: crate::LiveServer::tap
pub struct LiveTap {
    shared: Arc<Shared>,
    thinning: Thinning,
}

impl LiveTap {
    pub(crate) fn new(shared: Arc<Shared>) -> Self {
        let thinning = Thinning::new(shared.options.can_hz);
        Self { shared, thinning }
    }
}

impl MessageTap for LiveTap {
    fn channels(&mut self, channels: &[Channel]) {
        self.shared.set_channels(channels);
    }

    fn message(&mut self, channel: Channel, log_ns: u64, _publish_ns: u64, cdr: &[u8]) {
        if self.thinning.skip(channel, log_ns, cdr) {
            self.shared.thinned.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.shared.publish(channel, log_ns, cdr);
    }

    fn end_batch(&mut self) {
        self.shared.wake_all();
    }

    fn status(&mut self) -> Option<DiagnosticStatus> {
        Some(self.shared.status())
    }
}

/// `/can/*` for live clients: per channel and CAN id, at most one frame per `period_ns` of
/// log time (the first of each period).
struct Thinning {
    period_ns: u64,
    /// (channel id, CAN id) → log time of the last frame forwarded.
    last: HashMap<(u16, u32), u64>,
}

impl Thinning {
    fn new(hz: u32) -> Self {
        Self {
            period_ns: if hz == 0 {
                0
            } else {
                1_000_000_000 / u64::from(hz)
            },
            last: HashMap::new(),
        }
    }

    /// Whether a message is thinned out (not forwarded).
    fn skip(&mut self, channel: Channel, log_ns: u64, cdr: &[u8]) -> bool {
        if self.period_ns == 0 {
            return false;
        }
        let id = match channel {
            Channel::CanRx | Channel::CanTx => msg::decode::<msg::Frame>(cdr).map(|f| f.id),
            Channel::CanFaults => msg::decode::<msg::BusFault>(cdr).map(|f| f.frame.id),
            _ => return false,
        };
        // A frame that does not decode is forwarded: thinning never hides the unexpected.
        let Ok(id) = id else { return false };
        match self.last.get_mut(&(channel.id(), id)) {
            Some(last) if log_ns < last.saturating_add(self.period_ns) => true,
            Some(last) => {
                *last = log_ns;
                false
            }
            None => {
                self.last.insert((channel.id(), id), log_ns);
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame_cdr(id: u32) -> Vec<u8> {
        let f = msg::Frame {
            id,
            dlc: 8,
            ..msg::Frame::default()
        };
        let mut out = Vec::new();
        msg::encode(&mut out, &f);
        out
    }

    #[test]
    fn can_frames_are_thinned_per_channel_and_id_and_the_rest_never() {
        let mut t = Thinning::new(100);
        let (a, b) = (frame_cdr(0x201), frame_cdr(0x202));
        let mut forwarded = Vec::new();
        // One second of two ids at 1 kHz on /can/rx, and one id on /can/tx.
        for ms in 0..1000u64 {
            let t_ns = ms * 1_000_000;
            for (channel, cdr, name) in [
                (Channel::CanRx, &a, "rx 201"),
                (Channel::CanRx, &b, "rx 202"),
                (Channel::CanTx, &a, "tx 201"),
            ] {
                if !t.skip(channel, t_ns, cdr) {
                    forwarded.push(name);
                }
            }
        }
        for name in ["rx 201", "rx 202", "tx 201"] {
            assert_eq!(
                forwarded.iter().filter(|n| **n == name).count(),
                100,
                "{name}"
            );
        }
        // Other channels, and all frames at 0 Hz, pass.
        assert!(!t.skip(Channel::Odom, 5, b"whatever"));
        let mut all = Thinning::new(0);
        assert!((0..10).all(|i| !all.skip(Channel::CanRx, i, &a)));
        // A frame that does not decode passes.
        assert!(!t.skip(Channel::CanRx, 1, b"bad"));
    }
}
