//! The velocity loop the core runs for current-driven wheels (DJI C620/C610): a PI per wheel
//! with anti-windup, and the two watches that only a loop's own currents can feed, a wheel
//! that runs away and wheels that fight (`docs/control.md`, "Wheel runaway" and "Wheels that
//! fight"). Velocity-mode drives (ODrive) run their own loop and have none of this.

use kinematics::{ChassisVelocity, MecanumKinematics, WheelSpeeds};

use super::Instant;
use crate::config::Gains;

/// Wheel runaway: a current at least this fraction of the limit in force is saturated.
pub const RUNAWAY_SATURATION: f32 = 0.95;
/// Wheel runaway: how long a wheel's current must stay saturated towards its setpoint before
/// its speed is judged, µs.
pub const RUNAWAY_WINDOW_US: u64 = 60_000;
/// Wheel runaway: a wheel turning against its setpoint at least this fast (rad/s at the
/// wheel) is turning the other way.
pub const RUNAWAY_MIN_SPEED: f32 = 1.0;
/// Wheel runaway: a wheel whose speed moved at least this much (rad/s) the other way than
/// its current pushes, since its current saturated, moves away from its setpoint.
pub const RUNAWAY_GROWTH: f32 = 2.0;
/// Wheels that fight: a residual of the currents (the part no body motion explains) with
/// an RMS at least this fraction of `limits.max_current` is a fight (0.8 A of 16 A).
pub const FIGHT_CURRENT_FRACTION: f32 = 0.05;
/// Wheels that fight: the watch rests while the commanded twist strafes and turns at once,
/// at least this fast each (m/s and rad/s), where the rollers' drag makes a right robot's
/// wheels push against each other too.
pub const FIGHT_COMBINED_MIN: f32 = 0.02;
/// Wheels that fight: how long the residual must stay above its threshold, µs.
pub const FIGHT_WINDOW_US: u64 = 60_000;

/// The loop's state for the four wheels.
#[derive(Debug, Clone, Copy)]
pub(super) struct CurrentLoop {
    /// Velocity PI integrators, A.
    integral: [f32; 4],
    runaway: [RunawayWatch; 4],
    fight: FightWatch,
    /// Steps a window of [`RUNAWAY_WINDOW_US`] and one of [`FIGHT_WINDOW_US`] span: a watch
    /// fires only after its window has passed *and* the core has seen that many steps of it,
    /// so a loop that stalls (a late runner, an overrun) does not judge on one late look.
    runaway_steps: u32,
    fight_steps: u32,
}

/// What the watches read at one step: the loop's inputs and outputs of the previous step
/// (the currents the motors are acting on) and the latest measured speeds.
pub(super) struct WatchInputs<'a> {
    pub kin: &'a MecanumKinematics<f32, 4>,
    /// Currents commanded at the previous step, A.
    pub currents: [f32; 4],
    /// Wheel speed setpoints of the previous step, rad/s.
    pub setpoints: [f32; 4],
    /// Latest measured wheel speeds, rad/s.
    pub speeds: [f32; 4],
    /// The current limit in force, A (0: no wheel is driven).
    pub limit: f32,
    /// `limits.max_current`, A.
    pub max_current: f32,
    /// The twist commanded, and whether the robot is enabled (the fight watch runs only then).
    pub commanded: ChassisVelocity<f32>,
    pub enabled: bool,
}

impl CurrentLoop {
    /// A loop at rest for a control period of `period_us`.
    pub(super) fn new(period_us: u64) -> Self {
        let steps =
            |window_us: u64| u32::try_from(window_us / period_us.max(1)).unwrap_or(u32::MAX);
        Self {
            integral: [0.0; 4],
            runaway: [RunawayWatch::default(); 4],
            fight: FightWatch::default(),
            runaway_steps: steps(RUNAWAY_WINDOW_US),
            fight_steps: steps(FIGHT_WINDOW_US),
        }
    }

    /// Forgets the integrators (a halt: the motors get zero current from the next step).
    pub(super) fn reset(&mut self) {
        self.integral = [0.0; 4];
    }

    /// New gains, bumpless: each integrator takes up the change of the proportional and
    /// feed-forward terms at the last step's `setpoints` and `speeds`, so that the current
    /// those give is the same with `new` as with `old` (within the limit `max`). The
    /// integrator holds amperes (`ki` is inside its increments), so `ki` moves nothing.
    pub(super) fn retune(
        &mut self,
        old: &Gains,
        new: &Gains,
        setpoints: [f32; 4],
        speeds: [f32; 4],
        max: f32,
    ) {
        for i in 0..4 {
            let error = setpoints[i] - speeds[i];
            let change = (new.kv - old.kv) * setpoints[i] + (new.kp - old.kp) * error;
            self.integral[i] = symmetric_limit(self.integral[i] - change, max);
        }
    }

    /// One step of the velocity PI of the wheels in `mask` (bit i: wheel i; the others get no
    /// current, and their integrators are emptied) with the current limit `max`: the currents.
    #[inline]
    pub(super) fn run(
        &mut self,
        setpoints: [f32; 4],
        speeds: [f32; 4],
        g: &Gains,
        mask: u8,
        max: f32,
        dt: f32,
    ) -> [f32; 4] {
        if mask == 0 {
            self.integral = [0.0; 4];
            return [0.0; 4];
        }
        let mut c = pi_step(&mut self.integral, setpoints, speeds, g, max, dt);
        if mask != 0b1111 {
            for (i, (c, integral)) in c.iter_mut().zip(&mut self.integral).enumerate() {
                if mask & (1 << i) == 0 {
                    *c = 0.0;
                    *integral = 0.0;
                }
            }
        }
        c
    }

