//! The control core on a scripted bus: motor feedback is fed at the drives' real rates, robot
//! commands at chosen times, and the frames the core emits are decoded with the same codecs
//! the rest of the stack uses.

// The scripted drives walk several per-wheel arrays in step.
#![allow(clippy::needless_range_loop)]

use firmware::CanFrame;
use firmware::config::{Config, Drive, Geometry};
use firmware::control::{Controller, Instant, Outbox};
use firmware::protocol::dji::{self, CurrentCommand, EscModel};
use firmware::protocol::odrive::{self, AxisState, ControlMode, NodeId};
use firmware::protocol::robot::{self, Command, Fault, ModeRequest, RobotState, TwistCmd};
use proptest::prelude::*;

/// One millisecond of simulated time per tick (the default 1 kHz loop).
const TICK_US: u64 = 1_000;

/// A controller with scripted drives: each alive motor reports `speed` (wheel rad/s in the
/// motor's own sign) at the drive's feedback rate, with a consistent angle.
struct Rig {
    ctl: Controller,
    config: Config,
    now_us: u64,
    alive: [bool; 4],
    /// Motor-side wheel speed each drive reports, rad/s.
    speed: [f32; 4],
    /// Motor-side rotor angle, counts (DJI) / turns (ODrive), unwrapped.
    rotor: [f64; 4],
    /// DJI: a stuck encoder reports this rotor angle and rpm whatever the rotor does.
    frozen: [Option<(u16, i16)>; 4],
    /// ODrive: the axis error each heartbeat reports, until a `Clear_Errors` to the node
    /// clears it (unless `error_persists`).
    axis_error: [u32; 4],
    /// ODrive: the cause of the axis error is still there: `Clear_Errors` does not clear it.
    error_persists: [bool; 4],
    /// Every frame emitted, with its time.
    log: Vec<(u64, CanFrame)>,
    /// The `seq` of the next twist (the alive counter a host increments).
    seq: u8,
}

impl Rig {
    fn new(config: Config) -> Self {
        Self {
            ctl: Controller::new(&config).expect("valid config"),
            config,
            now_us: 0,
            alive: [true; 4],
            speed: [0.0; 4],
            rotor: [0.0; 4],
            frozen: [None; 4],
            axis_error: [0; 4],
            error_persists: [false; 4],
            log: Vec::new(),
            seq: 0,
        }
    }

    fn dji() -> Self {
        Self::new(Config::dji_m3508_example())
    }

    /// ODrive example with the watchdog stop "at once", so setpoints reach zero in one period.
    fn odrive() -> Self {
        let mut c = Config::odrive_example();
        c.limits.stop_linear_decel = f32::INFINITY;
        c.limits.stop_angular_decel = f32::INFINITY;
        Self::new(c)
    }

    fn now(&self) -> Instant {
        Instant::from_micros(self.now_us)
    }

    fn send(&mut self, cmd: Command) {
        let frame = cmd.to_can_frame();
        self.ctl.on_frame(self.now(), &frame);
    }

    fn raw(&mut self, frame: CanFrame) {
        self.ctl.on_frame(self.now(), &frame);
    }

    /// Sends a twist as a host does: `seq` one more than the last one's.
    fn twist(&mut self, vx: f32, vy: f32, wz: f32) {
        let seq = self.seq;
        self.seq = seq.wrapping_add(1);
        self.twist_seq(vx, vy, wz, seq);
    }

    /// Sends a twist with this `seq` (the counter of `twist` is left alone).
    fn twist_seq(&mut self, vx: f32, vy: f32, wz: f32, seq: u8) {
        self.send(Command::Twist(TwistCmd { vx, vy, wz, seq }));
    }

    fn feed_motors(&mut self) {
        let ms = self.now_us / 1000;
        match self.config.drive {
            Drive::Dji {
                model,
                esc_ids,
                gear_ratio,
                ..
            } => {
                for w in 0..4 {
                    let rotor_rad_s = self.speed[w] * gear_ratio;
                    self.rotor[w] += f64::from(rotor_rad_s) * 1e-3 * 8192.0 / std::f64::consts::TAU;
                    if !self.alive[w] {
                        continue;
                    }
                    let (rotor_angle, rotor_speed_rpm) = self.frozen[w].unwrap_or((
                        self.rotor[w].rem_euclid(8192.0) as u16,
                        (rotor_rad_s * 60.0 / std::f32::consts::TAU).round() as i16,
                    ));
                    let fb = dji::Feedback {
                        model,
                        esc: dji::EscId::new(esc_ids[w]).unwrap(),
                        rotor_angle,
                        rotor_speed_rpm,
                        torque_current: 0,
                        temperature_c: 30,
                    };
                    self.raw(fb.to_can_frame());
                }
            }
            Drive::Odrive {
                node_ids,
                gear_ratio,
                ..
            } => {
                for w in 0..4 {
                    let turns_s = self.speed[w] * gear_ratio / std::f32::consts::TAU;
                    self.rotor[w] += f64::from(turns_s) * 1e-3;
                    if !self.alive[w] {
                        continue;
                    }
                    let node = NodeId::new(node_ids[w]).unwrap();
                    if ms.is_multiple_of(10) {
                        let est = odrive::Feedback::EncoderEstimates {
                            pos: self.rotor[w] as f32,
                            vel: turns_s,
                        };
                        self.raw(est.to_can_frame(node));
                    }
                    if ms.is_multiple_of(100) {
                        self.raw(odrive_heartbeat(
                            node.get(),
                            AxisState::ClosedLoopControl,
                            self.axis_error[w],
                        ));
                    }
                }
            }
        }
    }

    /// Feeds this millisecond's motor feedback, runs one step, advances the clock.
    fn tick(&mut self) -> Outbox {
        self.feed_motors();
        let out = self.ctl.step(self.now());
        for f in &out {
            self.log.push((self.now_us, *f));
            if let Drive::Odrive { node_ids, .. } = self.config.drive
                && let Ok(a) = odrive::Command::decode(f)
                && let odrive::Command::ClearErrors { .. } = a.msg
                && let Some(w) = node_ids.iter().position(|&n| n == a.node.get())
                && !self.error_persists[w]
            {
                self.axis_error[w] = 0;
            }
        }
        self.now_us += TICK_US;
        out
    }

    fn run_ms(&mut self, ms: u64) -> Vec<Outbox> {
        (0..ms).map(|_| self.tick()).collect()
    }

    /// Runs until `pred` holds for a step's output; returns the time it first held.
    fn run_until(&mut self, max_ms: u64, pred: impl Fn(&Rig, &Outbox) -> bool) -> Option<u64> {
        for _ in 0..max_ms {
            let t = self.now_us;
            let out = self.tick();
            if pred(self, &out) {
                return Some(t);
            }
        }
        None
    }

    fn enable(&mut self) {
        self.send(Command::Mode(ModeRequest::Enable));
    }

    fn status(&self) -> robot::Status {
        self.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::Status(s)) => Some(s),
                _ => None,
            })
            .expect("a status frame was sent")
    }

    /// The last `STATUS_COUNTERS` sent, with its time.
    fn counters(&self) -> (u64, robot::StatusCounters) {
        self.log
            .iter()
            .rev()
            .find_map(|(t, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::StatusCounters(c)) => Some((*t, c)),
                _ => None,
            })
            .expect("a status counters frame was sent")
    }
}

/// The ODrive velocity setpoints (rev/s) in a step's output, in wheel order; None if absent.
fn odrive_vels(config: &Config, out: &Outbox) -> Option<[f32; 4]> {
    let Drive::Odrive { node_ids, .. } = config.drive else {
        panic!("not an ODrive config")
    };
    let mut vels = [f32::NAN; 4];
    for f in out {
        if let Ok(a) = odrive::Command::decode(f)
            && let odrive::Command::SetInputVel { vel, .. } = a.msg
            && let Some(w) = node_ids.iter().position(|&n| n == a.node.get())
        {
            vels[w] = vel;
        }
    }
    vels.iter().all(|v| !v.is_nan()).then_some(vels)
}

/// The DJI currents (A, motor sign) in a step's output, ESC 1-4.
fn dji_currents(out: &Outbox) -> Option<[f32; 4]> {
    out.iter().find_map(|f| {
        CurrentCommand::decode(f, EscModel::C620)
            .ok()
            .map(|c| c.amps())
    })
}

fn all_zero(v: [f32; 4]) -> bool {
    v.iter().all(|&x| x == 0.0)
}

#[test]
fn odrive_enable_sends_mode_and_closed_loop_then_twist_gives_exact_setpoints() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    let out = rig.tick();
    let mut seen_mode = 0;
    let mut seen_closed = 0;
    for f in &out {
        match odrive::Command::decode(f).map(|a| a.msg) {
            Ok(odrive::Command::SetControllerMode { control_mode, .. }) => {
                assert_eq!(control_mode, ControlMode::VelocityControl);
                seen_mode += 1;
            }
            Ok(odrive::Command::SetAxisState(AxisState::ClosedLoopControl)) => seen_closed += 1,
            _ => {}
        }
    }
    assert_eq!((seen_mode, seen_closed), (4, 4), "{out:?}");

    // Forward 0.5 m/s; ramp at 4 m/s² takes 125 ms. Keep commanding every 20 ms.
    for _ in 0..10 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(20);
    }
    rig.twist(0.5, 0.0, 0.0);
    let vels = {
        let mut v = None;
        for _ in 0..5 {
            let o = rig.tick();
            if let Some(x) = odrive_vels(&rig.config, &o) {
                v = Some(x);
            }
        }
        v.expect("setpoints every 5 ms at 200 Hz")
    };
    // Wheel speed 0.5 / 0.05 = 10 rad/s; motor 10 * 5 / 2π rev/s; right side mirrored.
    let want = 10.0 * 5.0 / std::f32::consts::TAU;
    let expect = [want, -want, want, -want];
    for (got, want) in vels.iter().zip(expect) {
        assert!((got - want).abs() < 1e-4, "{vels:?} vs {expect:?}");
    }
}

