//! The DJI M3508 with its C620: the current's lag and limits, the 13-bit rotor angle, and
//! the feedback faults (a stuck encoder, a motor offline).

use core::f64::consts::TAU;

use hostsim::nodes::plant::{DjiDrive, Drive, Plant, Shaft, WHEELS, Wheel};
use kinematics::ChassisVelocity;

use super::{WheelPi, kin};

#[test]
fn m3508_current_lag_and_limits() {
    let mut drive = DjiDrive::default();
    let at_rest = Shaft::default();
    // Raw scale: 8192 ↔ 10 A; first-order lag with τ = 1 ms.
    drive.set_current_raw(8192);
    for _ in 0..10 {
        drive.advance(1e-4, at_rest);
    }
    let expected = 10.0 * (1.0 - (-1.0_f64).exp());
    assert!(
        (drive.current() - expected).abs() < 1e-9,
        "{}",
        drive.current()
    );
    // The ESC clamps to 20 A; the stall torque is Kt · 20 A = 6 N·m at the output.
    drive.set_current_raw(i16::MAX);
    let mut torque = 0.0;
    for _ in 0..200 {
        torque = drive.advance(1e-4, at_rest);
    }
    assert!((drive.current() - 20.0).abs() < 1e-6);
    assert!((torque - 6.0).abs() < 1e-6, "stall torque {torque}");
    assert_eq!(drive.feedback_for(at_rest).torque_current, 16384);
    drive.set_current_raw(i16::MIN);
    for _ in 0..200 {
        drive.advance(1e-4, at_rest);
    }
    assert!((drive.current() + 20.0).abs() < 1e-6);

    // Speed limit: full current on a free wheel never exceeds the no-load speed.
    let gear = drive.gear_ratio();
    let inertia = drive.reflected_inertia() + 2.0e-3;
    let no_load = 482.0 * TAU / 60.0;
    drive.set_current_raw(16384);
    let mut omega = 0.0;
    let mut peak = 0.0_f64;
    for _ in 0..30_000 {
        let rotor = Shaft {
            angle: 0.0,
            speed: omega * gear,
        };
        let tau = drive.advance(1e-4, rotor);
        omega += 1e-4 * tau / inertia;
        peak = peak.max(omega);
    }
    let fb = drive.feedback_for(Shaft {
        angle: 0.0,
        speed: omega * gear,
    });
    println!(
        "free spin: {:.2} rad/s at the output ({:.1} rpm), no-load {no_load:.2}; rotor \
         {} rpm, current {:.2} A",
        omega,
        omega * 60.0 / TAU,
        fb.rotor_speed_rpm,
        drive.current()
    );
    assert!(peak <= no_load, "peak {peak} above no-load {no_load}");
    assert!(omega > 0.98 * no_load, "{omega}");
    // Near the no-load speed the voltage limit takes the current away.
    assert!(drive.current() < 2.0);
    assert!((f64::from(fb.rotor_speed_rpm) - omega * gear * 60.0 / TAU).abs() <= 0.5);
}

/// Unwraps a 13-bit counter sequence into a total count.
fn unwrap_counts(samples: &[u16]) -> i64 {
    let mut total = 0_i64;
    for pair in samples.windows(2) {
        let d = (i64::from(pair[1]) - i64::from(pair[0])).rem_euclid(8192);
        total += if d >= 4096 { d - 8192 } else { d };
    }
    total
}

#[test]
fn rotor_angle_wraps_and_tracks_the_wheel() {
    let setpoints = kin().inverse(ChassisVelocity::new(1.0, 0.0, 0.0)).0;
    let mut plant = Plant::dji_m3508_example().expect("valid");
    let mut pi = WheelPi::new();
    let mut angles: [Vec<u16>; WHEELS] = Default::default();
    let first = Wheel::ALL.map(|w| plant.state().wheel_angle[w.index()]);
    for _ in 0..500 {
        pi.control(&mut plant, &setpoints, 1e-3);
        plant.step(1e-3).expect("valid");
        for fb in plant.take_feedback() {
            angles[fb.wheel.index()].push(fb.feedback.rotor_angle);
        }
    }
    let gear = 3591.0 / 187.0;
    for w in Wheel::ALL {
        let i = w.index();
        // One frame per millisecond.
        assert_eq!(angles[i].len(), 500, "{w:?}");
        let sign = if plant.inverted()[i] { -1.0 } else { 1.0 };
        let wheel_turned = plant.state().wheel_angle[i] - first[i];
        let counts = unwrap_counts(&angles[i]) as f64;
        // The first sample is taken 1 ms in; the motion before it is a fraction of a count.
        let expected_from_first = sign * gear * wheel_turned * 8192.0 / TAU;
        let wraps = angles[i]
            .windows(2)
            .filter(|p| p[0].abs_diff(p[1]) > 4096)
            .count();
        println!(
            "{w:?}: {counts} counts, {wraps} wraps, rotor/wheel = {:.4}",
            counts / (wheel_turned * 8192.0 / TAU)
        );
        assert!(wraps >= 15, "{w:?}: the counter must wrap");
        // Robot drives forward: a mirrored motor counts down.
        assert_eq!(counts > 0.0, sign > 0.0, "{w:?}");
        // The last frame is the rotor angle at that instant, floored to a count.
        let last = f64::from(*angles[i].last().expect("samples"));
        let truth = (sign * gear * plant.state().wheel_angle[i]).rem_euclid(TAU) * 8192.0 / TAU;
        assert!(
            (last - truth.floor()).abs() < 0.5,
            "{w:?}: {last} vs {truth}"
        );
        assert!(
            (counts - expected_from_first).abs() < 0.02 * expected_from_first.abs(),
            "{w:?}: {counts} vs {expected_from_first}"
        );
    }
}