    /// Runs both watches for this step (each one always, so that its intervals stay current);
    /// whether a wheel ran away, and whether the wheels fight.
    pub(super) fn watch(&mut self, now: Instant, w: &WatchInputs<'_>) -> (bool, bool) {
        let threshold = RUNAWAY_SATURATION * w.limit;
        let mut runaway = false;
        for (i, watch) in self.runaway.iter_mut().enumerate() {
            let (current, setpoint, speed) = (w.currents[i], w.setpoints[i], w.speeds[i]);
            // Saturated, and pushing towards the setpoint.
            let saturated =
                w.limit > 0.0 && current.abs() >= threshold && current * (setpoint - speed) > 0.0;
            let push = if saturated { current.signum() } else { 0.0 };
            runaway |= watch.judge(now, push, setpoint, speed, self.runaway_steps);
        }
        let fight = self.fight.judge(now, w, self.fight_steps);
        (runaway, fight)
    }
}

/// Runaway watch of one current-driven wheel.
#[derive(Debug, Clone, Copy, Default)]
struct RunawayWatch {
    /// First step of the running interval of saturated current towards the setpoint.
    since: Option<Instant>,
    /// The wheel's speed at that step, rad/s.
    speed0: f32,
    /// Steps in the interval so far.
    steps: u32,
}

impl RunawayWatch {
    /// Updates the interval for this step (`push`: the sign of the saturated current, 0 when
    /// it is not saturated towards the setpoint); `true` once it has lasted
    /// [`RUNAWAY_WINDOW_US`] and the wheel turns against its setpoint or has moved away from
    /// it since the interval began.
    #[inline]
    fn judge(&mut self, now: Instant, push: f32, setpoint: f32, speed: f32, steps: u32) -> bool {
        if push == 0.0 {
            self.since = None;
            return false;
        }
        let since = match self.since {
            Some(t) => t,
            None => {
                self.since = Some(now);
                self.speed0 = speed;
                self.steps = 0;
                now
            }
        };
        self.steps = self.steps.saturating_add(1);
        if now.micros_since(since) < RUNAWAY_WINDOW_US || self.steps <= steps {
            return false;
        }
        let against = setpoint * speed < 0.0 && speed.abs() >= RUNAWAY_MIN_SPEED;
        let away = (speed - self.speed0) * push <= -RUNAWAY_GROWTH;
        against || away
    }
}

/// The wheel-fight watch of the four wheels.
#[derive(Debug, Clone, Copy, Default)]
struct FightWatch {
    /// Since when the currents' residual has been above its threshold, and for how many steps.
    since: Option<(Instant, u32)>,
    /// The watch rests (a strafe-and-turn, until the residual is below its threshold again).
    rest: bool,
}

impl FightWatch {
    /// `true` once the residual of the currents has been above the threshold for
    /// [`FIGHT_WINDOW_US`] while enabled.
    fn judge(&mut self, now: Instant, w: &WatchInputs<'_>, steps: u32) -> bool {
        let c = w.commanded;
        let combined = c.vy.abs() >= FIGHT_COMBINED_MIN && c.wz.abs() >= FIGHT_COMBINED_MIN;
        let threshold = FIGHT_CURRENT_FRACTION * w.max_current;
        let above = w.enabled && {
            let (_, residual) = w.kin.forward_with_residual(&WheelSpeeds(w.currents));
            residual.rms() >= threshold
        };
        // A strafe-and-turn rests the watch; the loops' integrators hold its pushing for a
        // while after it, so the watch wakes only once the residual has been below the
        // threshold again.
        self.rest = combined || (self.rest && above);
        let fighting = above && !self.rest;
        if !fighting {
            self.since = None;
            return false;
        }
        let (since, n) = self.since.get_or_insert((now, 0));
        *n = n.saturating_add(1);
        now.micros_since(*since) >= FIGHT_WINDOW_US && *n > steps
    }
}

/// One step of the four wheels' velocity PI with conditional integration (anti-windup): a
/// wheel's integrator only moves when its output is not saturated, or when the error would
/// pull it back out of saturation. Returns the currents; the wheels are independent (written
/// as one loop so that the compiler can run them side by side).
fn pi_step(
    integral: &mut [f32; 4],
    setpoint: [f32; 4],
    speed: [f32; 4],
    g: &Gains,
    max: f32,
    dt: f32,
) -> [f32; 4] {
    let mut current = [0.0; 4];
    for i in 0..4 {
        let error = setpoint[i] - speed[i];
        let proportional = g.kv * setpoint[i] + g.kp * error;
        let increment = g.ki * error * dt;
        let unclamped = proportional + integral[i] + increment;
        // `&` and a select rather than `&&` and a branch: the same values, and no branch
        // per wheel.
        let saturated_same_way = (unclamped.abs() > max) & ((unclamped > 0.0) == (error > 0.0));
        let moved = symmetric_limit(integral[i] + increment, max);
        integral[i] = if saturated_same_way {
            integral[i]
        } else {
            moved
        };
        current[i] = symmetric_limit(proportional + integral[i], max);
    }
    current
}

/// `x` limited to `[-max, max]`. Not `f32::clamp`: its check of the bounds formats floats in
/// its panic message, which costs the MCU image about 19 KB of formatting code.
pub(super) fn symmetric_limit(x: f32, max: f32) -> f32 {
    x.max(-max).min(max)
}