#[test]
fn dji_twist_gives_currents_with_mounting_signs_and_pi_action() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.twist(1.0, 0.0, 0.0);
    // First step: commanded twist is one ramp increment, 4 m/s² * 1 ms = 4 mm/s.
    let out = rig.tick();
    let amps = dji_currents(&out).expect("a current frame every period");
    let g = rig.config.gains;
    let sp = 0.004 / 0.076; // wheel rad/s
    let want = g.kp * sp + g.ki * sp * 1e-3;
    // Motors report zero speed, so the error is the setpoint; right side mirrored.
    let expect = [want, -want, want, -want];
    for (got, want) in amps.iter().zip(expect) {
        // The C620 resolution is 20/16384 A.
        assert!(
            (got - want).abs() <= 20.0 / 16384.0,
            "{amps:?} vs {expect:?}"
        );
    }
    // Held error: the integrator grows, the current rises, and it stops at max_current.
    for _ in 0..50 {
        rig.twist(1.0, 0.0, 0.0);
        rig.run_ms(10);
    }
    let amps = dji_currents(&rig.tick()).unwrap();
    let max = rig.config.limits.max_current;
    for (i, a) in amps.iter().enumerate() {
        let want = if i % 2 == 0 { max } else { -max };
        assert!(
            (a - want).abs() <= 20.0 / 16384.0,
            "saturated at ±max: {amps:?}"
        );
    }
}

#[test]
fn anti_windup_releases_at_once_when_the_wheel_catches_up() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..100 {
        rig.twist(1.0, 0.0, 0.0);
        rig.run_ms(10);
    }
    // The wheels suddenly reach the setpoint (1 m/s / 0.076 m): with the integrator clamped
    // at the output limit the current falls below the limit on the very next step.
    let sp = 1.0 / 0.076;
    rig.speed = [sp, -sp, sp, -sp];
    rig.twist(1.0, 0.0, 0.0);
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(amps[0] <= rig.config.limits.max_current, "{amps:?}");
    rig.speed = [sp + 2.0, -(sp + 2.0), sp + 2.0, -(sp + 2.0)];
    rig.twist(1.0, 0.0, 0.0);
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(amps[0] < rig.config.limits.max_current - 1.0, "{amps:?}");
}

/// Drives forward, stops commanding at `t_last`, and returns the time zero setpoints first
/// appear and the last nonzero one before that.
fn watchdog_zero_time(rig: &mut Rig, with_status_polls: bool) -> (u64, u64) {
    rig.run_ms(20);
    rig.enable();
    for _ in 0..30 {
        rig.twist(0.3, 0.1, 0.2);
        rig.run_ms(10);
    }
    rig.twist(0.3, 0.1, 0.2);
    let t_last = rig.now_us;
    let mut zero_at = None;
    for ms in 0..400u32 {
        if with_status_polls && ms.is_multiple_of(5) {
            rig.send(Command::StatusRequest);
        }
        let t = rig.now_us;
        let out = rig.tick();
        if let Some(v) = odrive_vels(&rig.config, &out) {
            if all_zero(v) {
                zero_at.get_or_insert(t);
            } else {
                assert!(zero_at.is_none(), "motion resumed at {t}");
            }
        }
    }
    (t_last, zero_at.expect("zero setpoints were sent"))
}

#[test]
fn commands_stop_zero_setpoints_within_timeout_plus_two_periods() {
    let mut rig = Rig::odrive();
    let (t_last, zero_at) = watchdog_zero_time(&mut rig, false);
    let period = 1_000;
    // ODrive setpoints go out at 200 Hz: allow that period as the "control period" here.
    let setpoint_period = 5_000;
    let bound = 100_000 + 2 * period.max(setpoint_period);
    assert!(
        zero_at - t_last <= bound,
        "zero after {} us, bound {bound}",
        zero_at - t_last
    );
    assert!(zero_at - t_last > 100_000, "not before the timeout");
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert_eq!(rig.ctl.fault(), Fault::Watchdog);
    // Idle is requested once the stop completes.
    let idle = rig.log.iter().any(|(_, f)| {
        matches!(
            odrive::Command::decode(f).map(|a| a.msg),
            Ok(odrive::Command::SetAxisState(AxisState::Idle))
        )
    });
    assert!(idle);
}

/// A DJI rig whose watchdog stop is instant: zero current at the step the watchdog fires.
fn dji_instant_stop() -> Rig {
    let mut c = Config::dji_m3508_example();
    c.limits.stop_linear_decel = f32::INFINITY;
    c.limits.stop_angular_decel = f32::INFINITY;
    Rig::new(c)
}

/// What the host does after its last twist.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum AfterLastTwist {
    /// Sends nothing more.
    Silent,
    /// Repeats that last frame unchanged every 20 ms (50 Hz), as a stuck gateway would.
    Repeats,
}

/// Whole rig runs of a stop: a DJI rig with an instant stop drives at 0.5 m/s for 200 ms,
/// then the host sends its last twist and goes `after` for 400 ms.
struct StopRun {
    rig: Rig,
    /// When the last (new) twist arrived, µs.
    t_last: u64,
    /// The first step whose current frame is all zeros, µs (they stay zero to the end).
    t_zero: u64,
    /// When the repeats arrived, µs.
    repeats: Vec<u64>,
}

fn stop_after_last_twist(after: AfterLastTwist) -> StopRun {
    let mut rig = dji_instant_stop();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..20 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(10);
    }
    let last = Command::Twist(TwistCmd {
        vx: 0.5,
        vy: 0.0,
        wz: 0.0,
        seq: rig.seq,
    })
    .to_can_frame();
    rig.raw(last);
    let t_last = rig.now_us;
    let mut repeats = Vec::new();
    let mut t_zero = None;
    for k in 0..400u64 {
        if after == AfterLastTwist::Repeats && k > 0 && k.is_multiple_of(20) {
            rig.raw(last);
            repeats.push(rig.now_us);
        }
        let t = rig.now_us;
        let amps = dji_currents(&rig.tick()).expect("a current frame every period");
        if all_zero(amps) {
            t_zero.get_or_insert(t);
        } else {
            assert!(
                t_zero.is_none(),
                "{after:?}: current {amps:?} at {t} us after zero"
            );
        }
    }
    StopRun {
        rig,
        t_last,
        t_zero: t_zero.expect("currents reach zero"),
        repeats,
    }
}

#[test]
fn dji_zero_currents_within_timeout_plus_two_periods_with_an_instant_stop() {
    let run = stop_after_last_twist(AfterLastTwist::Silent);
    let dt = run.t_zero - run.t_last;
    assert!(dt > 100_000 && dt <= 102_000, "zero currents after {dt} us");
    assert_eq!(run.rig.ctl.snapshot().repeated_seq, 0);
}

#[test]
fn a_host_repeating_its_last_twist_frame_stops_the_robot_as_silence_does() {
    let silent = stop_after_last_twist(AfterLastTwist::Silent);
    let run = stop_after_last_twist(AfterLastTwist::Repeats);
    let dt = run.t_zero - run.t_last;
    assert!(
        dt > 100_000 && dt <= 102_000,
        "zero currents {dt} us after the last accepted twist"
    );
    assert_eq!(
        dt,
        silent.t_zero - silent.t_last,
        "the repeats moved the stop"
    );
    let snap = run.rig.ctl.snapshot();
    assert_eq!(
        (snap.state, snap.fault),
        (RobotState::Disabled, Fault::Watchdog)
    );
    // Every repeat is counted, those after the stop too, and none is a rejected frame.
    assert_eq!(run.repeats.len(), 19);
    assert_eq!(snap.repeated_seq, 19);
    assert_eq!(snap.rx_errors.total(), 0);
    // STATUS_COUNTERS follows every STATUS, in the same step, with the count at that step.
    let telemetry: Vec<(u64, robot::Telemetry)> = run
        .rig
        .log
        .iter()
        .filter_map(|(t, f)| robot::Telemetry::decode(f).ok().map(|m| (*t, m)))
        .filter(|(_, m)| {
            matches!(
                m,
                robot::Telemetry::Status(_) | robot::Telemetry::StatusCounters(_)
            )
        })
        .collect();
    assert!(telemetry.len() >= 2 * 6, "{} frames", telemetry.len());
    for pair in telemetry.chunks(2) {
        let [
            (t_s, robot::Telemetry::Status(_)),
            (t_c, robot::Telemetry::StatusCounters(c)),
        ] = pair
        else {
            panic!("STATUS and STATUS_COUNTERS not in pairs: {pair:?}");
        };
        assert_eq!(t_s, t_c);
        let due = run.repeats.iter().filter(|&t| t <= t_c).count();
        assert_eq!(usize::from(c.repeated_seq), due, "at {t_c} us");
        assert_eq!((c.wrong_dlc, c.out_of_range, c.non_finite), (0, 0, 0));
    }
    let (t_c, c) = run.rig.counters();
    assert!(t_c >= run.t_last + 300_000 && c.repeated_seq >= 15, "{c:?}");
}

