//! Odometry from tracking pods (`POD_COUNTS`): each frame's count increments become a body
//! increment through the pod localizer (Road Runner's two- and three-wheel formulas, general
//! layouts) and move the pose along the SE(2) exponential; the wheels' motion over the same
//! interval, less the pods', is the slip estimate (`ODOM_SLIP`). Pods silent for
//! `odometry.pod_timeout_ms`: the wheels take over, with what they drove since the last pod
//! frame, and the pods again from their second frame (the first sets the baseline), so the
//! pose never jumps. Specified in `docs/control.md`, "Odometry from tracking pods".

use kinematics::{ChassisVelocity, Twist2};

use super::{Controller, Instant};
use crate::config::{OdometryConfig, PODS_MAX, PodSolve};
use crate::protocol::robot::{OdometrySource, PodCounts};

/// Time constant of the slip estimate's low-pass filter, s: long enough to smooth a 2000
/// count-per-turn pod's quantisation at 200 frames a second (7 mm/s a count), short enough
/// to show a slide within a few control periods of its start.
pub const SLIP_TIME_CONSTANT_S: f32 = 0.1;

/// The pods, their baseline and what the wheels did since the last pod frame.
#[derive(Debug, Clone, Copy)]
pub(super) struct Pods {
    /// The solve of the configured layout; `None` with `odometry.source = "wheels"`.
    solve: Option<PodSolve>,
    /// Each pod's travel per count, m.
    metres_per_count: [f32; PODS_MAX],
    /// The counts of the last frame used; `None`: the next frame sets it (at start and
    /// after a silence).
    baseline: Option<[u16; PODS_MAX]>,
    /// `seq` of the last accepted frame (kept through a silence, as the gyro's).
    last_seq: Option<u8>,
    /// Arrival of the last accepted frame.
    last_at: Option<Instant>,
    /// Count increments of the frames taken since the last step, summed.
    pending: Option<[i32; PODS_MAX]>,
    /// Each pod's wheel angle since the start, rad (the counts' increments; not what a
    /// silence hid).
    pub(super) angles: [f32; PODS_MAX],
    /// Each pod's angle per count, rad.
    radians_per_count: [f32; PODS_MAX],
    /// How many pods are configured.
    pub(super) count: u8,
    /// The wheels' body increment since the last pod frame (summed in the body frame: over
    /// one frame interval the body turns little).
    wheels_since: Twist2<f32>,
    /// The heading source's (gyro or wheels) rotation over the same steps, rad.
    heading_since: f32,
    /// Time since the last pod frame, s (the steps summed).
    since_s: f32,
    /// The wheels' body velocity (forward kinematics of their speeds) at the last step.
    wheel_velocity: ChassisVelocity<f32>,
    /// The wheels' body velocity less the pods', low-pass filtered.
    pub(super) slip: ChassisVelocity<f32>,
    /// Where the odometry came from at the last step.
    pub(super) source: OdometrySource,
}

impl Pods {
    /// The pods of a validated configuration.
    pub(super) fn new(o: &OdometryConfig) -> Self {
        let mut metres_per_count = [0.0; PODS_MAX];
        let mut radians_per_count = [0.0; PODS_MAX];
        for ((m, r), pod) in metres_per_count
            .iter_mut()
            .zip(&mut radians_per_count)
            .zip(o.pods.as_slice())
        {
            *m = pod.metres_per_count();
            *r = core::f32::consts::TAU / pod.counts_per_turn as f32;
        }
        // Validation built it once already; it cannot fail here.
        let solve = crate::config::pod_localizer(o.source, &o.pods)
            .ok()
            .flatten();
        Self {
            solve,
            metres_per_count,
            baseline: None,
            last_seq: None,
            last_at: None,
            pending: None,
            angles: [0.0; PODS_MAX],
            radians_per_count,
            // At most PODS_MAX.
            count: o.pods.len() as u8,
            wheels_since: Twist2::default(),
            heading_since: 0.0,
            since_s: 0.0,
            wheel_velocity: ChassisVelocity::default(),
            slip: ChassisVelocity::default(),
            source: if solve.is_some() {
                OdometrySource::WheelsPodsSilent
            } else {
                OdometrySource::Wheels
            },
        }
    }

    /// Whether the pods give the odometry now.
    fn active(&self) -> bool {
        matches!(
            self.source,
            OdometrySource::Pods2Gyro | OdometrySource::Pods3
        )
    }

    /// The body velocity to report: while the pods give the odometry, the wheels' less the
    /// slip (one frame interval's pod velocity is coarse: a count of a 2000-count, 24 mm pod
    /// in 5 ms is 15 mm/s, and 63 mrad/s between pods 0.24 m apart); else `wheels`.
    pub(super) fn velocity(&self, wheels: ChassisVelocity<f32>) -> ChassisVelocity<f32> {
        if !self.active() {
            return wheels;
        }
        let (v, s) = (self.wheel_velocity, self.slip);
        ChassisVelocity::new(v.vx - s.vx, v.vy - s.vy, v.wz - s.wz)
    }

