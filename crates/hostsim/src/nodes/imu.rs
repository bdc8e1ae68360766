//! The simulated IMU node: a gyro on the chassis that sends its yaw rate (`IMU_YAW_RATE`,
//! the robot protocol's optional frame) on the bus.
//!
//! At every sample time `k / rate_hz` (k = 1, 2, ...) the node reads the plant's true yaw rate
//! at that instant and sends
//!
//! ```text
//! yaw_rate = wz_true + bias + σ · n_k,      σ = noise_density · √rate_hz
//! ```
//!
//! with `n_k` independent standard normal numbers (white rate noise: its integral, the
//! heading, random-walks by `noise_density · √t`), the bias constant, and `seq` counting up
//! from 0 (mod 256). Units as on datasheets: the bias in °/s, the noise density in °/s/√Hz;
//! the frame carries rad/s, counter-clockwise positive, saturated at the protocol's ±35 rad/s.
//!
//! The noise comes from a SplitMix64 generator seeded from the scenario's seed (through
//! [`imu_seed`], so that it does not repeat the bus's fault draws) and Box–Muller with `libm`:
//! the same seed gives the same frames, bit for bit, on every machine.
//!
//! [`WithImu`] puts the node beside any [`SimPlant`] ([`crate::nodes::sensor::WithNode`]: the plant
//! advanced to each sample instant, the frames sent as the bus node [`Node::Imu`]). Without
//! an IMU it only passes every call through, so a run without one is what it was before the
//! IMU existed.

use firmware::CanFrame;
use firmware::protocol::robot::{Command, ImuYawRate};
use serde::Deserialize;

use crate::bus::{Node, SplitMix64};
use crate::nodes::SimPlant;
use crate::nodes::sensor::{SensorNode, WithNode};

/// The IMU of a scenario (its `[imu]` table).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImuParams {
    /// Whether the node is on the bus (default `true` when the table is there; a scenario
    /// without an `[imu]` table has no IMU).
    pub enabled: bool,
    /// Frames per second, Hz (default 200). In `(0, 2000]`.
    pub rate_hz: f64,
    /// Constant gyro bias, °/s (default 0.1, a common MEMS figure: 6° of heading a minute
    /// if nothing removes it). In `[-100, 100]`.
    pub bias_deg_s: f64,
    /// White rate noise density, °/s/√Hz (default 0.005; datasheets give 0.002-0.015). Each
    /// sample's noise has the standard deviation `noise_density · √rate_hz`. In `[0, 10]`.
    pub noise_density: f64,
}

impl Default for ImuParams {
    fn default() -> Self {
        Self {
            enabled: true,
            rate_hz: 200.0,
            bias_deg_s: 0.1,
            noise_density: 0.005,
        }
    }
}

impl ImuParams {
    /// The first value out of range: `(key, value, what is expected)`.
    #[must_use]
    pub fn invalid(&self) -> Option<(&'static str, f64, &'static str)> {
        let in_range = |v: f64, lo: f64, hi: f64| v.is_finite() && lo <= v && v <= hi;
        if !(in_range(self.rate_hz, 0.0, 2000.0) && self.rate_hz > 0.0) {
            return Some(("rate_hz", self.rate_hz, "a rate in (0, 2000] Hz"));
        }
        if !in_range(self.bias_deg_s, -100.0, 100.0) {
            return Some(("bias_deg_s", self.bias_deg_s, "a bias in [-100, 100] °/s"));
        }
        if !in_range(self.noise_density, 0.0, 10.0) {
            return Some((
                "noise_density",
                self.noise_density,
                "a rate noise density in [0, 10] °/s/√Hz",
            ));
        }
        None
    }

    /// The standard deviation of one sample's noise, °/s.
    #[must_use]
    pub fn sample_std_deg_s(&self) -> f64 {
        self.noise_density * self.rate_hz.sqrt()
    }
}

/// The IMU's generator seed for a scenario seed: the seed through one SplitMix64 step with
/// a constant of its own, so the IMU's noise and the bus's faults are independent draws.
#[must_use]
pub fn imu_seed(scenario_seed: u64) -> u64 {
    let mut r = SplitMix64(scenario_seed ^ 0x494D_555F_5941_5752); // "IMU_YAWR"
    r.next_u64()
}