#[test]
fn a_twist_with_the_last_accepted_seq_is_not_applied_even_with_other_values() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.twist_seq(0.2, 0.0, 0.0, 41);
    let t_accepted = rig.now_us;
    // The ramp to 0.2 m/s at 4 m/s² takes 50 ms.
    rig.run_ms(60);
    assert_eq!(rig.ctl.snapshot().commanded.vx, 0.2);
    // seq 41 again with other values, then beyond the limits: neither is applied; the
    // first is a repeat, the second a rejected frame (the limits are checked first).
    rig.twist_seq(1.0, 0.0, 0.5, 41);
    rig.twist_seq(5.0, 0.0, 0.0, 41);
    for _ in 0..41 {
        rig.tick();
        let snap = rig.ctl.snapshot();
        assert_eq!(
            (snap.commanded.vx, snap.commanded.wz, snap.fault),
            (0.2, 0.0, Fault::None),
            "at {} us",
            rig.now_us - t_accepted
        );
    }
    let snap = rig.ctl.snapshot();
    assert_eq!((snap.repeated_seq, snap.rx_errors.out_of_range), (1, 1));
    // Neither fed the watchdog: it fires 101 ms after the twist it accepted.
    assert_eq!(rig.now_us - t_accepted, 101_000);
    rig.tick();
    assert_eq!(rig.ctl.fault(), Fault::Watchdog);
}

#[test]
fn any_other_seq_is_accepted_wrapping_and_skipping_included() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    // One twist every 60 ms: a twist not accepted would leave 120 ms without one, and the
    // watchdog (100 ms) would fire.
    let seqs = [
        250u8, 251, 252, 253, 254, 255, 0, 1, 2, 9, 10, 200, 201, 17, 16, 255, 0, 128,
    ];
    for (k, &seq) in seqs.iter().enumerate() {
        let vx = 0.1 + 0.02 * k as f32;
        rig.twist_seq(vx, 0.0, 0.0, seq);
        rig.run_ms(60);
        let snap = rig.ctl.snapshot();
        assert_eq!(
            (snap.state, snap.fault),
            (RobotState::Enabled, Fault::None),
            "seq {seq}"
        );
        // Applied: the ramp (4 m/s²) has reached it, to the field's resolution of 1 mm/s.
        assert!(
            (snap.commanded.vx - vx).abs() < 1e-6,
            "seq {seq} was not applied: {} m/s",
            snap.commanded.vx
        );
    }
    assert_eq!(rig.ctl.snapshot().repeated_seq, 0);
}

#[test]
fn the_first_twist_after_an_enable_or_a_reset_is_accepted_whatever_its_seq() {
    let mut rig = dji_instant_stop();
    rig.run_ms(5);
    rig.enable();
    rig.twist_seq(0.3, 0.0, 0.0, 77);
    rig.run_ms(150);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::Watchdog)
    );
    // The same frame while stopped: counted, and nothing moves.
    for _ in 0..3 {
        rig.twist_seq(0.3, 0.0, 0.0, 77);
        assert!(dji_currents(&rig.tick()).is_some_and(all_zero));
    }
    assert_eq!(rig.ctl.snapshot().repeated_seq, 3);
    // Back to driving after the watchdog stop, after a disable, after an e-stop and a reset:
    // each time the first twist after the enable carries the seq accepted before.
    for way in ["watchdog stop", "disable", "e-stop and reset"] {
        match way {
            "disable" => rig.send(Command::Mode(ModeRequest::Disable)),
            "e-stop and reset" => {
                rig.send(Command::Estop);
                rig.tick();
                assert_eq!(rig.ctl.state(), RobotState::Estop);
                rig.send(Command::Mode(ModeRequest::Reset));
            }
            _ => {}
        }
        rig.tick();
        assert_eq!(rig.ctl.state(), RobotState::Disabled, "{way}");
        rig.enable();
        rig.twist_seq(0.3, 0.0, 0.0, 77);
        let moved = rig.run_until(3, |_, o| dji_currents(o).is_some_and(|a| a[0] > 0.0));
        assert!(
            moved.is_some(),
            "after the {way}: the twist was not accepted"
        );
        rig.run_ms(50);
        assert_eq!(rig.ctl.fault(), Fault::None, "{way}");
    }
    assert_eq!(rig.ctl.snapshot().repeated_seq, 3);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Against a model of the rule: a twist is a repeat exactly when its seq equals the last
    /// accepted one's (small alphabets, wrap-around included, so that repeats are common).
    #[test]
    fn repeats_are_exactly_the_twists_with_the_last_accepted_seq(
        seqs in prop::collection::vec(prop_oneof![0u8..3, 254u8..=255], 1..200),
    ) {
        let mut rig = Rig::dji();
        rig.run_ms(5);
        rig.enable();
        rig.tick();
        let (mut last, mut repeats) = (None, 0u32);
        for &seq in &seqs {
            // All at one instant: no step runs, so the watchdog cannot intervene.
            rig.twist_seq(0.1, 0.0, 0.0, seq);
            if last == Some(seq) {
                repeats += 1;
            } else {
                last = Some(seq);
            }
        }
        let snap = rig.ctl.snapshot();
        prop_assert_eq!(snap.repeated_seq, repeats);
        prop_assert_eq!(snap.rx_errors.total(), 0);
    }
}

#[test]
fn finite_stop_deceleration_ramps_down_at_the_configured_limit() {
    let mut c = Config::odrive_example();
    c.limits.stop_linear_decel = 5.0; // m/s²: 0.5 m/s -> 0 in 100 ms
    let mut rig = Rig::new(c);
    rig.run_ms(20);
    rig.enable();
    for _ in 0..30 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(10);
    }
    rig.twist(0.5, 0.0, 0.0);
    let t_last = rig.now_us;
    let t_zero = rig
        .run_until(500, |r, o| odrive_vels(&r.config, o).is_some_and(all_zero))
        .unwrap();
    let dt = t_zero - t_last;
    // Timeout 100 ms + 100 ms of ramp, within two setpoint periods.
    assert!(
        (200_000..=210_000).contains(&dt),
        "zero after {dt} us, want 200-210 ms"
    );
}

#[test]
fn status_polls_and_mode_commands_do_not_keep_motion_alive() {
    let mut quiet = Rig::odrive();
    let (q_last, q_zero) = watchdog_zero_time(&mut quiet, false);
    let mut polled = Rig::odrive();
    let (p_last, p_zero) = watchdog_zero_time(&mut polled, true);
    assert_eq!(
        q_zero - q_last,
        p_zero - p_last,
        "status polls changed the stop time"
    );
    // Status requests were answered.
    let statuses = polled
        .log
        .iter()
        .filter(|(_, f)| matches!(robot::Telemetry::decode(f), Ok(robot::Telemetry::Status(_))))
        .count();
    let periodic = polled.log.last().unwrap().0 / 100_000 + 1;
    assert!(statuses as u64 > periodic + 50, "{statuses} status frames");
}

/// `frame` with its data replaced: `edit` gets the 8-byte buffer, `dlc` sets the length.
fn tampered(frame: CanFrame, dlc: u8, edit: impl FnOnce(&mut [u8; 8])) -> CanFrame {
    let mut data = [0u8; 8];
    let src = embedded_can::Frame::data(&frame);
    data[..src.len()].copy_from_slice(src);
    edit(&mut data);
    let id = embedded_can::Frame::id(&frame);
    let embedded_can::Id::Standard(id) = id else {
        panic!("standard ids only")
    };
    CanFrame::from_buffer(id, data, dlc)
}

#[test]
fn rejected_commands_are_counted_and_never_feed_the_watchdog() {
    let twist = |vx| {
        Command::Twist(TwistCmd {
            vx,
            vy: 0.0,
            wz: 0.0,
            seq: 1,
        })
    };
    // Faster than limits.max_linear_speed (3 m/s): rejected by the core.
    let too_fast = twist(5.0).to_can_frame();
    // vx raw = -32768, reserved as invalid: rejected by the decoder.
    let reserved = tampered(twist(0.1).to_can_frame(), 8, |d| {
        d[0] = 0x00;
        d[1] = 0x80;
    });
    // Wrong DLC.
    let short = tampered(twist(0.1).to_can_frame(), 5, |_| {});

    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    rig.twist(0.3, 0.0, 0.0);
    let t_cmd = rig.now_us;
    let mut zero_at = None;
    for _ in 0..300 {
        rig.raw(too_fast);
        rig.raw(reserved);
        rig.raw(short);
        let t = rig.now_us;
        let out = rig.tick();
        if odrive_vels(&rig.config, &out).is_some_and(all_zero) {
            zero_at.get_or_insert(t);
        }
    }
    let dt = zero_at.expect("watchdog stopped the robot") - t_cmd;
    assert!(dt <= 110_000, "invalid commands kept it alive: {dt} us");
    rig.send(Command::StatusRequest);
    rig.tick();
    let snap = rig.ctl.snapshot();
    assert_eq!(snap.rx_errors.out_of_range, 600);
    assert_eq!(snap.rx_errors.wrong_dlc, 300);
    let status = rig.status();
    assert_eq!(status.rx_errors, 900);
    assert_eq!(status.unknown_ids, 0);
}

/// A frame as a driver that reports the DLC register unchanged gives it (embassy-stm32 0.6):
/// a classic frame may carry DLC 9-15, and `data()` slices the 8-byte buffer by the DLC.
struct RawDlcFrame {
    id: embedded_can::Id,
    dlc: usize,
    data: [u8; 8],
}

