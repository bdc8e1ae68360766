//! The simulated tracking-pod node: unpowered omni wheels with encoders rolling on the floor
//! under the chassis, whose counts it sends as `POD_COUNTS` (the robot protocol's optional
//! frame, version 7).
//!
//! The robot believes in the pods of its configuration (`[[odometry.pods]]`); the true pods
//! differ by the scenario's errors (`[[pods.pod]]`: radius, direction, contact point). A pod
//! does not slip along its rolling direction, so its wheel angle is the true contact point's
//! travel along the true direction, over the true radius:
//!
//! ```text
//! angle = (cos φ (T_x − y T_ω) + sin φ (T_y + x T_ω) + noise) / r,    T = ∫(vx, vy, ω) dt
//! count = floor(angle / 2π · counts_per_turn) mod 65536
//! ```
//!
//! `T` is the chassis's own integral ([`Chassis::body_travel`](crate::nodes::plant::Chassis::body_travel)),
//! exact in every substep the pose is integrated with, not only at the frames; `noise` is
//! white noise on the travel rate of density `noise` (m/s/√Hz: the travel random-walks by
//! `noise · √t`), one independent draw per pod and sample, from a SplitMix64 generator
//! seeded through [`pods_seed`] and Box–Muller with `libm`: the same seed gives the same
//! frames, bit for bit, on every machine. At every `k / rate_hz` (k = 1, 2, ...) the node
//! sends the counts with `seq` counting up from 0 (mod 256), unless a `pods_silent` fault
//! holds it (the counts and `seq` go on; nothing is sent). [`WithPods`] puts it beside any
//! [`SimPlant`] ([`crate::nodes::sensor::WithNode`]) and hands its frames to the runner
//! ([`SimPlant::node_frames`], the bus node
//! [`Node::Pods`]); without pods it only passes every call through.

use firmware::CanFrame;
use firmware::config::{PODS_MAX, PodConfig};
use firmware::protocol::robot::{Command, PodCounts};
use serde::Deserialize;

use crate::bus::{Node, SplitMix64};
use crate::nodes::SimPlant;
use crate::nodes::sensor::{SensorNode, WithNode};

/// The pod node of a scenario (its `[pods]` table). The pods themselves are the robot
/// configuration's (`[[odometry.pods]]`); this says how the true ones differ.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PodsParams {
    /// Frames per second, Hz (default 200). In `(0, 2000]`.
    pub rate_hz: f64,
    /// White noise on each pod's measured travel rate, m/s/√Hz (default 0): each pod's
    /// travel random-walks by `noise · √t` m. In `[0, 1]`.
    pub noise: f64,
    /// An error of every pod's scale, added to each pod's own (a batch of wheels, a worn
    /// tread): true radius = nominal × (1 + `radius_error` + the pod's). In `[-0.5, 0.5]`.
    pub radius_error: f64,
    /// A turn of the whole pod block, degrees counter-clockwise, added to each pod's own
    /// misalignment. In `[-180, 180]`.
    pub misalignment_deg: f64,
    /// The true pods' own errors (`[[pods.pod]]`), in the configuration's order; pods
    /// without an entry have only the block's.
    pub pod: Vec<PodErrors>,
}

impl Default for PodsParams {
    fn default() -> Self {
        Self {
            rate_hz: 200.0,
            noise: 0.0,
            radius_error: 0.0,
            misalignment_deg: 0.0,
            pod: Vec::new(),
        }
    }
}

/// How one true pod differs from its configuration (a `[[pods.pod]]` table: its own errors,
/// beside the block's in `[pods]`; [`PodsParams::errors`] adds them). All default 0.
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PodErrors {
    /// True radius = nominal × (1 + `radius_error`). In `[-0.5, 0.5]`, and with the block's.
    pub radius_error: f64,
    /// True direction = nominal + this, degrees counter-clockwise. In `[-180, 180]`, and
    /// with the block's.
    pub misalignment_deg: f64,
    /// True contact point less the nominal, forward, m. In `[-1, 1]`.
    pub offset_x: f64,
    /// True contact point less the nominal, leftward, m. In `[-1, 1]`.
    pub offset_y: f64,
}

