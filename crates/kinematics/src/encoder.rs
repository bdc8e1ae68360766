//! Encoder integration: wrapping hardware counters to wheel angles and speeds.
//!
//! Drives report position as a counter of fixed width that wraps: the DJI C620 sends the rotor
//! angle as 13 bits (0..8191, one rotor turn), others 16 or 32 bits. [`Encoder`] takes each
//! raw reading, forms the *wrapping* difference to the previous one (the shortest way round
//! the counter) and accumulates it in an `i64`, so integration is exact for as long as the
//! robot runs: no float sum that drifts, no jump at the wrap.
//!
//! The wheel angle per count is `2π / (counts_per_rev · gear_ratio)`, with the sign flipped for
//! a mirrored mounting, and the speed is the angle increment over the sample interval
//! (Tlale and de Villiers, eq. 2: `θ̇ = C Δm / ΔT`). The difference is unambiguous only while the
//! counter moves less than half its range between two readings: for a 13-bit rotor angle read at 1
//! kHz that is 4096 counts per ms, 30,000 rpm of the rotor.

use crate::error::EncoderError;
use crate::real::Real;

/// How a wheel's encoder counts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderConfig<T> {
    /// Counter width in bits, 1..=32 (13 for the DJI rotor angle).
    pub bits: u8,
    /// Counts per revolution of the shaft the encoder is on (8192 for the DJI rotor angle).
    pub counts_per_rev: u32,
    /// Turns of the encoder's shaft per turn of the wheel (3591/187 for the M3508 gearbox; 1
    /// for an encoder on the wheel).
    pub gear_ratio: T,
    /// `true` if a positive count rolls the robot backward (a mirrored right-hand motor).
    pub inverted: bool,
}

impl<T: Real> EncoderConfig<T> {
    /// The DJI M3508 with C620: 13-bit rotor angle, 8192 counts per rotor turn, 3591/187 gear.
    #[must_use]
    pub fn dji_m3508(inverted: bool) -> Self {
        Self {
            bits: 13,
            counts_per_rev: 8192,
            gear_ratio: T::lit(3591.0 / 187.0),
            inverted,
        }
    }

    /// The DJI M2006 with C610: 13-bit rotor angle, 8192 counts per rotor turn, 36:1 gear.
    #[must_use]
    pub fn dji_m2006(inverted: bool) -> Self {
        Self {
            bits: 13,
            counts_per_rev: 8192,
            gear_ratio: T::lit(36.0),
            inverted,
        }
    }

    /// Wheel angle per count, rad, signed by the mounting.
    ///
    /// # Errors
    /// [`EncoderError`] naming the field that is out of range.
    pub fn radians_per_count(&self) -> Result<T, EncoderError> {
        if !(1..=32).contains(&self.bits) {
            return Err(EncoderError::Bits { bits: self.bits });
        }
        if self.counts_per_rev == 0 {
            return Err(EncoderError::CountsPerRev {
                counts_per_rev: self.counts_per_rev,
            });
        }
        if !(self.gear_ratio.finite() && self.gear_ratio > T::zero()) {
            return Err(EncoderError::GearRatio {
                gear_ratio: self.gear_ratio.to_f64(),
            });
        }
        let k = T::two_pi() / (T::lit(f64::from(self.counts_per_rev)) * self.gear_ratio);
        Ok(if self.inverted { -k } else { k })
    }
}

/// One wheel's counter integrator. Exact over any number of wraps (the sum is an `i64` of
/// counts); the first reading after construction or [`reset`](Self::reset) only sets the
/// reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Encoder<T> {
    radians_per_count: T,
    /// `2^bits - 1`.
    mask: u32,
    last: Option<u32>,
    total: i64,
}

impl<T: Real> Encoder<T> {
    /// An integrator for the given configuration, at angle zero.
    ///
    /// # Errors
    /// [`EncoderError`] naming the field that is out of range.
    pub fn new(config: &EncoderConfig<T>) -> Result<Self, EncoderError> {
        let radians_per_count = config.radians_per_count()?;
        Ok(Self {
            radians_per_count,
            mask: u32::MAX >> (32 - u32::from(config.bits)),
            last: None,
            total: 0,
        })
    }

    /// Takes a raw counter reading and returns the wrapped increment in counts since the
    /// previous one (0 for the first), before the mounting sign.
    ///
    /// # Errors
    /// [`EncoderError::RawOutOfRange`] if `raw` does not fit the counter width; the state is
    /// left unchanged.
    pub fn update(&mut self, raw: u32) -> Result<i64, EncoderError> {
        if raw > self.mask {
            return Err(EncoderError::RawOutOfRange {
                raw,
                max: self.mask,
            });
        }
        let delta = match self.last {
            None => 0,
            Some(last) => wrapping_delta(raw, last, self.mask),
        };
        self.last = Some(raw);
        self.total += delta;
        Ok(delta)
    }