impl embedded_can::Frame for RawDlcFrame {
    fn new(_: impl Into<embedded_can::Id>, _: &[u8]) -> Option<Self> {
        None
    }
    fn new_remote(_: impl Into<embedded_can::Id>, _: usize) -> Option<Self> {
        None
    }
    fn is_extended(&self) -> bool {
        false
    }
    fn is_remote_frame(&self) -> bool {
        false
    }
    fn id(&self) -> embedded_can::Id {
        self.id
    }
    fn dlc(&self) -> usize {
        self.dlc
    }
    fn data(&self) -> &[u8] {
        &self.data[..self.dlc]
    }
}

#[test]
fn a_dlc_above_8_is_a_wrong_dlc_not_a_panic() {
    for (mut rig, ids) in [
        (Rig::dji(), [0x201u16, 0x301, 0x300]),
        (Rig::odrive(), [0x009, 0x001, 0x301]),
    ] {
        rig.run_ms(5);
        let before = rig.ctl.snapshot().rx_errors.wrong_dlc;
        for id in ids {
            for dlc in 9..=15 {
                let frame = RawDlcFrame {
                    id: embedded_can::StandardId::new(id).unwrap().into(),
                    dlc,
                    data: [0; 8],
                };
                rig.ctl.on_frame(rig.now(), &frame);
                assert_eq!(CanFrame::from_frame(&frame), None);
            }
        }
        assert_eq!(rig.ctl.snapshot().rx_errors.wrong_dlc - before, 3 * 7);
    }
}

#[test]
fn non_finite_feedback_is_rejected_and_counted() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    let node = NodeId::new(0).unwrap();
    let est = odrive::Feedback::EncoderEstimates { pos: 1.0, vel: 0.0 }.to_can_frame(node);
    let f = tampered(est, 8, |d| d[0..4].copy_from_slice(&f32::NAN.to_le_bytes()));
    let pose_before = rig.ctl.pose();
    rig.raw(f);
    rig.run_ms(1);
    assert_eq!(rig.ctl.snapshot().rx_errors.non_finite, 1);
    assert_eq!(rig.ctl.pose(), pose_before);
}

#[test]
fn another_hosts_odrive_requests_are_neither_feedback_nor_errors() {
    let mut rig = odrive_driving();
    let pose_before = rig.ctl.pose();
    let before = rig.ctl.snapshot().rx_errors;
    let node = NodeId::new(0).unwrap();
    // An odrivetool-style poll of every message the core reads, as RTR and as empty frames.
    for cmd in [
        odrive::Command::GetHeartbeat,
        odrive::Command::GetError,
        odrive::Command::GetEncoderEstimates,
    ] {
        let rtr = cmd.to_can_frame(node);
        rig.raw(rtr);
        rig.raw(tampered(rtr, 0, |_| {}));
    }
    rig.run_ms(1);
    let snap = rig.ctl.snapshot();
    assert_eq!(snap.rx_errors, before, "requests counted as errors");
    assert_eq!(snap.state, RobotState::Enabled);
    // The pose moved by the step's driving only, not by a request read as estimates.
    assert!((rig.ctl.pose().x - pose_before.x).abs() < 1e-3);
}

#[test]
fn unknown_ids_are_counted_separately() {
    let mut rig = Rig::dji();
    rig.run_ms(2);
    for id in [0x123u16, 0x7FF, 0x209] {
        rig.raw(CanFrame::from_buffer(
            embedded_can::StandardId::new(id).unwrap(),
            [0; 8],
            8,
        ));
    }
    rig.send(Command::StatusRequest);
    rig.tick();
    let s = rig.status();
    assert_eq!((s.unknown_ids, s.rx_errors), (3, 0));
    assert_eq!(s.motors_online, 0b1111);
}

#[test]
fn a_stale_motor_faults_within_three_feedback_periods() {
    let mut rig = Rig::dji();
    rig.run_ms(10);
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(5);
    rig.alive[2] = false; // RL goes silent
    let t_silent = rig.now_us;
    let t_fault = rig
        .run_until(50, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("stale motor faults");
    assert_eq!(rig.ctl.fault(), Fault::MotorStale);
    // Last feedback at t_silent - 1 ms; stale after 3 ms; seen at the next step.
    assert!(t_fault - t_silent <= 4_000, "{} us", t_fault - t_silent);
    // A stale motor is not online.
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().motors_online, 0b1011);
    // Fault means no torque.
    assert!(dji_currents(&rig.tick()).is_some_and(all_zero));
    // Reset while the motor is still silent faults again; back alive, reset clears it.
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    rig.alive[2] = true;
    rig.tick();
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(5);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
}

#[test]
fn a_motor_never_seen_faults_after_the_boot_timeout() {
    let mut rig = Rig::dji();
    rig.alive[1] = false;
    let t = rig
        .run_until(2000, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("missing motor faults");
    assert_eq!(rig.ctl.fault(), Fault::MotorMissing);
    assert_eq!(
        t, 1_001_000,
        "boot timeout 1000 ms, detected on the next step"
    );
    assert_eq!(rig.status().motors_online, 0b1101);
}

#[test]
fn the_latch_holds_until_enable_and_a_fresh_command() {
    let mut rig = Rig::odrive();
    let _ = watchdog_zero_time(&mut rig, false);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    // Twists alone do nothing.
    for _ in 0..20 {
        rig.twist(0.4, 0.0, 0.0);
        let out = rig.tick();
        assert!(odrive_vels(&rig.config, &out).is_none_or(all_zero));
    }
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    // Enable alone: enabled, but holding still (no fresh command yet).
    rig.enable();
    for _ in 0..50 {
        let out = rig.tick();
        assert!(odrive_vels(&rig.config, &out).is_none_or(all_zero));
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    // A fresh command after the enable moves it.
    rig.twist(0.4, 0.0, 0.0);
    let moved = rig.run_until(20, |r, o| {
        odrive_vels(&r.config, o).is_some_and(|v| v[0] > 0.0)
    });
    assert!(moved.is_some());
}

#[test]
fn estop_latches_until_reset_then_enable_and_a_fresh_command() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..10 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(10);
    }
    rig.send(Command::Estop);
    let out = rig.tick();
    assert!(
        dji_currents(&out).is_some_and(all_zero),
        "e-stop cuts torque at once"
    );
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    // Enable and twists are ignored while e-stopped.
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    rig.run_ms(20);
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().state, RobotState::Estop);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    let out = rig.tick();
    assert!(dji_currents(&out).is_some_and(|a| a[0] > 0.0));
}

#[test]
fn odometry_follows_the_wheels_and_is_published_at_100_hz() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    // Wheels turning as for 0.5 m/s forward (motor sign: right side mirrored).
    let w = 0.5 / 0.076;
    rig.speed = [w, -w, w, -w];
    let start = rig.log.len();
    rig.run_ms(1000);
    let pose = rig.ctl.pose();
    assert!((pose.x - 0.5).abs() < 2e-3, "x = {}", pose.x);
    assert!(pose.y.abs() < 1e-3 && pose.heading.abs() < 1e-3);
    let positions: Vec<_> = rig.log[start..]
        .iter()
        .filter_map(|(t, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::OdomPosition(p)) => Some((*t, p)),
            _ => None,
        })
        .collect();
    assert_eq!(positions.len(), 100);
    let v = rig.ctl.snapshot().measured;
    assert!((v.vx - 0.5).abs() < 0.01, "measured vx {}", v.vx);
}

/// `config` with its `lateral_effectiveness` set to `k`.
fn with_lateral_effectiveness(mut config: Config, k: f32) -> Config {
    let Geometry::Standard {
        lateral_effectiveness,
        ..
    } = &mut config.geometry
    else {
        panic!("the examples are standard layouts")
    };
    *lateral_effectiveness = k;
    config
}

#[test]
fn a_lateral_effectiveness_scales_the_odometry_of_the_same_wheel_motion_by_itself() {
    // The same wheels (0.3 m/s forward and 0.5 m/s to the left as the ideal model reads
    // them) into a default controller and one configured with lateral_effectiveness 0.72.
    let mut ideal = Rig::dji();
    let mut slip = Rig::new(with_lateral_effectiveness(
        Config::dji_m3508_example(),
        0.72,
    ));
    let (f, l) = (0.3 / 0.076, 0.5 / 0.076);
    // Wheel speeds FL, FR, RL, RR = f - l, f + l, f + l, f - l; motor sign: right mirrored.
    let motor = [f - l, -(f + l), f + l, -(f - l)];
    for rig in [&mut ideal, &mut slip] {
        rig.run_ms(5);
        rig.speed = motor;
        rig.run_ms(1000);
    }
    let (a, b) = (ideal.ctl.pose(), slip.ctl.pose());
    assert!(
        (a.y - 0.5).abs() < 2e-3 && (a.x - 0.3).abs() < 2e-3,
        "{a:?}"
    );
    // The lateral odometry by exactly the factor, the rest unchanged: to f32 rounding, and
    // to what the heading (a few µrad from the encoder quantisation, the same bits in both)
    // carries between the axes, (1 - 0.72) times the other axis' travel times sin(heading).
    assert_eq!(b.heading.to_bits(), a.heading.to_bits());
    let turned = |travel: f32| (1.0 - 0.72) * travel * a.heading.abs();
    assert!(a.heading.abs() < 1e-5, "{a:?}");
    assert!(
        (b.y - 0.72 * a.y).abs() <= turned(a.x) + 1e-6 * a.y,
        "{} vs 0.72 * {}",
        b.y,
        a.y
    );
    assert!(
        (b.x - a.x).abs() <= turned(a.y) + 1e-6 * a.x,
        "{} vs {}",
        b.x,
        a.x
    );
    let (va, vb) = (ideal.ctl.snapshot().measured, slip.ctl.snapshot().measured);
    assert!(
        (vb.vy - 0.72 * va.vy).abs() <= 1e-6 * va.vy,
        "{vb:?} vs {va:?}"
    );
    assert_eq!(vb.vx.to_bits(), va.vx.to_bits());
    assert_eq!(vb.wz.to_bits(), va.wz.to_bits());
    // And the ODOM_POSITION frames say so (0.1 mm resolution).
    let last_y = |rig: &Rig| {
        rig.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::OdomPosition(p)) => Some(p.y),
                _ => None,
            })
            .expect("odometry frames")
    };
    assert!((last_y(&slip) - 0.72 * last_y(&ideal)).abs() <= 2e-4);
}

