//! Pacing a simulation to the wall clock, for live viewers.

use std::time::{Duration, Instant};

/// Keeps a simulation's time on the wall clock: [`pace`](Self::pace) sleeps until
/// `start + simulated time / rate`, and records how late each step found the wall clock
/// (after the sleep: the sleep's overshoot; without one: how far behind the simulation is).
/// The simulation never runs ahead of `rate` × real time; one that falls behind (a loaded
/// machine) catches up as fast as it can, without re-anchoring, so simulated time keeps
/// tracking wall time.
#[derive(Debug, Clone)]
pub struct Pacer {
    start: Instant,
    rate: f64,
    /// Lateness of every paced step, µs (a 60 s run at 1 kHz: 240 kB).
    late_us: Vec<u32>,
}

/// How closely a [`Pacer`] kept simulated time on the wall clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PacingReport {
    /// Steps paced.
    pub steps: usize,
    /// Simulated seconds per wall-clock second asked for.
    pub rate: f64,
    /// Lateness of the wall clock against `start + simulated / rate` at a step, s: the mean,
    /// the 99th percentile and the largest.
    pub mean_late_s: f64,
    /// 99th percentile of the lateness, s.
    pub p99_late_s: f64,
    /// Largest lateness, s.
    pub max_late_s: f64,
}

impl std::fmt::Display for PacingReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "paced at {}x real time: {} steps, behind the wall clock by {:.3} ms on average, \
             {:.3} ms at the 99th percentile, {:.3} ms at most",
            self.rate,
            self.steps,
            self.mean_late_s * 1e3,
            self.p99_late_s * 1e3,
            self.max_late_s * 1e3
        )
    }
}

impl Pacer {
    /// A pacer whose simulated time 0 is now; `rate` simulated seconds per wall-clock second.
    ///
    /// # Panics
    /// If `rate` is outside [`Pacer::RATES`]: see [`Pacer::check_rate`] for the command line.
    #[must_use]
    pub fn new(rate: f64) -> Self {
        assert!(Self::check_rate(rate).is_ok(), "rate {rate}");
        Self {
            start: Instant::now(),
            rate,
            late_us: Vec::new(),
        }
    }

    /// The slowest and fastest rates, simulated seconds per wall-clock second: at the slowest
    /// a 1 ms control step takes a second of wall time; the fastest is beyond what a run
    /// keeps up with (it then runs as fast as it can). Outside them a run would never end or
    /// wait longer than `Duration` holds.
    pub const RATES: std::ops::RangeInclusive<f64> = 0.001..=1000.0;

    /// Whether `rate` can pace (in [`RATES`](Self::RATES)); the error says what is expected.
    ///
    /// # Errors
    /// The message for a refused rate.
    pub fn check_rate(rate: f64) -> Result<f64, String> {
        if Self::RATES.contains(&rate) {
            Ok(rate)
        } else {
            Err(format!(
                "{rate:?}: expected {} to {} simulated seconds per second (1 = real time)",
                Self::RATES.start(),
                Self::RATES.end()
            ))
        }
    }

    /// Waits until the wall clock reaches simulated time `sim_ns`.
    pub fn pace(&mut self, sim_ns: u64) {
        let target = self.start + Duration::from_secs_f64(sim_ns as f64 * 1e-9 / self.rate);
        let mut now = Instant::now();
        if now < target {
            std::thread::sleep(target - now);
            now = Instant::now();
        }
        let late = now.saturating_duration_since(target);
        self.late_us
            .push(u32::try_from(late.as_micros()).unwrap_or(u32::MAX));
    }

    /// The figures so far.
    #[must_use]
    pub fn report(&self) -> PacingReport {
        let mut sorted = self.late_us.clone();
        sorted.sort_unstable();
        let n = sorted.len();
        let at = |q: f64| {
            if n == 0 {
                0.0
            } else {
                let i = ((n as f64 * q).ceil() as usize).clamp(1, n) - 1;
                f64::from(sorted[i]) * 1e-6
            }
        };
        let sum: f64 = sorted.iter().map(|&u| f64::from(u)).sum();
        PacingReport {
            steps: n,
            rate: self.rate,
            mean_late_s: if n == 0 { 0.0 } else { sum / n as f64 * 1e-6 },
            p99_late_s: at(0.99),
            max_late_s: at(1.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simulated_time_follows_the_wall_clock_at_the_rate() {
        let wall = Instant::now();
        let mut pacer = Pacer::new(4.0);
        // 200 ms simulated in 1 ms steps at 4x: 50 ms of wall-clock time.
        for step in 0..=200u64 {
            pacer.pace(step * 1_000_000);
        }
        let took = wall.elapsed();
        assert!(took >= Duration::from_millis(50), "{took:?}");
        assert!(took < Duration::from_millis(150), "{took:?}");
        let report = pacer.report();
        assert_eq!(report.steps, 201);
        assert!(report.max_late_s < 0.1, "{report}");
        assert!(report.mean_late_s <= report.p99_late_s);
        assert!(report.p99_late_s <= report.max_late_s);
    }

    #[test]
    fn a_simulation_behind_the_clock_does_not_sleep_and_counts_how_late() {
        let mut pacer = Pacer::new(1.0);
        std::thread::sleep(Duration::from_millis(20));
        let before = Instant::now();
        pacer.pace(0);
        assert!(before.elapsed() < Duration::from_millis(5));
        assert!(pacer.report().max_late_s >= 0.019, "{}", pacer.report());
    }

    #[test]
    fn rates_are_those_a_run_can_keep() {
        for good in [0.001, 0.5, 1.0, 1000.0] {
            assert_eq!(Pacer::check_rate(good), Ok(good));
        }
        // 1e-300 made `Duration::from_secs_f64` panic; 1e-9 slept 11 days a step.
        for bad in [
            0.0,
            -1.0,
            1e-300,
            1e-9,
            0.000_999,
            1000.1,
            f64::NAN,
            f64::INFINITY,
        ] {
            let err = Pacer::check_rate(bad).unwrap_err();
            assert!(err.contains("expected 0.001 to 1000"), "{err}");
        }
    }
}
