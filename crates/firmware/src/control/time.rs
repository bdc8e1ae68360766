//! Time as the core sees it: an [`Instant`] passed in by the adapter, and the rate dividers
//! that make the slower frames due on their steps.

/// A point in time, microseconds since an arbitrary epoch; monotonic. The core never reads a
/// clock: the adapter (runner, board, simulator) passes it in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Instant(u64);

impl Instant {
    /// From microseconds.
    #[must_use]
    pub const fn from_micros(us: u64) -> Self {
        Self(us)
    }

    /// From milliseconds.
    #[must_use]
    pub const fn from_millis(ms: u64) -> Self {
        Self(ms * 1000)
    }

    /// Microseconds since the epoch.
    #[must_use]
    pub const fn as_micros(self) -> u64 {
        self.0
    }

    /// Microseconds from `earlier` to `self`, zero if `earlier` is later.
    #[must_use]
    pub const fn micros_since(self, earlier: Self) -> u64 {
        self.0.saturating_sub(earlier.0)
    }

    /// The later of `self` and `mark` (`self` when there is no mark): a frame stamped before
    /// the last one does not move a time mark back.
    #[inline]
    #[must_use]
    pub(super) fn mark(self, mark: Option<Self>) -> Self {
        mark.map_or(self, |t| t.max(self))
    }
}

/// A rate divider: due on the first tick and then on every `period`-th one, like
/// `steps % period == 0` for a step counter starting at 0, without a division per step.
#[derive(Debug, Clone, Copy)]
pub(super) struct Every {
    period: u32,
    /// Ticks left before the next due one.
    left: u32,
}

impl Every {
    /// A divider with `period >= 1` (a 0 is treated as 1: due on every tick).
    pub(super) const fn new(period: u32) -> Self {
        Self {
            period: if period == 0 { 1 } else { period },
            left: 0,
        }
    }

    /// Advances by one tick; `true` when this tick is due.
    #[inline]
    pub(super) fn tick(&mut self) -> bool {
        let due = self.left == 0;
        self.left = if due { self.period - 1 } else { self.left - 1 };
        due
    }
}
