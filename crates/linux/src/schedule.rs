//! The fixed-rate schedule both real-time loops keep: the runner's ([`crate::run_recorded`])
//! and the simulated drives' (`hostsim plant`).

/// Deadlines at `start + k · period`, never computed from the previous wake-up, so lateness
/// does not accumulate. A wake-up more than one period late is an **overrun**: the schedule is
/// re-anchored there (`start := woke, k := 0`) instead of running a burst of catch-up ticks.
///
/// ```
/// use mecanum_linux::Schedule;
///
/// let mut s = Schedule::new(1_000, 1_000);
/// assert_eq!(s.deadline(), 1_000);
/// assert_eq!(s.woke(1_050), 50); // 50 µs late: on schedule
/// s.advance();
/// assert_eq!(s.deadline(), 2_000);
/// assert_eq!(s.woke(3_500), 1_500); // more than a period late: re-anchored
/// s.advance();
/// assert_eq!((s.deadline(), s.overruns()), (4_500, 1));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schedule {
    start: u64,
    anchor: u64,
    k: u64,
    period: u64,
    overruns: u64,
}

impl Schedule {
    /// The first deadline at `start_us`, then one every `period_us` (at least 1).
    #[must_use]
    pub const fn new(start_us: u64, period_us: u64) -> Self {
        Self {
            start: start_us,
            anchor: start_us,
            k: 0,
            period: if period_us == 0 { 1 } else { period_us },
            overruns: 0,
        }
    }

    /// The period, µs.
    #[must_use]
    pub const fn period(&self) -> u64 {
        self.period
    }

    /// The first deadline, µs of the clock.
    #[must_use]
    pub const fn start(&self) -> u64 {
        self.start
    }

    /// The current tick's deadline, µs of the clock.
    #[must_use]
    pub const fn deadline(&self) -> u64 {
        self.anchor
            .saturating_add(self.k.saturating_mul(self.period))
    }

    /// The tick woke at `woke_us`: its lateness after the deadline, µs. More than one period
    /// late is an overrun, and the schedule is re-anchored at `woke_us`.
    pub const fn woke(&mut self, woke_us: u64) -> u64 {
        let late = woke_us.saturating_sub(self.deadline());
        if late > self.period {
            self.overruns += 1;
            self.anchor = woke_us;
            self.k = 0;
        }
        late
    }

    /// The tick is done: the next deadline is one period on.
    pub const fn advance(&mut self) {
        self.k += 1;
    }

    /// Overruns so far.
    #[must_use]
    pub const fn overruns(&self) -> u64 {
        self.overruns
    }
}