impl PodsParams {
    /// The first value out of range: `(key under [pods], value, what is expected)`; a pod's
    /// key is `pod[i].<field>`.
    #[must_use]
    pub fn invalid(&self) -> Option<(String, f64, &'static str)> {
        let in_range = |v: f64, lo: f64, hi: f64| v.is_finite() && lo <= v && v <= hi;
        if !(in_range(self.rate_hz, 0.0, 2000.0) && self.rate_hz > 0.0) {
            return Some(("rate_hz".into(), self.rate_hz, "a rate in (0, 2000] Hz"));
        }
        if !in_range(self.noise, 0.0, 1.0) {
            return Some((
                "noise".into(),
                self.noise,
                "a travel-rate noise density in [0, 1] m/s/√Hz",
            ));
        }
        for (field, value, lo, hi, expected) in [
            ("radius_error", self.radius_error, -0.5, 0.5, RADIUS_ERROR),
            (
                "misalignment_deg",
                self.misalignment_deg,
                -180.0,
                180.0,
                MISALIGNMENT,
            ),
        ] {
            if !in_range(value, lo, hi) {
                return Some((field.into(), value, expected));
            }
        }
        for (i, own) in self.pod.iter().enumerate() {
            let e = self.errors(i);
            for (field, value, lo, hi, expected) in [
                ("radius_error", own.radius_error, -0.5, 0.5, RADIUS_ERROR),
                (
                    "misalignment_deg",
                    own.misalignment_deg,
                    -180.0,
                    180.0,
                    MISALIGNMENT,
                ),
                (
                    "radius_error",
                    e.radius_error,
                    -0.5,
                    0.5,
                    "with the block's radius_error, a fraction in [-0.5, 0.5]",
                ),
                (
                    "misalignment_deg",
                    e.misalignment_deg,
                    -180.0,
                    180.0,
                    "with the block's misalignment_deg, an angle in [-180, 180] °",
                ),
                ("offset_x", e.offset_x, -1.0, 1.0, "an offset in [-1, 1] m"),
                ("offset_y", e.offset_y, -1.0, 1.0, "an offset in [-1, 1] m"),
            ] {
                if !in_range(value, lo, hi) {
                    return Some((format!("pod[{i}].{field}"), value, expected));
                }
            }
        }
        None
    }

    /// Pod `i`'s errors in all: its own (`[[pods.pod]]`, none if it has no entry) and the
    /// block's.
    #[must_use]
    pub fn errors(&self, i: usize) -> PodErrors {
        let own = self.pod.get(i).copied().unwrap_or_default();
        PodErrors {
            radius_error: self.radius_error + own.radius_error,
            misalignment_deg: self.misalignment_deg + own.misalignment_deg,
            ..own
        }
    }

    /// The standard deviation of the noise one sample adds to each pod's travel, m:
    /// `noise / √rate_hz` (the travel-rate noise integrated over one sample period).
    #[must_use]
    pub fn sample_std_m(&self) -> f64 {
        self.noise / libm::sqrt(self.rate_hz)
    }
}

const RADIUS_ERROR: &str = "a fraction in [-0.5, 0.5] (true radius = nominal × (1 + radius_error))";
const MISALIGNMENT: &str = "an angle in [-180, 180] °";

/// The pods' generator seed for a scenario seed: the seed through one SplitMix64 step with a
/// constant of its own, so the pods' noise, the IMU's and the bus's faults are independent
/// draws.
#[must_use]
pub fn pods_seed(scenario_seed: u64) -> u64 {
    let mut r = SplitMix64(scenario_seed ^ 0x504F_445F_434E_5453); // "POD_CNTS"
    r.next_u64()
}

/// One true pod: where it touches the floor, which way it counts up, its wheel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruePod {
    /// Contact point, forward, m.
    pub x: f64,
    /// Contact point, leftward, m.
    pub y: f64,
    /// Direction in which it counts up, rad counter-clockwise from the body's x axis.
    pub direction: f64,
    /// Wheel radius, m.
    pub radius: f64,
    /// Encoder counts per wheel turn.
    pub counts_per_turn: u32,
    /// `(cos φ, sin φ, x sin φ − y cos φ)`: the travel's coefficients on `(vx, vy, ω)`.
    coefficients: [f64; 3],
}