#[test]
fn a_lateral_effectiveness_asks_the_wheels_for_the_strafe_divided_by_it() {
    let setpoints = |config: Config| {
        let mut c = config;
        c.limits.stop_linear_decel = f32::INFINITY;
        c.limits.stop_angular_decel = f32::INFINITY;
        let mut rig = Rig::new(c);
        rig.run_ms(20);
        rig.enable();
        // 0.5 m/s to the left; the ramp at 4 m/s² takes 125 ms.
        for _ in 0..10 {
            rig.twist(0.0, 0.5, 0.0);
            rig.run_ms(20);
        }
        rig.twist(0.0, 0.5, 0.0);
        (0..5)
            .filter_map(|_| {
                let out = rig.tick();
                odrive_vels(&rig.config, &out)
            })
            .last()
            .expect("setpoints every 5 ms at 200 Hz")
    };
    let ideal = setpoints(Config::odrive_example());
    let slip = setpoints(with_lateral_effectiveness(Config::odrive_example(), 0.72));
    // Wheels FL, FR, RL, RR = (-a, a, a, -a) with a = 0.5 / 0.72 / 0.05 rad/s; motor rev/s
    // through the 5:1 belt, the right side mirrored: (-m, -m, m, m).
    let m = 0.5 / 0.72 / 0.05 * 5.0 / std::f32::consts::TAU;
    for (w, want) in [-m, -m, m, m].into_iter().enumerate() {
        assert!((slip[w] - want).abs() <= 1e-5 * m, "{slip:?} vs {want}");
        assert!(
            (slip[w] * 0.72 - ideal[w]).abs() <= 1e-5 * m,
            "{slip:?} vs {ideal:?}"
        );
    }
}

#[test]
fn same_inputs_same_frames_bit_for_bit() {
    let run = || {
        let mut rig = Rig::dji();
        rig.run_ms(5);
        rig.enable();
        for k in 0..50 {
            rig.twist(0.01 * k as f32, -0.005 * k as f32, 0.02 * k as f32);
            rig.speed = [
                k as f32 * 0.1,
                -(k as f32) * 0.1,
                k as f32 * 0.12,
                -(k as f32) * 0.09,
            ];
            rig.run_ms(7);
        }
        rig.log
    };
    let (a, b) = (run(), run());
    assert!(a.len() > 300);
    assert_eq!(a, b);
}

#[test]
fn shutdown_sends_zero_and_idle() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    rig.twist(0.3, 0.0, 0.0);
    rig.run_ms(50);
    let out = rig.ctl.shutdown();
    let mut zero = 0;
    let mut idle = 0;
    for f in &out {
        match odrive::Command::decode(f).map(|a| a.msg) {
            Ok(odrive::Command::SetInputVel { vel: 0.0, .. }) => zero += 1,
            Ok(odrive::Command::SetAxisState(AxisState::Idle)) => idle += 1,
            _ => {}
        }
    }
    assert_eq!((zero, idle), (4, 4));
    let mut dji = Rig::dji();
    dji.run_ms(5);
    assert!(dji_currents(&dji.ctl.shutdown()).is_some_and(all_zero));
}

/// The rotor speed (rpm) a DJI rig reports for wheel `w` now.
fn rig_rpm(rig: &Rig, w: usize) -> i16 {
    let Drive::Dji { gear_ratio, .. } = rig.config.drive else {
        panic!("not a DJI config")
    };
    (rig.speed[w] * gear_ratio * 60.0 / std::f32::consts::TAU).round() as i16
}

/// A DJI rig enabled and driving with `twist`, its wheels following the setpoints exactly.
fn dji_driving(twist: [f32; 3], ms: u64) -> Rig {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    follow(&mut rig, twist, ms);
    rig
}

/// Streams `twist` every 10 ms for `ms` while the wheels follow the core's setpoints with a
/// 10 ms lag (so the velocity loops work and command current).
fn follow(rig: &mut Rig, [vx, vy, wz]: [f32; 3], ms: u64) {
    for k in 0..ms {
        if k % 10 == 0 {
            rig.twist(vx, vy, wz);
        }
        rig.tick();
        let sp = rig.ctl.snapshot().wheel_setpoints.0;
        // Motor sign: the right-hand motors are mirrored.
        for (w, s) in [sp[0], -sp[1], sp[2], -sp[3]].into_iter().enumerate() {
            rig.speed[w] += (s - rig.speed[w]) * 0.1;
        }
    }
}

#[test]
fn a_stuck_encoder_that_still_reports_speed_faults_within_its_window() {
    use firmware::control::ENCODER_STUCK_SPINNING_US;
    // Cruising at 0.5 m/s: wheel 6.6 rad/s, rotor ~1200 rpm.
    let mut rig = dji_driving([0.5, 0.0, 0.0], 300);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    // RL's encoder freezes: the same angle and the same rpm in every frame from now on.
    let angle = rig.rotor[2].rem_euclid(8192.0) as u16;
    rig.frozen[2] = Some((angle, rig_rpm(&rig, 2)));
    let t_stuck = rig.now_us;
    let t_fault = rig
        .run_until(100, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the stuck encoder is found");
    assert_eq!(rig.ctl.fault(), Fault::EncoderStuck);
    // The first repeated angle arrives one feedback period after the freeze, is seen by the
    // next step, and the interval must then last the window.
    let latency = t_fault - t_stuck;
    assert!(
        (ENCODER_STUCK_SPINNING_US..=ENCODER_STUCK_SPINNING_US + 3_000).contains(&latency),
        "{latency} us"
    );
    assert!(dji_currents(&rig.tick()).is_some_and(all_zero));
    // A reset while it is still stuck faults again; once the encoder is back, reset clears.
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(2);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Fault, Fault::EncoderStuck)
    );
    rig.frozen[2] = None;
    rig.speed = [0.0; 4];
    rig.run_ms(2);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(50);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
}