/// The example DJI plant after 200 ms of driving forward at 0.5 m/s under the wheel PI, its
/// feedback so far taken: the PI and the wheel setpoints to go on with.
fn cruising() -> (Plant<DjiDrive>, WheelPi, [f64; 4]) {
    let setpoints = kin().inverse(ChassisVelocity::new(0.5, 0.0, 0.0)).0;
    let mut plant = Plant::dji_m3508_example().expect("valid");
    let mut pi = WheelPi::new();
    for _ in 0..200 {
        pi.control(&mut plant, &setpoints, 1e-3);
        plant.step(1e-3).expect("valid");
    }
    plant.take_feedback();
    (plant, pi, setpoints)
}

#[test]
fn faults_freeze_or_silence_the_feedback() {
    let (mut plant, mut pi, setpoints) = cruising();
    plant.set_stuck_encoder(Wheel::FrontLeft, true);
    plant.set_offline(Wheel::RearRight, true);
    let angle_before = plant.state().wheel_angle[0];
    let mut fl = Vec::new();
    for _ in 0..100 {
        pi.control(&mut plant, &setpoints, 1e-3);
        plant.step(1e-3).expect("valid");
        for t in plant.take_feedback() {
            assert_ne!(t.wheel, Wheel::RearRight, "offline wheel sent feedback");
            if t.wheel == Wheel::FrontLeft {
                fl.push(t.feedback);
            }
        }
    }
    assert_eq!(fl.len(), 100);
    assert!(
        fl.windows(2)
            .all(|p| (p[0].rotor_angle, p[0].rotor_speed_rpm)
                == (p[1].rotor_angle, p[1].rotor_speed_rpm)),
        "stuck angle or speed changed"
    );
    assert!(fl[0].rotor_speed_rpm > 1000);
    assert!(
        plant.state().wheel_angle[0] - angle_before > 0.5,
        "the wheel keeps turning"
    );
    plant.set_stuck_encoder(Wheel::FrontLeft, false);
    plant.set_offline(Wheel::RearRight, false);
    plant.step(1e-3).expect("valid");
    let fb = plant.take_feedback();
    assert_eq!(fb.len(), 4);
    assert_ne!(fb[0].feedback.rotor_angle, fl[0].rotor_angle);
}

#[test]
fn faults_set_for_an_instant_take_effect_exactly_then() {
    let (mut plant, ..) = cruising();
    // RR offline from 205.5 ms, in the middle of the next 10 ms: its frames of 201..=205 ms
    // go out, those of 206..=210 ms do not; the others send all ten.
    plant.set_faults_at(205_500_000, [false; 4], [false, false, false, true]);
    assert!(!plant.is_offline(Wheel::RearRight), "not before its time");
    plant.step(10e-3).expect("valid");
    assert!(plant.is_offline(Wheel::RearRight));
    let fb = plant.take_feedback();
    let times = |wheel| -> Vec<u64> {
        fb.iter()
            .filter(|t| t.wheel == wheel)
            .map(|t| t.time_ns / 1_000_000)
            .collect()
    };
    assert_eq!(times(Wheel::RearRight), [201, 202, 203, 204, 205]);
    assert_eq!(times(Wheel::FrontLeft), (201..=210).collect::<Vec<_>>());
    // Back online at an instant already reached: at once.
    plant.set_faults_at(0, [false; 4], [false; 4]);
    assert!(!plant.is_offline(Wheel::RearRight));
}