impl TruePod {
    /// The true pod of the configured `nominal` with the errors `e`.
    #[must_use]
    pub fn new(nominal: &PodConfig, e: &PodErrors) -> Self {
        let x = f64::from(nominal.x) + e.offset_x;
        let y = f64::from(nominal.y) + e.offset_y;
        let direction = (f64::from(nominal.direction_deg) + e.misalignment_deg).to_radians();
        let (s, c) = libm::sincos(direction);
        Self {
            x,
            y,
            direction,
            radius: f64::from(nominal.radius) * (1.0 + e.radius_error),
            counts_per_turn: nominal.counts_per_turn,
            coefficients: [c, s, x * s - y * c],
        }
    }

    /// The travel rate of the contact point along the pod's direction for the body
    /// velocity `[vx, vy, ω]`, m/s: `cos φ (vx − ω y) + sin φ (vy + ω x)`.
    #[must_use]
    pub fn travel_rate(&self, v: [f64; 3]) -> f64 {
        let [a, b, k] = self.coefficients;
        a * v[0] + b * v[1] + k * v[2]
    }

    /// The count of the wheel having rolled `travel` metres: the encoder's
    /// `floor(travel / (2π r) · counts_per_turn)`, wrapped to 16 bits.
    #[must_use]
    pub fn count(&self, travel: f64) -> u16 {
        let turns = travel / (std::f64::consts::TAU * self.radius);
        let edges = libm::floor(turns * f64::from(self.counts_per_turn));
        // Far inside i64 for any run (a day at 10 m/s on a 1 cm wheel at 10⁶ counts a turn
        // is 1.4e13); the low 16 bits are the count modulo 65536, negatives included.
        edges as i64 as u16
    }
}

/// The pod node: the true pods, its schedule, counter, generator, silences and the frames
/// not yet collected.
#[derive(Debug, Clone)]
pub struct PodNode {
    rate_hz: f64,
    pods: Vec<TruePod>,
    std_m: f64,
    /// Each pod's accumulated noise, m.
    noise_m: Vec<f64>,
    /// Sample `k` is due at `round(k · 1e9 / rate_hz)` ns.
    k: u64,
    next_ns: u64,
    seq: u8,
    rng: SplitMix64,
    /// `[from, until)` windows, ns, in which the node sends nothing (`pods_silent`).
    silent: Vec<(u64, u64)>,
    queue: Vec<(u64, CanFrame)>,
    /// The plant's body travel when the node was put on it ([`SimPlant::truth_travel`]).
    origin: [f64; 3],
    /// For a plant that does not integrate its travel: `truth_velocity` at the end of each
    /// advance times its length.
    own_travel: [f64; 3],
}

impl PodNode {
    /// A node with the configured pods `nominal` (at most [`PODS_MAX`]; more are ignored)
    /// made true by `params` (validated: see [`PodsParams::invalid`]; errors beyond the
    /// configured pods are ignored), generator seed `seed` ([`pods_seed`] of a scenario's
    /// seed).
    #[must_use]
    pub fn new(params: &PodsParams, nominal: &[PodConfig], seed: u64) -> Self {
        let pods: Vec<TruePod> = nominal
            .iter()
            .take(PODS_MAX)
            .enumerate()
            .map(|(i, p)| TruePod::new(p, &params.errors(i)))
            .collect();
        let mut node = Self {
            rate_hz: params.rate_hz,
            noise_m: vec![0.0; pods.len()],
            pods,
            std_m: params.sample_std_m(),
            k: 0,
            next_ns: 0,
            seq: 0,
            rng: SplitMix64(seed),
            silent: Vec::new(),
            queue: Vec::new(),
            origin: [0.0; 3],
            own_travel: [0.0; 3],
        };
        node.schedule_next();
        node
    }

    /// The same node, silent in each `[from, until)` window (ns of the plant's time): it
    /// samples and counts on, and sends nothing.
    #[must_use]
    pub fn silenced(mut self, windows: impl IntoIterator<Item = (u64, u64)>) -> Self {
        self.silent.extend(windows);
        self
    }