#[test]
fn an_encoder_reading_zero_while_driven_and_the_others_turn_faults_within_its_window() {
    use firmware::control::ENCODER_STUCK_DRAGGED_US;
    // Turning while driving: every wheel at a different speed.
    let mut rig = dji_driving([0.4, 0.1, 0.8], 300);
    // FR's encoder dies reading zero speed at a fixed angle; the wheel itself keeps turning
    // with the chassis, so its PI sees a full error and drives it hard.
    let angle = rig.rotor[1].rem_euclid(8192.0) as u16;
    rig.frozen[1] = Some((angle, 0));
    let t_stuck = rig.now_us;
    let t_fault = rig
        .run_until(200, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the dead encoder is found");
    assert_eq!(rig.ctl.fault(), Fault::EncoderStuck);
    let latency = t_fault - t_stuck;
    assert!(
        (ENCODER_STUCK_DRAGGED_US..=ENCODER_STUCK_DRAGGED_US + 3_000).contains(&latency),
        "{latency} us"
    );
}

#[test]
fn a_genuinely_stalled_drive_is_not_a_stuck_encoder() {
    // Commanded forward, but the robot is against a wall: every rotor stands at rpm 0, every
    // PI saturates at max_current, for a whole second.
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..100 {
        rig.twist(0.8, 0.0, 0.0);
        rig.run_ms(10);
    }
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(
        amps.iter()
            .all(|a| a.abs() >= rig.config.limits.max_current - 0.01)
    );
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Enabled, Fault::None)
    );
    // Turning on the spot against the obstacle: the same.
    for _ in 0..50 {
        rig.twist(0.0, 0.0, 1.0);
        rig.run_ms(10);
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn normal_driving_never_looks_like_a_stuck_encoder() {
    let mut rig = dji_driving([0.0, 0.0, 0.0], 20);
    // Starts, stops, reversals (every wheel passes through zero speed), slow creeping (a
    // rotor moving a count at a time), strafes and turns on the spot.
    for twist in [
        [0.5, 0.0, 0.0],
        [-0.5, 0.0, 0.0],
        [0.0, 0.4, 0.0],
        [0.0, -0.4, 1.5],
        [0.002, 0.0, 0.0],
        [0.3, 0.3, -2.0],
        [0.0, 0.0, 0.0],
        [1.5, -0.5, 0.5],
    ] {
        follow(&mut rig, twist, 400);
        assert_eq!(
            (rig.ctl.state(), rig.ctl.fault()),
            (RobotState::Enabled, Fault::None),
            "{twist:?}"
        );
    }
}

/// Clear_Errors frames in a step's output: the node ids they go to.
fn clear_errors_nodes(out: &Outbox) -> Vec<u8> {
    out.iter()
        .filter_map(|f| match odrive::Command::decode(f) {
            Ok(a) if matches!(a.msg, odrive::Command::ClearErrors { .. }) => Some(a.node.get()),
            _ => None,
        })
        .collect()
}

/// An ODrive enabled and driving forward after its first heartbeats.
fn odrive_driving() -> Rig {
    let mut rig = Rig::odrive();
    rig.run_ms(150);
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(50);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    rig
}

#[test]
fn a_reset_clears_an_odrive_drive_error_and_the_robot_can_drive_again() {
    let mut rig = odrive_driving();
    rig.axis_error[1] = 0x0100_0000; // the axis watchdog expired
    rig.run_until(150, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the heartbeat's error faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveError);
    rig.run_ms(300);
    assert_eq!(rig.ctl.state(), RobotState::Fault, "latched");

    rig.send(Command::Mode(ModeRequest::Reset));
    // A heartbeat sent before the drive got Clear_Errors still carries the error: ignored.
    rig.raw(odrive_heartbeat(1, AxisState::Idle, 0x0100_0000));
    let out = rig.tick();
    assert_eq!(clear_errors_nodes(&out), [0, 1, 2, 3]);
    // Three heartbeat periods later the errors are gone and nothing faulted again.
    rig.run_ms(300);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(20);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    let vels = (0..20)
        .find_map(|_| {
            let out = rig.tick();
            odrive_vels(&rig.config, &out)
        })
        .expect("setpoints at their rate");
    assert!(vels[0] > 0.0, "{vels:?}");
}

#[test]
fn an_odrive_error_whose_cause_persists_faults_again_after_the_reset() {
    let mut rig = odrive_driving();
    rig.axis_error[2] = 0x0000_0800; // a hardware fault: Clear_Errors does not remove it
    rig.error_persists[2] = true;
    rig.run_until(150, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("faults");
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    let t = rig
        .run_until(300, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the first heartbeat after the grace faults again");
    assert_eq!(rig.ctl.fault(), Fault::DriveError);
    // Heartbeats every 100 ms; the first one more than 150 ms after the clear.
    assert!(t - t_reset <= 251_000, "{} us", t - t_reset);
}

#[test]
fn an_odrive_position_jump_is_not_integrated_and_is_counted() {
    let mut rig = Rig::odrive();
    rig.run_ms(50);
    // The drive on wheel 0 reboots: its position estimate restarts 1000 turns lower.
    rig.rotor[0] -= 1000.0;
    rig.run_ms(50);
    let s = rig.ctl.snapshot();
    assert_eq!(s.rx_errors.out_of_range, 1);
    assert!(
        s.pose.x.abs() < 1e-6 && s.pose.y.abs() < 1e-6 && s.pose.heading.abs() < 1e-6,
        "{:?}",
        s.pose
    );
    // The new count is the reference from then on: driving moves the pose as usual.
    let Drive::Odrive { inverted, .. } = rig.config.drive else {
        unreachable!()
    };
    let w = 0.5 / 0.05; // the example's 50 mm wheels
    rig.speed = inverted.map(|i| if i { -w } else { w });
    rig.run_ms(1000);
    let x = rig.ctl.pose().x;
    assert!((x - 0.5).abs() < 0.02, "x = {x}");
    assert_eq!(rig.ctl.snapshot().rx_errors.out_of_range, 1);
}

#[test]
fn a_twist_stamped_earlier_does_not_move_the_watchdog_back() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(50);
    rig.twist(0.2, 0.0, 0.0);
    let t_last = rig.now_us;
    // The same setpoint in a frame of its own (a new seq) arriving late, stamped 40 ms before
    // the last one.
    let late = Command::Twist(TwistCmd {
        vx: 0.2,
        vy: 0.0,
        wz: 0.0,
        seq: rig.seq,
    })
    .to_can_frame();
    rig.ctl
        .on_frame(Instant::from_micros(t_last - 40_000), &late);
    let timeout_us = u64::from(rig.config.timing.command_timeout_ms) * 1000;
    rig.run_ms(timeout_us / 1000 - 1);
    assert_eq!(
        rig.ctl.fault(),
        Fault::None,
        "the watchdog counts from {t_last}"
    );
    rig.run_ms(3);
    assert_eq!(rig.ctl.fault(), Fault::Watchdog);
}

#[test]
fn the_heartbeat_uptime_wraps_after_2_pow_32_ms() {
    let mut rig = Rig::dji();
    rig.run_ms(1);
    rig.now_us += (1u64 << 32) * 1000;
    rig.run_ms(200);
    let uptime = rig
        .log
        .iter()
        .rev()
        .find_map(|(_, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::Heartbeat(h)) => Some(h.uptime_ms),
            _ => None,
        })
        .unwrap();
    assert!((1..=201).contains(&uptime), "uptime {uptime} ms");
}

/// An ODrive heartbeat from `node` (trajectory done, no procedure result).
fn odrive_heartbeat(node: u8, axis_state: AxisState, axis_error: u32) -> CanFrame {
    odrive::Feedback::Heartbeat(odrive::Heartbeat {
        axis_error,
        axis_state,
        procedure_result: 0,
        trajectory_done: true,
    })
    .to_can_frame(NodeId::new(node).unwrap())
}

#[test]
fn an_odrive_axis_that_leaves_closed_loop_while_enabled_faults() {
    // Right after the enable, a heartbeat still reporting Idle predates the request.
    let mut rig = Rig::odrive();
    rig.run_ms(150);
    rig.enable();
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    rig.run_ms(10);
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Enabled);

    // Later, an axis reporting Idle with no error (another node commanded it, a reboot that
    // kept its errors to itself) cannot follow its setpoints: the robot faults.
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_ms(10);
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Fault, Fault::DriveError)
    );
}

// ------------------------------------------------------------------------------------------
// Gyro heading (`odometry.heading_source = "gyro"`, `IMU_YAW_RATE`)

/// The DJI example with the heading from the gyro.
fn gyro_config() -> Config {
    let mut c = Config::dji_m3508_example();
    c.odometry.heading_source = firmware::config::HeadingMode::Gyro;
    c
}

impl Rig {
    /// Sends an `IMU_YAW_RATE`.
    fn gyro(&mut self, yaw_rate: f32, seq: u8) {
        self.send(Command::ImuYawRate(robot::ImuYawRate { yaw_rate, seq }));
    }

    /// Runs `ms` steps with a 200 Hz IMU reading `rate` (its frames at every 5th ms, `seq`
    /// counting on from `*seq`).
    fn run_with_gyro(&mut self, ms: u64, rate: f32, seq: &mut u8) {
        for _ in 0..ms {
            if (self.now_us / 1000).is_multiple_of(5) {
                self.gyro(rate, *seq);
                *seq = seq.wrapping_add(1);
            }
            self.tick();
        }
    }

    /// The last `ODOM_VELOCITY` sent.
    fn odom_velocity(&self) -> robot::OdomVelocity {
        self.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::OdomVelocity(v)) => Some(v),
                _ => None,
            })
            .expect("an odometry frame was sent")
    }
}