    /// Whether the robot is configured with pods (it sends `ODOM_SLIP`).
    pub(super) fn configured(&self) -> bool {
        self.solve.is_some()
    }

    /// From this step on the pods give the odometry: nothing driven since counts yet.
    fn take_over(&mut self) {
        self.source = match self.solve {
            Some(PodSolve::Three(_)) => OdometrySource::Pods3,
            _ => OdometrySource::Pods2Gyro,
        };
        self.restart_interval();
    }

    /// A new frame interval: nothing driven since the last frame.
    fn restart_interval(&mut self) {
        self.wheels_since = Twist2::default();
        self.heading_since = 0.0;
        self.since_s = 0.0;
    }
}

impl Controller {
    /// Takes a valid `POD_COUNTS`: its increments since the last frame, or the baseline (the
    /// first frame, and the first after a silence, from which the pods take over).
    pub(super) fn on_pods(&mut self, now: Instant, c: PodCounts) {
        let p = &mut self.pods;
        if p.solve.is_none() {
            return; // a robot without pods expects none
        }
        if p.last_seq == Some(c.seq) {
            // The same frame again (a stuck node or gateway): not a sign of life.
            self.repeated_seq = self.repeated_seq.saturating_add(1);
            return;
        }
        p.last_seq = Some(c.seq);
        p.last_at = Some(now.mark(p.last_at));
        let Some(base) = p.baseline.replace(c.counts) else {
            p.take_over();
            return;
        };
        let pending = p.pending.get_or_insert([0; PODS_MAX]);
        for i in 0..PODS_MAX {
            // The signed 16-bit difference: a wrapping counter that turned < 32768 counts.
            let counts = i32::from(c.counts[i].wrapping_sub(base[i]) as i16);
            pending[i] += counts;
            p.angles[i] += counts as f32 * p.radians_per_count[i];
        }
    }

    /// With pods configured: whether they are alive; silent past the timeout, the wheels
    /// take over with what they drove since the last pod frame.
    pub(super) fn update_pods(&mut self, now: Instant) {
        let timeout_us = u64::from(self.config.odometry.pod_timeout_ms) * 1000;
        let p = &mut self.pods;
        if !p.active() {
            return;
        }
        let alive = p.last_at.is_some_and(|t| now.micros_since(t) <= timeout_us);
        if !alive {
            // What the wheels drove since the last pod frame, the heading source's rotation.
            self.odometry.apply(Twist2 {
                dtheta: p.heading_since,
                ..p.wheels_since
            });
            p.source = OdometrySource::WheelsPodsSilent;
            p.baseline = None;
            p.pending = None;
            p.restart_interval();
            p.slip = ChassisVelocity::default();
        }
    }

    /// With the pods giving the odometry: the step's wheel increment `wheels` and the heading
    /// source's rotation `heading` (and the wheels' velocity) are kept (for two pods' solve, the slip estimate and a
    /// fallback); a pod frame since the last step moves the pose. Returns `false` when the
    /// wheels give the odometry.
    pub(super) fn integrate_pods(
        &mut self,
        wheels: Twist2<f32>,
        heading: f32,
        wheel_velocity: ChassisVelocity<f32>,
    ) -> bool {
        let dt = self.dt;
        let p = &mut self.pods;
        p.wheel_velocity = wheel_velocity;
        let Some(solve) = p.solve.filter(|_| p.active()) else {
            return false;
        };
        p.wheels_since.dx += wheels.dx;
        p.wheels_since.dy += wheels.dy;
        p.wheels_since.dtheta += wheels.dtheta;
        p.heading_since += heading;
        p.since_s += dt;
        let Some(counts) = p.pending.take() else {
            return true;
        };
        let arc = |i: usize| counts[i] as f32 * p.metres_per_count[i];
        let step = match solve {
            PodSolve::Three(l) => l.increment([arc(0), arc(1), arc(2)]),
            PodSolve::Two(l) => l.increment([arc(0), arc(1)], p.heading_since),
        };
        self.odometry.apply(step);
        let interval = p.since_s.max(dt);
        let w = p.wheels_since;
        let difference = ChassisVelocity::new(
            (w.dx - step.dx) / interval,
            (w.dy - step.dy) / interval,
            (w.dtheta - step.dtheta) / interval,
        );
        let k = interval / (SLIP_TIME_CONSTANT_S + interval);
        p.slip = ChassisVelocity::new(
            p.slip.vx + k * (difference.vx - p.slip.vx),
            p.slip.vy + k * (difference.vy - p.slip.vy),
            p.slip.wz + k * (difference.wz - p.slip.wz),
        );
        p.restart_interval();
        true
    }
}