    /// The true pods, in the configuration's order.
    #[must_use]
    pub fn pods(&self) -> &[TruePod] {
        &self.pods
    }

    /// When the next sample is due, ns.
    #[must_use]
    pub const fn next_ns(&self) -> u64 {
        self.next_ns
    }

    fn schedule_next(&mut self) {
        self.k += 1;
        self.next_ns = crate::nodes::plant::round(self.k as f64 * 1e9 / self.rate_hz) as u64;
    }

    /// Takes the sample due now (`now_ns` = [`Self::next_ns`]) of the body's travel since the
    /// start, `T = [∫vx, ∫vy, ∫ω]` (m, m, rad), queues its frame unless the node is silent
    /// now, and schedules the next.
    pub fn sample(&mut self, now_ns: u64, travel: [f64; 3]) {
        let mut counts = [0u16; PODS_MAX];
        for (i, pod) in self.pods.iter().enumerate() {
            if self.std_m > 0.0 {
                self.noise_m[i] += self.std_m * self.rng.normal();
            }
            counts[i] = pod.count(pod.travel_rate(travel) + self.noise_m[i]);
        }
        let silent = self
            .silent
            .iter()
            .any(|&(from, until)| from <= now_ns && now_ns < until);
        if !silent {
            let frame = Command::PodCounts(PodCounts {
                counts,
                seq: self.seq,
            })
            .to_can_frame();
            self.queue.push((now_ns, frame));
        }
        self.seq = self.seq.wrapping_add(1);
        self.schedule_next();
    }

    /// Moves the frames sent up to `until_ns` into `out`, in time order.
    pub fn drain(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        let n = self.queue.partition_point(|(t, _)| *t <= until_ns);
        out.extend(self.queue.drain(..n));
    }
}

/// A plant with a pod node on it (see the [module documentation](self)).
pub type WithPods<'a, P> = WithNode<'a, P, PodNode>;

impl<'a, P: SimPlant> WithNode<'a, P, PodNode> {
    /// `plant` with the pod node `node` (none: a pass-through). The plant must be at time 0.
    pub fn new(plant: &'a mut P, node: Option<PodNode>) -> Self {
        Self::with(plant, node)
    }

    /// The pod node, if there is one.
    #[must_use]
    pub const fn pods(&self) -> Option<&PodNode> {
        self.node()
    }
}

impl SensorNode for PodNode {
    const NODE: Node = Node::Pods;

    fn next_ns(&self) -> u64 {
        self.next_ns
    }

    fn start<P: SimPlant + ?Sized>(&mut self, plant: &P) {
        self.origin = plant.truth_travel().unwrap_or_default();
    }

    fn advanced<P: SimPlant + ?Sized>(&mut self, plant: &P, dt_ns: u64) {
        if plant.truth_travel().is_none() {
            let v = plant.truth_velocity();
            let dt = dt_ns as f64 * 1e-9;
            for (t, v) in self.own_travel.iter_mut().zip(v) {
                *t += v * dt;
            }
        }
    }

    fn measure<P: SimPlant + ?Sized>(&mut self, at_ns: u64, plant: &P) {
        // The body's travel since the start: the plant's own integral, else the node's.
        let travel = match plant.truth_travel() {
            Some(t) => [0, 1, 2].map(|i| t[i] - self.origin[i]),
            None => self.own_travel,
        };
        self.sample(at_ns, travel);
    }