#[test]
fn gyro_heading_is_the_rate_less_the_bias_learned_standing_still() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let bias = 0.002f32; // 0.115 °/s
    let mut seq = 0;
    // Disabled, wheels at rest: the bias is learned once the robot has stood still for
    // gyro_standstill_ms (50 ms); until then the uncorrected rate turns the heading.
    rig.run_with_gyro(1000, bias, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!(s.heading_source, HeadingSource::Gyro);
    assert_eq!(rig.status().heading_source, HeadingSource::Gyro);
    assert!((s.gyro_bias - bias).abs() < 1e-7, "bias {}", s.gyro_bias);
    // Frames at 50..995 ms (the standstill began at the first step, t = 0).
    assert_eq!(s.gyro_bias_samples, 190);
    let before = rig.ctl.pose().heading;
    // 50 ms at the uncorrected rate (and 1 ms more: the first frame counts from the step
    // after it), then nothing.
    assert!(
        (before - bias * 0.051).abs() < 2e-6,
        "heading {before} after the standstill"
    );
    rig.run_with_gyro(100, bias, &mut seq);
    assert!((rig.ctl.pose().heading - before).abs() < 1e-6);

    // Pushed forward at 0.2 m/s with the wheels turning (not at rest from the step that
    // sees them turn: no more bias samples) while the gyro reads 0.5 rad/s: the rotation is
    // the gyro's less the bias, the translation the wheels'.
    let wheel = 0.2 / 0.076;
    rig.speed = [wheel, -wheel, wheel, -wheel];
    rig.gyro(bias, seq);
    seq += 1;
    rig.tick();
    let samples = rig.ctl.snapshot().gyro_bias_samples;
    let before = rig.ctl.pose().heading;
    rig.run_with_gyro(1000, 0.5 + bias, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!(s.gyro_bias_samples, samples);
    let turned = rig.ctl.pose().heading - before;
    // From the first frame at the new rate on: 996 steps.
    assert!((turned - 0.5 * 0.996).abs() < 1e-4, "turned {turned} rad");
    assert!((s.measured.wz - 0.5).abs() < 1e-6, "wz {}", s.measured.wz);
    assert!((rig.odom_velocity().wz - 0.5).abs() <= 0.0005);
    // 0.2 m along an arc turning 0.5 rad: the chord's length 2 sin(0.25) / 0.5 * 0.2.
    let p = rig.ctl.pose();
    let chord = p.x.hypot(p.y);
    let want = 2.0 * (0.25f32).sin() / 0.5 * 0.2;
    assert!((chord - want).abs() < 2e-3, "chord {chord}, want {want}");
    assert!(
        p.y > 0.04,
        "the arc bends left (counter-clockwise): y {}",
        p.y
    );
}

#[test]
fn the_bias_is_not_learned_while_moving_or_when_switched_off() {
    // Enabled and commanded to drive, the wheels still at rest (just starting): not a
    // standstill.
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    rig.enable();
    for _ in 0..50 {
        rig.twist(0.3, 0.0, 0.0);
        rig.run_with_gyro(10, 0.01, &mut seq);
    }
    assert_eq!(rig.ctl.snapshot().gyro_bias_samples, 0);

    let mut config = gyro_config();
    config.odometry.gyro_bias_estimation = false;
    let mut rig = Rig::new(config);
    rig.run_with_gyro(1000, 0.01, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!((s.gyro_bias, s.gyro_bias_samples), (0.0, 0));
    // The whole bias turns the heading: 0.01 rad/s for 999 steps.
    assert!((rig.ctl.pose().heading - 0.00999).abs() < 2e-5);
}

#[test]
fn a_silent_gyro_hands_the_heading_to_the_wheels_and_takes_it_back() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    // Not heard yet: the wheels, and the reason.
    rig.run_ms(200);
    assert_eq!(rig.status().heading_source, HeadingSource::WheelsGyroSilent);
    rig.run_with_gyro(300, 0.0, &mut seq);
    assert_eq!(rig.status().heading_source, HeadingSource::Gyro);

    // Driving, the gyro reads a turn the wheels do not see (the wheels say straight).
    rig.enable();
    let wheel = 0.2 / 0.076;
    rig.speed = [wheel, -wheel, wheel, -wheel];
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_with_gyro(10, 0.3, &mut seq);
    }
    // The last frame went out at the last multiple of 5 ms; then silence.
    let last_frame_us = (rig.now_us - 1000) / 5000 * 5000;
    let (heading, heading_us) = (rig.ctl.pose().heading, rig.now_us);
    let mut fell_back = None;
    // 200 ms: a STATUS goes out after the fallback.
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        for _ in 0..10 {
            let t = rig.now_us;
            rig.tick();
            if fell_back.is_none() && rig.ctl.heading_source() == HeadingSource::WheelsGyroSilent {
                fell_back = Some(t);
            }
        }
    }
    // gyro_timeout_ms = 50: the first step more than 50 ms after the last frame.
    assert_eq!(fell_back, Some(last_frame_us + 51_000));
    // A warning, not a fault: still driving.
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Enabled, Fault::None)
    );
    let s = rig.status();
    assert_eq!(
        (s.state, s.heading_source),
        (RobotState::Enabled, HeadingSource::WheelsGyroSilent)
    );
    // Meanwhile the wheels' heading (straight, but for the scripted encoders' rounding: a
    // few 1e-4 rad over these 150 ms) held, after the gyro's turn until the fallback.
    let silent_turn = rig.ctl.pose().heading - heading;
    let gyro_turn = 0.3 * (last_frame_us + 51_000 - heading_us) as f32 * 1e-6;
    assert!(
        (silent_turn - gyro_turn).abs() < 5e-4,
        "turned {silent_turn} rad during the silence, the gyro {gyro_turn}"
    );

    // Back: a fresh frame (a restarted node counts from anywhere) makes the gyro the source
    // at the next step.
    seq = 0;
    rig.gyro(0.3, seq);
    seq += 1;
    rig.tick();
    assert_eq!(rig.ctl.heading_source(), HeadingSource::Gyro);
    let h = rig.ctl.pose().heading;
    rig.twist(0.2, 0.0, 0.0);
    rig.run_with_gyro(99, 0.3, &mut seq);
    let back = rig.ctl.pose().heading - h;
    assert!((back - 0.3 * 0.099).abs() < 1e-4, "{back}");
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn malformed_and_repeated_imu_frames_are_counted_and_not_used() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    rig.run_with_gyro(100, 0.0, &mut seq);
    let imu = |data: &[u8]| {
        CanFrame::standard(embedded_can::StandardId::new(0x304).unwrap(), data).unwrap()
    };
    let with = |rate: f32| {
        let mut d = [0u8; 8];
        d[..4].copy_from_slice(&rate.to_le_bytes());
        d[4] = 200;
        d
    };
    // For 200 ms only malformed frames, every 5 ms: wrong DLC, NaN, -inf, 36 rad/s.
    let bad: [&[u8]; 4] = [
        &[0; 7],
        &with(f32::NAN),
        &with(f32::NEG_INFINITY),
        &with(36.0),
    ];
    for i in 0..40 {
        rig.raw(imu(bad[i % 4]));
        rig.run_ms(5);
    }
    let s = rig.ctl.snapshot();
    assert_eq!(s.heading_source, HeadingSource::WheelsGyroSilent);
    let e = s.rx_errors;
    assert_eq!((e.wrong_dlc, e.non_finite, e.out_of_range), (10, 20, 10));
    assert_eq!(e.unknown_id, 0);
    rig.run_ms(100);
    let (_, c) = rig.counters();
    assert_eq!((c.wrong_dlc, c.non_finite, c.out_of_range), (10, 20, 10));
    assert_eq!(rig.status().rx_errors, 40);
    assert_eq!(rig.status().heading_source, HeadingSource::WheelsGyroSilent);

    // A node stuck on one frame: the first is taken, its repeats are counted and do not
    // keep the gyro alive (not even after the silence they cause).
    let repeats_before = rig.ctl.snapshot().repeated_seq;
    for _ in 0..40 {
        rig.gyro(0.7, 9);
        rig.run_ms(5);
    }
    let s = rig.ctl.snapshot();
    assert_eq!(s.repeated_seq - repeats_before, 39);
    assert_eq!(s.heading_source, HeadingSource::WheelsGyroSilent);
    // It turned the heading only while its one frame was fresh: 0.7 rad/s for 50 ms.
    assert_eq!(s.state, RobotState::Disabled);
    rig.run_ms(100);
    assert_eq!(rig.counters().1.repeated_seq, 39);
}

#[test]
fn without_a_gyro_configured_imu_frames_change_nothing() {
    use firmware::control::HeadingSource;
    // The same drive, one rig hearing an IMU that reads 0.5 rad/s, one hearing none: every
    // frame the core sends is the same (STATUS.heading_source stays WHEELS).
    let drive = |imu: bool| {
        let mut rig = Rig::dji();
        let mut seq = 0;
        rig.run_ms(50);
        rig.enable();
        let wheel = 0.2 / 0.076;
        rig.speed = [wheel, -wheel, wheel, -wheel];
        for _ in 0..50 {
            rig.twist(0.2, 0.0, 0.0);
            if imu {
                rig.run_with_gyro(10, 0.5, &mut seq);
            } else {
                rig.run_ms(10);
            }
        }
        rig
    };
    let (with, without) = (drive(true), drive(false));
    assert_eq!(with.log, without.log);
    assert_eq!(with.ctl.heading_source(), HeadingSource::Wheels);
    assert_eq!(with.status().heading_source, HeadingSource::Wheels);
    assert_eq!(with.ctl.pose(), without.ctl.pose());
}

// ------------------------------------------------------------------------------------------
// Wheel test (bring-up check) and wheel runaway

fn wheel_test(wheel: u8, speed: f32, duration_ms: u16) -> Command {
    Command::WheelTest(robot::WheelTest {
        wheel,
        speed,
        duration_ms,
    })
}

/// The `WHEEL_TEST_RESULT`s in the rig's log, with their times.
fn test_results(rig: &Rig) -> Vec<(u64, robot::WheelTestResult)> {
    rig.log
        .iter()
        .filter_map(|(t, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::WheelTestResult(r)) => Some((*t, r)),
            _ => None,
        })
        .collect()
}

#[test]
fn a_wheel_test_drives_that_wheel_alone_gently_and_reports_how_far_it_turned() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    // FR (wheel 1, mounted mirrored) at 3 rad/s for 500 ms.
    rig.send(wheel_test(1, 3.0, 500));
    let limit = firmware::control::WHEEL_TEST_CURRENT_FRACTION * rig.config.limits.max_current;
    let start = rig.now_us;
    let mut peak = 0.0f32;
    for _ in 0..500 {
        let out = rig.tick();
        assert_eq!(rig.ctl.state(), RobotState::WheelTest);
        let amps = dji_currents(&out).expect("current frames in the test");
        // Only ESC 2 (FR) gets current, within a quarter of max_current, pushing forward
        // (negative on the mirrored motor).
        assert_eq!((amps[0], amps[2], amps[3]), (0.0, 0.0, 0.0), "{amps:?}");
        assert!(
            amps[1] <= 0.0 && amps[1] >= -limit - 20.0 / 16384.0,
            "{amps:?}"
        );
        peak = peak.min(amps[1]);
        // The wheel follows: its motor turns backwards (mirrored) at 3 rad/s.
        rig.speed[1] = -3.0;
    }
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let results = test_results(&rig);
    assert_eq!(results.len(), 1, "{results:?}");
    let (t, r) = results[0];
    assert_eq!(
        t - start,
        500_000,
        "the result goes out at the step the test ends"
    );
    assert_eq!((r.wheel, r.outcome), (1, robot::TestOutcome::Done));
    // 499 ms at 3 rad/s (the first step's feedback still reported 0).
    assert!((r.angle - 1.497).abs() < 0.01, "angle {}", r.angle);
    // The first step's, kp · 3 rad/s + ki · 3 rad/s · 1 ms, in the wheel's sense.
    let g = rig.config.gains;
    let first = g.kp * 3.0 + g.ki * 3.0 * 1e-3;
    assert!(
        (r.peak_current - first).abs() < 0.01 && (peak + first).abs() < 0.01,
        "{r:?}"
    );
    // The robot stays disabled and can be enabled as usual.
    rig.speed[1] = 0.0;
    rig.run_ms(50);
    rig.enable();
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn a_wheel_test_is_refused_unless_disabled_and_ends_on_disable_or_estop() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.send(wheel_test(0, 2.0, 1000));
    rig.run_ms(2);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    let r = test_results(&rig);
    assert_eq!(r.len(), 1);
    assert_eq!(
        (r[0].1.wheel, r[0].1.outcome),
        (0, robot::TestOutcome::Refused)
    );

    rig.send(Command::Mode(ModeRequest::Disable));
    rig.send(wheel_test(2, -2.0, 1000));
    rig.run_ms(100);
    assert_eq!(rig.ctl.state(), RobotState::WheelTest);
    rig.enable();
    rig.tick();
    assert_eq!(
        rig.ctl.state(),
        RobotState::WheelTest,
        "enable is ignored meanwhile"
    );
    rig.send(Command::Mode(ModeRequest::Disable));
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let r = test_results(&rig);
    assert_eq!(
        (r[1].1.wheel, r[1].1.outcome),
        (2, robot::TestOutcome::Stopped)
    );

    rig.send(wheel_test(3, 2.0, 1000));
    rig.run_ms(10);
    rig.send(Command::Estop);
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let r = test_results(&rig);
    assert_eq!(
        (r[2].1.wheel, r[2].1.outcome),
        (3, robot::TestOutcome::Stopped)
    );
    rig.send(wheel_test(3, 2.0, 1000));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    assert_eq!(test_results(&rig)[3].1.outcome, robot::TestOutcome::Refused);
}