    /// Wheel angle increment for a count increment, rad (mounting sign applied).
    ///
    /// The count is converted exactly for `|counts| <= 2^24` in `f32` and `2^53` in `f64`;
    /// larger counts are rounded to `T` first (one rounding, relative error below `ε / 2`).
    /// [`total_counts`](Self::total_counts) itself stays exact.
    #[must_use]
    #[inline]
    pub fn counts_to_radians(&self, counts: i64) -> T {
        // `counts` is exact in T up to the width of its significand: |counts| <= 2^24 in f32
        // (enough for any increment, and 16.7 million counts of total angle: 2048 turns of
        // a 13-bit rotor counter), 2^53 in f64. Beyond that it is rounded to the nearest
        // representable count (relative error below 6e-8 in f32).
        #[allow(clippy::cast_precision_loss)]
        let c = counts as f64;
        T::lit(c) * self.radians_per_count
    }

    /// Wheel speed from a count increment over `dt` seconds, rad/s (Tlale and de Villiers, eq. 2).
    #[must_use]
    #[inline]
    pub fn speed(&self, counts: i64, dt: T) -> T {
        self.counts_to_radians(counts) / dt
    }

    /// Counts accumulated since construction or the last reset (unwrapped, before the sign).
    #[must_use]
    pub const fn total_counts(&self) -> i64 {
        self.total
    }

    /// Wheel angle accumulated since construction or the last reset, rad.
    #[must_use]
    pub fn angle(&self) -> T {
        self.counts_to_radians(self.total)
    }

    /// The last raw reading, if any.
    #[must_use]
    pub const fn last_raw(&self) -> Option<u32> {
        self.last
    }

    /// Zeroes the accumulated angle and forgets the reference reading.
    pub fn reset(&mut self) {
        self.last = None;
        self.total = 0;
    }
}

/// `raw - last` on a counter of `mask + 1` values, as the signed value of smallest magnitude
/// (`[-2^(bits-1), 2^(bits-1))`).
#[inline]
fn wrapping_delta(raw: u32, last: u32, mask: u32) -> i64 {
    let modulus = u64::from(mask) + 1;
    let d = u64::from(raw.wrapping_sub(last) & mask);
    // Both fit in i64 (at most 2^32).
    let (d, m) = (d.cast_signed(), modulus.cast_signed());
    if d >= m / 2 { d - m } else { d }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrapping_delta_takes_the_short_way() {
        let m13 = (1 << 13) - 1;
        assert_eq!(wrapping_delta(5, 8190, m13), 7);
        assert_eq!(wrapping_delta(8190, 5, m13), -7);
        assert_eq!(wrapping_delta(4096, 0, m13), -4096);
        assert_eq!(wrapping_delta(4095, 0, m13), 4095);
        assert_eq!(wrapping_delta(1, u32::MAX, u32::MAX), 2);
        assert_eq!(wrapping_delta(u32::MAX, 1, u32::MAX), -2);
        assert_eq!(wrapping_delta(0, 1, 1), -1);
    }

    #[test]
    fn bad_config_names_the_field() {
        let mut c = EncoderConfig::<f64>::dji_m3508(false);
        c.bits = 33;
        assert_eq!(Encoder::new(&c), Err(EncoderError::Bits { bits: 33 }));
        c.bits = 0;
        assert_eq!(Encoder::new(&c), Err(EncoderError::Bits { bits: 0 }));
        c.bits = 13;
        c.counts_per_rev = 0;
        assert!(matches!(
            Encoder::new(&c),
            Err(EncoderError::CountsPerRev { counts_per_rev: 0 })
        ));
        c.counts_per_rev = 8192;
        c.gear_ratio = f64::NAN;
        assert!(matches!(
            Encoder::new(&c),
            Err(EncoderError::GearRatio { .. })
        ));
        c.gear_ratio = -1.0;
        assert!(matches!(
            Encoder::new(&c),
            Err(EncoderError::GearRatio { .. })
        ));
    }

    #[test]
    fn out_of_range_reading_is_refused_and_changes_nothing() {
        let mut e = Encoder::new(&EncoderConfig::<f32>::dji_m3508(false)).unwrap();
        assert_eq!(e.update(100), Ok(0));
        assert_eq!(
            e.update(8192),
            Err(EncoderError::RawOutOfRange {
                raw: 8192,
                max: 8191
            })
        );
        assert_eq!(e.last_raw(), Some(100));
        assert_eq!(e.update(110), Ok(10));
        assert_eq!(e.total_counts(), 10);
    }
}
