//! The command watchdog and the twist alive counter (`docs/control.md`, "Command watchdog").

use crate::rig::*;

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
    let t_last = rig.drive_then_fall_silent([0.5, 0.0, 0.0]);
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