#[test]
fn an_odrive_wheel_test_puts_only_that_axis_in_closed_loop() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.send(wheel_test(2, 4.0, 200));
    let out = rig.tick();
    let Drive::Odrive {
        node_ids,
        gear_ratio,
        ..
    } = rig.config.drive
    else {
        unreachable!()
    };
    let closed: Vec<u8> = out
        .iter()
        .filter_map(|f| odrive::Command::decode(f).ok())
        .filter(|a| a.msg == odrive::Command::SetAxisState(AxisState::ClosedLoopControl))
        .map(|a| a.node.get())
        .collect();
    assert_eq!(closed, vec![node_ids[2]]);
    let vels = rig
        .run_ms(20)
        .iter()
        .find_map(|o| odrive_vels(&rig.config, o))
        .expect("velocity setpoints in the test");
    let want = 4.0 * gear_ratio / core::f32::consts::TAU; // RL: not mirrored
    assert_eq!(vels[..2], [0.0, 0.0]);
    assert!((vels[2] - want).abs() < 1e-3 && vels[3] == 0.0, "{vels:?}");
    rig.run_ms(200);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert_eq!(test_results(&rig)[0].1.outcome, robot::TestOutcome::Done);
}

/// Enables, drives forward at `vx`, and from `from_ms` on makes wheel `wheel`'s motor report
/// `motor_speed` (its own sign) while the others follow their setpoints exactly. Returns the
/// rig and, if it faulted, the time of the faulting step µs after the onset of the fight:
/// the first step of the interval running at the fault in which the residual of the
/// currents the motors acted on (the oracle: the rig's current frames, in the wheels' sense,
/// through the configuration's kinematics) was at or above the fight threshold.
fn fight_run(wheel: usize, motor_speed: f32, vx: f32, from_ms: u64) -> (Rig, Option<u64>) {
    fight_run_stalling(wheel, motor_speed, vx, from_ms, None)
}

/// [`fight_run`], with the loop stalled once, if `stall` says so: before step `k` the clock
/// jumps `us` (a late runner), so that step is the only one the core sees of that time.
fn fight_run_stalling(
    wheel: usize,
    motor_speed: f32,
    vx: f32,
    from_ms: u64,
    stall: Option<(u64, u64)>,
) -> (Rig, Option<u64>) {
    use firmware::control::FIGHT_CURRENT_FRACTION;
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    let kin = rig.config.kinematics().unwrap();
    let threshold = FIGHT_CURRENT_FRACTION * rig.config.limits.max_current;
    let mirrored = |i: usize| if i % 2 == 1 { -1.0 } else { 1.0 };
    let mut onset = None;
    for k in 0..1000u64 {
        if k % 10 == 0 {
            rig.twist(vx, 0.0, 0.0);
        }
        let snap = rig.ctl.snapshot();
        for i in 0..4 {
            rig.speed[i] = mirrored(i) * snap.wheel_setpoints.0[i];
        }
        if k >= from_ms {
            rig.speed[wheel] = motor_speed;
        }
        // The currents the motors act on at this step: the last step's, wheel sense.
        let acting = kinematics::WheelSpeeds(snap.currents);
        let (_, residual) = kin.forward_with_residual(&acting);
        if residual.rms() >= threshold {
            onset.get_or_insert(rig.now_us);
        } else {
            onset = None;
        }
        if let Some((at_k, us)) = stall
            && at_k == k
        {
            rig.now_us += us;
        }
        let out = rig.tick();
        let amps = dji_currents(&out).unwrap();
        if rig.ctl.state() == RobotState::Fault {
            assert!(all_zero(amps), "zero torque at once: {amps:?}");
            let at = rig.now_us - TICK_US;
            return (rig, onset.map(|s| at - s));
        }
    }
    (rig, None)
}

#[test]
fn a_wheel_that_does_not_follow_while_the_others_do_is_a_fight_within_the_window() {
    use firmware::control::FIGHT_WINDOW_US;
    // FL commanded forward at 0.5 m/s, its motor turning backwards at 5 rad/s; then RR
    // (mirrored) at 1 m/s = 13.2 rad/s but held at 2 rad/s (blocked); then RR turning
    // backwards. Each time the three others follow: the currents fight.
    for (wheel, motor_speed, vx, from_ms) in
        [(0, -5.0, 0.5, 100), (3, -2.0, 1.0, 0), (3, 1.5, 1.0, 0)]
    {
        let (rig, latency) = fight_run(wheel, motor_speed, vx, from_ms);
        assert_eq!(
            (rig.ctl.state(), rig.ctl.fault()),
            (RobotState::Fault, Fault::WheelFight),
            "wheel {wheel} at {motor_speed}"
        );
        let latency = latency.expect("a fight before the fault");
        assert!(
            (FIGHT_WINDOW_US..=FIGHT_WINDOW_US + 2_000).contains(&latency),
            "wheel {wheel}: {latency} µs after the onset"
        );
    }
    let (mut rig, _) = fight_run(0, -5.0, 0.5, 100);
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().fault, Fault::WheelFight);
    // Latched: a twist does not move it, a reset clears it.
    rig.speed = [0.0; 4];
    rig.twist(0.5, 0.0, 0.0);
    rig.run_ms(5);
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
}

#[test]
fn a_stalled_loop_does_not_judge_a_fight_on_one_late_look() {
    use firmware::control::FIGHT_WINDOW_US;
    // FL lags from 100 ms on; 20 ms later the loop stalls for 100 ms (a late runner): the
    // window has passed in time but the core saw one step of it. It faults only once it has
    // seen the window's 60 steps: the window and the stall after the onset.
    let stall_us = FIGHT_WINDOW_US + 40_000;
    let (rig, latency) = fight_run_stalling(0, -5.0, 0.5, 100, Some((120, stall_us)));
    assert_eq!(rig.ctl.fault(), Fault::WheelFight);
    let latency = latency.expect("a fight before the fault");
    assert!(
        (FIGHT_WINDOW_US + stall_us..=FIGHT_WINDOW_US + stall_us + 2_000).contains(&latency),
        "{latency} µs after the onset"
    );
}

#[test]
fn wheels_that_follow_do_not_fight_however_hard_they_accelerate() {
    // Full speed forward from rest and back, every wheel following its setpoint: large
    // currents, no residual.
    let (rig, latency) = fight_run(0, 0.0, 2.5, u64::MAX);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault(), latency),
        (RobotState::Enabled, Fault::None, None)
    );
}

#[test]
fn a_wheel_test_whose_wheel_runs_the_other_way_faults() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.send(wheel_test(0, 3.0, 2000));
    // The motor's current and its encoder disagree: positive feedback. (One wheel driven:
    // no fight to see, the runaway watch is what catches it.)
    use firmware::control::{RUNAWAY_SATURATION, RUNAWAY_WINDOW_US, WHEEL_TEST_CURRENT_FRACTION};
    let limit = WHEEL_TEST_CURRENT_FRACTION * rig.config.limits.max_current;
    let (mut saturated, mut faulted) = (None, None);
    let t0 = rig.now_us;
    for k in 0..2000u64 {
        rig.speed[0] = -0.01 * k as f32;
        let amps = dji_currents(&rig.tick()).unwrap();
        if rig.ctl.state() == RobotState::Fault {
            faulted = Some(rig.now_us - TICK_US);
            break;
        }
        if saturated.is_none() && amps[0].abs() >= RUNAWAY_SATURATION * limit {
            saturated = Some(rig.now_us - TICK_US);
        }
    }
    // Saturated within a few ms; the window over, the fault comes at the first step whose
    // feedback turns at least RUNAWAY_MIN_SPEED (1 rad/s) the other way: 100 ms in.
    let (saturated, faulted) = (saturated.expect("saturated"), faulted.expect("a runaway"));
    assert!(
        faulted - saturated >= RUNAWAY_WINDOW_US,
        "{} µs after saturation",
        faulted - saturated
    );
    assert!(
        saturated - t0 < 10_000,
        "saturated {} µs in",
        saturated - t0
    );
    assert!(
        (99_000..=102_000).contains(&(faulted - t0)),
        "faulted {} µs in",
        faulted - t0
    );
    assert_eq!(rig.ctl.fault(), Fault::WheelRunaway);
    rig.tick();
    let r = test_results(&rig);
    assert_eq!(
        (r[0].1.wheel, r[0].1.outcome),
        (0, robot::TestOutcome::Fault)
    );
    assert!(r[0].1.angle < 0.0, "{:?}", r[0]);
}