/// The IMU node: its schedule, counter, generator and the frames not yet collected.
#[derive(Debug, Clone)]
pub struct ImuNode {
    params: ImuParams,
    bias_rad_s: f64,
    std_rad_s: f64,
    /// Sample `k` is due at `round(k · 1e9 / rate_hz)` ns.
    k: u64,
    next_ns: u64,
    seq: u8,
    rng: SplitMix64,
    queue: Vec<(u64, CanFrame)>,
}

impl ImuNode {
    /// A node with `params` (validated: see [`ImuParams::invalid`]) and generator seed `seed`
    /// ([`imu_seed`] of a scenario's seed).
    #[must_use]
    pub fn new(params: ImuParams, seed: u64) -> Self {
        let mut node = Self {
            params,
            bias_rad_s: params.bias_deg_s.to_radians(),
            std_rad_s: params.sample_std_deg_s().to_radians(),
            k: 0,
            next_ns: 0,
            seq: 0,
            rng: SplitMix64(seed),
            queue: Vec::new(),
        };
        node.schedule_next();
        node
    }

    /// The parameters.
    #[must_use]
    pub const fn params(&self) -> &ImuParams {
        &self.params
    }

    /// When the next sample is due, ns.
    #[must_use]
    pub const fn next_ns(&self) -> u64 {
        self.next_ns
    }

    fn schedule_next(&mut self) {
        self.k += 1;
        self.next_ns = crate::nodes::plant::round(self.k as f64 * 1e9 / self.params.rate_hz) as u64;
    }

    /// Takes the sample due now (`now_ns` = [`Self::next_ns`]) of the true yaw rate
    /// `wz_true` (rad/s), queues its frame and schedules the next.
    pub fn sample(&mut self, now_ns: u64, wz_true: f64) {
        let noise = if self.std_rad_s > 0.0 {
            self.std_rad_s * self.rng.normal()
        } else {
            0.0
        };
        let measured = wz_true + self.bias_rad_s + noise;
        let frame = Command::ImuYawRate(ImuYawRate {
            // The codec saturates at the protocol's ±35 rad/s.
            yaw_rate: measured as f32,
            seq: self.seq,
        })
        .to_can_frame();
        self.seq = self.seq.wrapping_add(1);
        self.queue.push((now_ns, frame));
        self.schedule_next();
    }

    /// Moves the frames sent up to `until_ns` into `out`, in time order.
    pub fn drain(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        let n = self.queue.partition_point(|(t, _)| *t <= until_ns);
        out.extend(self.queue.drain(..n));
    }
}

/// A plant with an IMU node on it (see the [module documentation](self)).
pub type WithImu<'a, P> = WithNode<'a, P, ImuNode>;

impl<'a, P: SimPlant> WithNode<'a, P, ImuNode> {
    /// `plant` with an IMU of `params` (none if `None` or not enabled), seeded with
    /// [`imu_seed`]`(seed)`. The plant must be at time 0.
    pub fn new(plant: &'a mut P, params: Option<&ImuParams>, seed: u64) -> Self {
        let node = params
            .filter(|p| p.enabled)
            .map(|p| ImuNode::new(*p, imu_seed(seed)));
        Self::with(plant, node)
    }

    /// The IMU node, if there is one.
    #[must_use]
    pub const fn imu(&self) -> Option<&ImuNode> {
        self.node()
    }
}

impl SensorNode for ImuNode {
    const NODE: Node = Node::Imu;

    fn next_ns(&self) -> u64 {
        self.next_ns
    }

    fn measure<P: SimPlant + ?Sized>(&mut self, at_ns: u64, plant: &P) {
        self.sample(at_ns, plant.truth_velocity()[2]);
    }

