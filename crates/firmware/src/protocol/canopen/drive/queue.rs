//! What a node owes the bus: frames with the time each goes out, in that order (frames of one
//! time in the order they were queued), in a fixed capacity.

use crate::CanFrame;

/// Frames one node can owe at once. A caller that collects them every millisecond (or at
/// [`super::Drive402::next_due_ns`]) finds a few: an answer, a boot-up, a heartbeat, EMCY and
/// four TPDOs at most.
pub(super) const CAPACITY: usize = 24;

/// A node's frames to send, by time.
#[derive(Debug, Clone, Default)]
pub(super) struct Owed {
    frames: heapless::Deque<(u64, CanFrame), CAPACITY>,
    /// Frames that found the queue full (none in a run that collects them in time).
    lost: u32,
}

impl Owed {
    /// `frame`, to go out at `t_ns` (after those queued for the same time).
    pub(super) fn push(&mut self, t_ns: u64, frame: CanFrame) {
        if self.frames.is_full() {
            self.lost += 1;
            return;
        }
        let at = self.frames.iter().take_while(|(t, _)| *t <= t_ns).count();
        // Insert at `at`: to the back, then rotated into place (a few frames).
        let _ = self.frames.push_back((t_ns, frame));
        let mut i = self.frames.len() - 1;
        while i > at {
            self.frames.swap(i - 1, i);
            i -= 1;
        }
    }

    /// The time of the next frame.
    pub(super) fn next_ns(&self) -> Option<u64> {
        self.frames.front().map(|(t, _)| *t)
    }

    /// The next frame if it is due by `until_ns`.
    pub(super) fn pop_due(&mut self, until_ns: u64) -> Option<(u64, CanFrame)> {
        if self.next_ns()? <= until_ns {
            self.frames.pop_front()
        } else {
            None
        }
    }

    /// Drops everything owed (a reset, a bus-off).
    pub(super) fn clear(&mut self) {
        self.frames.clear();
    }

    /// Frames lost to a full queue so far.
    pub(super) const fn lost(&self) -> u32 {
        self.lost
    }
}
