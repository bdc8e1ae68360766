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

/// `/can/*` for live clients: per channel and CAN id, one frame per `period_ns` of log time
/// on average, on a schedule (the generic cell rate algorithm): a frame is forwarded when it
/// is at most half a period ahead of its id's due time, which then moves one period past the
/// later of itself and the frame. A periodic id at the limit passes whole whatever its jitter
/// (up to a quarter period: a 100 Hz id with 1 ms of jitter arrives at 100 Hz); a faster one
/// is cut to the limit, any second holding at most one frame more; a slower one passes whole.
struct Thinning {
    period_ns: u64,
    /// How far ahead of its due time a frame is still forwarded: half a period.
    early_ns: u64,
    /// (channel id, CAN id) → when its next frame is due, log time.
    due: HashMap<(u16, u32), u64>,
}

impl Thinning {
    fn new(hz: u32) -> Self {
        let period_ns = if hz == 0 {
            0
        } else {
            1_000_000_000 / u64::from(hz)
        };
        Self {
            period_ns,
            early_ns: period_ns / 2,
            due: HashMap::new(),
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
        let due = self.due.entry((channel.id(), id)).or_insert(log_ns);
        if log_ns.saturating_add(self.early_ns) < *due {
            return true;
        }
        *due = (*due).max(log_ns).saturating_add(self.period_ns);
        false
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
        // 100 a second, and one more from the half period of tolerance at the start.
        for name in ["rx 201", "rx 202", "tx 201"] {
            assert_eq!(
                forwarded.iter().filter(|n| **n == name).count(),
                101,
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

    /// Log times of `seconds` of an id at `hz`, each frame off its slot by up to `jitter_us`
    /// either way (a fixed pattern that sweeps the whole range), in order.
    fn jittered(hz: u64, jitter_us: i64, seconds: u64) -> Vec<u64> {
        let period_us = 1_000_000 / hz;
        (0..hz * seconds)
            .map(|k| {
                let off = (k as i64 * 7919) % (2 * jitter_us + 1) - jitter_us;
                (1_000_000 + k * period_us).saturating_add_signed(off) * 1_000
            })
            .collect()
    }

    fn count_forwarded(t: &mut Thinning, times: &[u64], id: u32) -> usize {
        let cdr = frame_cdr(id);
        times
            .iter()
            .filter(|&&ns| !t.skip(Channel::CanRx, ns, &cdr))
            .count()
    }

    #[test]
    fn a_jittered_id_at_the_limit_passes_whole_and_a_faster_one_is_cut_to_it() {
        // docs/live.md: a 100 Hz id with 1 ms of jitter arrives at 100 Hz (it arrived at 50
        // when each frame had to be a whole period after the last one forwarded).
        let mut t = Thinning::new(100);
        for jitter_us in [0, 100, 1_000, 2_400] {
            let times = jittered(100, jitter_us, 10);
            assert_eq!(
                count_forwarded(&mut t, &times, 0x300 + jitter_us as u32),
                times.len(),
                "100 Hz, jitter {jitter_us} us"
            );
        }
        // 1 kHz and 333 Hz ids with jitter: 100 a second over 10 s, one more at the start.
        for (hz, id) in [(1_000, 0x201), (333, 0x202)] {
            let n = count_forwarded(&mut t, &jittered(hz, 200, 10), id);
            assert!((1_000..=1_001).contains(&n), "{hz} Hz: {n} in 10 s");
        }
        // Slower than the limit, with jitter: whole.
        let times = jittered(40, 1_000, 10);
        assert_eq!(count_forwarded(&mut t, &times, 0x701), times.len());
        // At 50 Hz a 100 Hz id is halved, jitter or not.
        let mut half = Thinning::new(50);
        let n = count_forwarded(&mut half, &jittered(100, 1_000, 10), 0x300);
        assert!((500..=501).contains(&n), "{n}");
    }
}