    fn drain(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        ImuNode::drain(self, until_ns, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nodes::test_plant::Moving;

    fn frames(params: ImuParams, seed: u64, ms: u64) -> Vec<(u64, f32, u8)> {
        let mut plant = Moving::new([0.0, 0.0, 0.5]);
        let mut imu = WithImu::new(&mut plant, Some(&params), seed);
        let mut out = Vec::new();
        for _ in 0..ms {
            imu.advance_ns(1_000_000);
            imu.node_frames(Node::Imu, u64::MAX, &mut out);
        }
        out.iter()
            .map(|(t, f)| match Command::decode(f) {
                Ok(Command::ImuYawRate(g)) => (*t, g.yaw_rate, g.seq),
                other => panic!("{other:?}"),
            })
            .collect()
    }

    #[test]
    fn samples_at_the_rate_with_the_bias_and_the_noise_of_the_density() {
        let p = ImuParams::default();
        let f = frames(p, 7, 20_000);
        // 200 Hz: one frame every 5 ms from 5 ms on, seq counting and wrapping.
        assert_eq!(f.len(), 4000);
        assert!(
            f.iter()
                .enumerate()
                .all(|(i, x)| x.0 == (i as u64 + 1) * 5_000_000)
        );
        assert!(f.iter().enumerate().all(|(i, x)| x.2 == i as u8));
        let n = f.len() as f64;
        let mean = f.iter().map(|x| f64::from(x.1)).sum::<f64>() / n;
        let std = (f
            .iter()
            .map(|x| (f64::from(x.1) - mean).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        let bias = 0.1f64.to_radians();
        let sigma = (0.005 * 200f64.sqrt()).to_radians();
        // The mean of 4000 samples is within 4 standard errors of 0.5 rad/s + the bias.
        assert!(
            (mean - 0.5 - bias).abs() < 4.0 * sigma / n.sqrt(),
            "mean {mean}"
        );
        assert!((std / sigma - 1.0).abs() < 0.05, "std {std}, want {sigma}");
    }

    #[test]
    fn the_same_seed_gives_the_same_frames_and_another_seed_others() {
        let p = ImuParams::default();
        let (a, b, c) = (frames(p, 1, 500), frames(p, 1, 500), frames(p, 2, 500));
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Without noise the seed does not matter: the true rate plus the bias, exactly.
        let quiet = ImuParams {
            noise_density: 0.0,
            ..p
        };
        let q = frames(quiet, 3, 50);
        assert!(q.iter().all(|x| x.1 == (0.5 + 0.1f64.to_radians()) as f32));
        assert_eq!(q, frames(quiet, 4, 50));
    }

    #[test]
    fn a_rate_that_does_not_divide_a_millisecond_keeps_its_schedule() {
        let p = ImuParams {
            rate_hz: 300.0,
            ..ImuParams::default()
        };
        let f = frames(p, 1, 1000);
        assert_eq!(f.len(), 300);
        assert_eq!(f[0].0, 3_333_333);
        assert_eq!(f[1].0, 6_666_667);
        assert_eq!(f[299].0, 1_000_000_000);
    }

    #[test]
    fn without_an_imu_every_call_passes_through() {
        let mut plant = Moving::new([0.0, 0.0, 0.5]);
        let off = ImuParams {
            enabled: false,
            ..ImuParams::default()
        };
        let mut imu = WithImu::new(&mut plant, Some(&off), 1);
        assert!(imu.imu().is_none());
        imu.advance(0.0015);
        assert_eq!(imu.next_feedback_ns(), u64::MAX);
        let mut out = Vec::new();
        imu.node_frames(Node::Imu, u64::MAX, &mut out);
        assert!(out.is_empty());
        assert_eq!(plant.now_ns, 1_500_000);
    }

    #[test]
    fn out_of_range_parameters_are_named() {
        for (p, key) in [
            (
                ImuParams {
                    rate_hz: 0.0,
                    ..ImuParams::default()
                },
                "rate_hz",
            ),
            (
                ImuParams {
                    bias_deg_s: f64::NAN,
                    ..ImuParams::default()
                },
                "bias_deg_s",
            ),
            (
                ImuParams {
                    noise_density: -1.0,
                    ..ImuParams::default()
                },
                "noise_density",
            ),
        ] {
            assert_eq!(p.invalid().map(|x| x.0), Some(key));
        }
        assert_eq!(ImuParams::default().invalid(), None);
    }
}
