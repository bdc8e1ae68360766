//! The loop's clock ([`Clock`]) and the real one, `CLOCK_MONOTONIC` ([`MonotonicClock`]).

use std::time::Duration;

/// A monotonic clock in microseconds that can sleep.
pub trait Clock {
    /// Microseconds since an arbitrary, fixed epoch; never decreases.
    fn now_micros(&self) -> u64;

    /// Returns when [`now_micros`](Self::now_micros) is at least `deadline_us` (at once if it
    /// already is).
    fn sleep_until(&self, deadline_us: u64);
}

/// The most a [`MonotonicClock`] spins before a deadline, µs: ten periods of a 1 kHz loop.
/// More would spin through whole periods (the command lines refuse it where they parse it).
pub const MAX_SPIN_US: u64 = 10_000;

/// `CLOCK_MONOTONIC` through [`std::time::Instant`], with an optional busy-wait before each
/// deadline.
///
/// A plain sleep wakes up late by the kernel's timer slack (50 µs by default for normal
/// threads) plus the scheduling latency. With `spin_us > 0` the clock sleeps until
/// `spin_us` before the deadline and spins for the rest, which trades CPU time for a lower
/// lateness.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    epoch: std::time::Instant,
    spin_us: u64,
}

impl MonotonicClock {
    /// A clock whose epoch is now; `spin_us` as in the type's documentation (0: no spinning).
    #[must_use]
    pub fn new(spin_us: u64) -> Self {
        Self {
            epoch: std::time::Instant::now(),
            spin_us,
        }
    }
}

impl Clock for MonotonicClock {
    fn now_micros(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_micros()).unwrap_or(u64::MAX)
    }

    fn sleep_until(&self, deadline_us: u64) {
        // `now_micros` rounds down, so sleeping `deadline - now` never wakes up early.
        let remaining = deadline_us.saturating_sub(self.now_micros());
        if remaining > self.spin_us {
            std::thread::sleep(Duration::from_micros(remaining - self.spin_us));
        }
        while self.now_micros() < deadline_us {
            core::hint::spin_loop();
        }
    }
}