    fn drain(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        PodNode::drain(self, until_ns, out);
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::TAU;

    use super::*;
    use crate::nodes::test_plant::Moving;

    const R: f32 = 0.024;
    const CPT: u32 = 2000;

    fn pod(x: f32, y: f32, direction_deg: f32) -> PodConfig {
        PodConfig {
            x,
            y,
            direction_deg,
            radius: R,
            counts_per_turn: CPT,
        }
    }

    /// Three pods: two forward-counting ones left and right, one leftward-counting one at
    /// the back.
    fn layout() -> [PodConfig; 3] {
        [
            pod(0.05, 0.15, 0.0),
            pod(0.05, -0.15, 0.0),
            pod(-0.12, 0.02, 90.0),
        ]
    }

    /// Every frame of `ms` milliseconds on `plant`, decoded: `(time ns, counts, seq)`.
    fn run(
        plant: &mut Moving,
        params: &PodsParams,
        pods: &[PodConfig],
        seed: u64,
        ms: u64,
    ) -> Vec<(u64, [u16; 3], u8)> {
        run_node(plant, PodNode::new(params, pods, seed), ms)
    }

    fn run_node(plant: &mut Moving, node: PodNode, ms: u64) -> Vec<(u64, [u16; 3], u8)> {
        let mut with = WithPods::new(plant, Some(node));
        let mut out = Vec::new();
        for _ in 0..ms {
            with.advance_ns(1_000_000);
            with.node_frames(Node::Pods, u64::MAX, &mut out);
        }
        out.iter()
            .map(|(t, f)| match Command::decode(f) {
                Ok(Command::PodCounts(c)) => (*t, c.counts, c.seq),
                other => panic!("{other:?}"),
            })
            .collect()
    }

    /// The counts a pod of `layout()` shows after travelling `metres` (real-valued).
    fn expected(metres: f64, radius: f64) -> f64 {
        metres / (TAU * radius) * f64::from(CPT)
    }

    /// The signed difference of a wrapped count from 0.
    fn signed(c: u16) -> f64 {
        f64::from(c as i16)
    }

    #[test]
    fn a_translation_along_a_pod_counts_its_travel_over_its_circumference() {
        let r = f64::from(R);
        for (v, pod_index, speed) in [
            ([0.3, 0.0, 0.0], 0, 0.3),
            ([0.3, 0.0, 0.0], 1, 0.3),
            ([0.0, -0.25, 0.0], 2, -0.25),
        ] {
            for integrates in [true, false] {
                let mut plant = Moving::new(v);
                plant.integrates = integrates;
                let f = run(&mut plant, &PodsParams::default(), &layout(), 1, 1000);
                let last = f.last().unwrap();
                assert_eq!(last.0, 1_000_000_000);
                let want = expected(speed * 1.0, r);
                let got = signed(last.1[pod_index]);
                assert!(
                    (got - want).abs() <= 1.0,
                    "pod {pod_index}: {got}, want {want}"
                );
            }
        }
        // 0.3 m/s for 1 s on a 24 mm wheel at 2000 counts a turn: 3978.9 counts.
        assert!((expected(0.3, f64::from(R)) - 3978.87).abs() < 0.01);
    }

    #[test]
    fn a_spin_about_the_origin_counts_omega_times_the_lever_of_each_pod() {
        let w = 0.8;
        let mut plant = Moving::new([0.0, 0.0, w]);
        let f = run(&mut plant, &PodsParams::default(), &layout(), 1, 1000);
        let last = f.last().unwrap();
        for (i, p) in layout().iter().enumerate() {
            let (x, y) = (f64::from(p.x), f64::from(p.y));
            let phi = f64::from(p.direction_deg).to_radians();
            // cos φ (vx − ω y) + sin φ (vy + ω x) with v = 0: ω (x sin φ − y cos φ).
            let rate = w * (x * phi.sin() - y * phi.cos());
            let want = expected(rate * 1.0, f64::from(R));
            let got = signed(last.1[i]);
            assert!((got - want).abs() <= 1.0, "pod {i}: {got}, want {want}");
        }
        // The left pod counts back, the right one forward, the rear one right-to-left.
        assert!(signed(last.1[0]) < -600.0 && signed(last.1[1]) > 600.0);
        assert!(signed(last.1[2]) < -600.0);
    }

    #[test]
    fn a_larger_true_radius_counts_less() {
        let mut a = Moving::new([0.5, 0.0, 0.0]);
        let mut b = Moving::new([0.5, 0.0, 0.0]);
        let big = PodsParams {
            pod: vec![PodErrors {
                radius_error: 0.01,
                ..PodErrors::default()
            }],
            ..PodsParams::default()
        };
        let nominal = run(&mut a, &PodsParams::default(), &layout(), 1, 4000);
        let larger = run(&mut b, &big, &layout(), 1, 4000);
        // 2 m: 26,526 counts as configured, 26,263 on the 1 % larger wheel.
        let (n, l) = (
            f64::from(nominal.last().unwrap().1[0]),
            f64::from(larger.last().unwrap().1[0]),
        );
        assert!((n - expected(2.0, f64::from(R))).abs() <= 1.0, "{n}");
        assert!((l - n / 1.01).abs() <= 1.0, "{l} against {n} / 1.01");
        // Only the first pod has an error.
        assert_eq!(nominal.last().unwrap().1[1], larger.last().unwrap().1[1]);
    }

    #[test]
    fn a_misaligned_pod_measures_along_its_true_direction() {
        let tilted = PodsParams {
            pod: vec![PodErrors {
                misalignment_deg: 30.0,
                ..PodErrors::default()
            }],
            ..PodsParams::default()
        };
        let r = f64::from(R);
        // Forward at 0.4 m/s: cos 30° of it; leftward: sin 30°.
        for (v, share) in [
            ([0.4, 0.0, 0.0], 30f64.to_radians().cos()),
            ([0.0, 0.4, 0.0], 30f64.to_radians().sin()),
        ] {
            let mut plant = Moving::new(v);
            let f = run(&mut plant, &tilted, &layout(), 1, 1000);
            let got = signed(f.last().unwrap().1[0]);
            let want = expected(0.4 * share, r);
            assert!((got - want).abs() <= 1.0, "{v:?}: {got}, want {want}");
        }
        // An offset contact point: a spin now moves the pod by ω · offset_y backwards.
        let offset = PodsParams {
            pod: vec![
                PodErrors::default(),
                PodErrors {
                    offset_y: 0.05,
                    ..PodErrors::default()
                },
            ],
            ..PodsParams::default()
        };
        let mut plant = Moving::new([0.0, 0.0, 1.0]);
        let f = run(&mut plant, &offset, &layout(), 1, 1000);
        let got = signed(f.last().unwrap().1[1]);
        let want = expected(-(-0.15 + 0.05), r);
        assert!((got - want).abs() <= 1.0, "{got}, want {want}");
    }

    #[test]
    fn frames_come_at_the_rate_with_a_counting_seq_and_two_pods_send_a_zero_third() {
        let mut plant = Moving::new([0.2, 0.0, 0.0]);
        let p = PodsParams {
            rate_hz: 300.0,
            ..PodsParams::default()
        };
        let f = run(&mut plant, &p, &layout()[..2], 1, 1000);
        assert_eq!(f.len(), 300);
        assert_eq!(
            (f[0].0, f[1].0, f[299].0),
            (3_333_333, 6_666_667, 1_000_000_000)
        );
        assert!(f.iter().enumerate().all(|(i, x)| x.2 == i as u8));
        assert!(f.iter().all(|x| x.1[2] == 0));
        // The counts are monotonic at a constant forward speed.
        assert!(f.windows(2).all(|w| w[1].1[0] >= w[0].1[0]));
        // The plant advanced to each sample instant and then to the millisecond.
        assert_eq!(plant.advances[..3], [1_000_000, 1_000_000, 1_000_000]);
        assert_eq!(plant.advances[3..5], [333_333, 666_667]);
    }

    #[test]
    fn the_count_is_the_floor_of_the_turns_and_wraps() {
        let p = TruePod::new(&pod(0.0, 0.0, 0.0), &PodErrors::default());
        let per_count = TAU * f64::from(R) / f64::from(CPT);
        assert_eq!(p.count(0.0), 0);
        assert_eq!(p.count(0.99 * per_count), 0);
        assert_eq!(p.count(1.01 * per_count), 1);
        // A little backwards is count −1: 65535.
        assert_eq!(p.count(-0.01 * per_count), u16::MAX);
        assert_eq!(p.count(65_536.5 * per_count), 0);
        assert_eq!(p.count(65_537.5 * per_count), 1);
    }

    #[test]
    fn the_same_seed_gives_the_same_frames_and_the_noise_has_its_density() {
        let noisy = PodsParams {
            noise: 0.01,
            ..PodsParams::default()
        };
        let frames = |p: &PodsParams, seed, ms| {
            let mut plant = Moving::new([0.0; 3]);
            run(&mut plant, p, &layout(), seed, ms)
        };
        let (a, b, c) = (
            frames(&noisy, 5, 500),
            frames(&noisy, 5, 500),
            frames(&noisy, 6, 500),
        );
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Without noise the seed does not matter: a robot at rest counts nothing.
        let quiet = PodsParams::default();
        let q = frames(&quiet, 1, 100);
        assert!(q.iter().all(|x| x.1 == [0; 3]));
        assert_eq!(q, frames(&quiet, 2, 100));
        // 0.01 m/s/√Hz at 200 Hz: each sample adds σ = 0.707 mm to the travel, 9.4 counts;
        // the differences of the counts show it (within 5 %: 4000 samples estimate σ to
        // 1.1 %; the quantisation adds 1/6 count²).
        let f = frames(&noisy, 9, 20_000);
        let steps: Vec<f64> = f
            .windows(2)
            .map(|w| f64::from(w[1].1[2].wrapping_sub(w[0].1[2]) as i16))
            .collect();
        let n = steps.len() as f64;
        let mean = steps.iter().sum::<f64>() / n;
        let std = (steps.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / n).sqrt();
        let sigma = noisy.sample_std_m() / (TAU * f64::from(R) / f64::from(CPT));
        assert!((std / sigma - 1.0).abs() < 0.05, "std {std}, want {sigma}");
        assert!(mean.abs() < 4.0 * sigma / n.sqrt(), "mean {mean}");
    }

    #[test]
    fn a_silent_node_sends_nothing_and_counts_on() {
        let mut plant = Moving::new([0.3, 0.0, 0.0]);
        let node = PodNode::new(&PodsParams::default(), &layout(), 1)
            .silenced([(100_000_000, 200_000_000)]);
        let f = run_node(&mut plant, node, 300);
        // 60 samples, 20 of them (100 ms up to 195 ms) not sent.
        assert_eq!(f.len(), 40);
        assert_eq!((f[18].0, f[19].0), (95_000_000, 200_000_000));
        assert_eq!((f[18].2, f[19].2), (18, 39));
        let want = expected(0.3 * 0.2, f64::from(R));
        assert!((signed(f[19].1[0]) - want).abs() <= 1.0);
    }

    #[test]
    fn without_pods_every_call_passes_through() {
        let mut plant = Moving::new([0.5, 0.0, 0.1]);
        let mut with = WithPods::new(&mut plant, None);
        assert!(with.pods().is_none());
        with.advance(0.0015);
        with.advance_ns(0);
        with.advance_ns(2_500_001);
        assert_eq!(with.next_feedback_ns(), u64::MAX);
        assert_eq!(with.truth_velocity(), [0.5, 0.0, 0.1]);
        let mut out = Vec::new();
        with.node_frames(Node::Pods, u64::MAX, &mut out);
        with.node_frames(Node::Imu, u64::MAX, &mut out);
        assert!(out.is_empty());
        // Exactly the calls made, zero-length ones too.
        assert_eq!(plant.advances, [1_500_000, 0, 2_500_001]);
    }

    #[test]
    fn out_of_range_parameters_are_named() {
        let with_pod = |e: PodErrors| PodsParams {
            pod: vec![PodErrors::default(), e],
            ..PodsParams::default()
        };
        for (p, key) in [
            (
                PodsParams {
                    rate_hz: 0.0,
                    ..PodsParams::default()
                },
                "rate_hz",
            ),
            (
                PodsParams {
                    rate_hz: 2000.5,
                    ..PodsParams::default()
                },
                "rate_hz",
            ),
            (
                PodsParams {
                    noise: -0.1,
                    ..PodsParams::default()
                },
                "noise",
            ),
            (
                with_pod(PodErrors {
                    radius_error: f64::NAN,
                    ..PodErrors::default()
                }),
                "pod[1].radius_error",
            ),
            (
                with_pod(PodErrors {
                    misalignment_deg: 200.0,
                    ..PodErrors::default()
                }),
                "pod[1].misalignment_deg",
            ),
            (
                with_pod(PodErrors {
                    offset_y: 1.5,
                    ..PodErrors::default()
                }),
                "pod[1].offset_y",
            ),
        ] {
            assert_eq!(p.invalid().map(|x| x.0), Some(key.to_owned()));
        }
        assert_eq!(PodsParams::default().invalid(), None);
    }
}
