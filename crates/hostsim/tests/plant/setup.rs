//! Plants as they are built and run: parameters refused with the field, plants from the
//! firmware's example configurations, two runs bit for bit the same, and the cost of a run.

use core::f64::consts::PI;

use firmware::protocol::odrive::{AxisState, Command};
use hostsim::nodes::plant::chassis::STANDARD_GRAVITY;
use hostsim::nodes::plant::{
    Chassis, ChassisParams, ChassisState, DjiDrive, DjiFeedback, Drive, OdriveAxis, OdriveParams,
    Plant, Ripple, Wheel, WheelInput,
};
use kinematics::ChassisVelocity;

use super::odrive::odrive_command;
use super::{WheelPi, kin};

fn deterministic_run() -> (ChassisState, Vec<DjiFeedback>) {
    let params = ChassisParams {
        ripple: Some(Ripple::new(9, 0.05)),
        ..ChassisParams::default()
    };
    let drives = core::array::from_fn(|_| DjiDrive::default());
    let mut plant = Plant::new(params, drives, [false, true, false, true]).expect("valid");
    let setpoints = kin().inverse(ChassisVelocity::new(0.8, -0.3, 0.7)).0;
    let mut pi = WheelPi::new();
    let mut feedback = Vec::new();
    for _ in 0..1000 {
        pi.control(&mut plant, &setpoints, 1e-3);
        plant.step(1e-3).expect("valid");
        feedback.extend(plant.take_feedback().into_iter().map(|t| t.feedback));
    }
    (*plant.state(), feedback)
}

#[test]
fn determinism_two_runs_are_bit_identical() {
    let (a, fa) = deterministic_run();
    let (b, fb) = deterministic_run();
    let bits = |s: &ChassisState| {
        let mut v = vec![
            s.pose.x,
            s.pose.y,
            s.pose.heading,
            s.yaw,
            s.velocity.vx,
            s.velocity.vy,
            s.velocity.wz,
        ];
        v.extend(s.wheel_speed);
        v.extend(s.wheel_angle);
        v.into_iter().map(f64::to_bits).collect::<Vec<_>>()
    };
    assert_eq!(bits(&a), bits(&b));
    assert_eq!(fa, fb);
    assert_eq!(fa.len(), 4000);
}

#[test]
fn bad_parameters_are_refused_with_the_field() {
    let bad_mass = ChassisParams {
        mass: -1.0,
        ..ChassisParams::default()
    };
    let err = Chassis::new(bad_mass).expect_err("negative mass");
    assert_eq!(err.field, "chassis.mass");
    println!("{err}");

    let mut params = ChassisParams::default();
    params.wheels[2].radius = f64::NAN;
    let err = Chassis::new(params).expect_err("NaN radius");
    assert_eq!((err.field, err.wheel), ("chassis.wheels", Some(2)));
    println!("{err}");

    // All rollers parallel: rank < 3.
    let mut params = ChassisParams::default();
    for w in &mut params.wheels {
        w.roller_angle = PI / 4.0;
    }
    let err = Chassis::new(params).expect_err("singular");
    assert_eq!(err.field, "chassis.wheels");
    println!("{err}");

    // A step longer than a day is refused (it used to spin on 1e300 s for ever).
    let mut chassis = Chassis::new(ChassisParams::default()).expect("valid");
    let zero = [WheelInput::Torque(0.0); 4];
    assert_eq!(chassis.step(1e300, &zero).expect_err("1e300 s").field, "dt");
    chassis.step(1e-3, &zero).expect("a millisecond");

    let ripple = ChassisParams {
        ripple: Some(Ripple::new(9, 0.2)),
        ..ChassisParams::default()
    };
    assert_eq!(
        Chassis::new(ripple).expect_err("d > r").field,
        "chassis.ripple.axis_offset"
    );

    let err = OdriveAxis::new(OdriveParams {
        watchdog_timeout: Some(0.0),
        ..OdriveParams::default()
    })
    .expect_err("zero timeout");
    assert_eq!(err.field, "odrive.watchdog_timeout");

    let mut plant = Plant::dji_m3508_example().expect("valid");
    assert_eq!(plant.step(f64::NAN).expect_err("NaN").field, "dt");
    assert_eq!(plant.step(-1.0).expect_err("negative").field, "dt");
    assert_eq!(
        plant.set_friction(0.0).expect_err("zero").field,
        "chassis.friction"
    );
    assert_eq!(plant.time_ns(), 0);
    // Default load is m g / 4.
    let loads = ChassisParams::default().normal_loads();
    assert!((loads[0] - 20.0 * STANDARD_GRAVITY / 4.0).abs() < 1e-12);
}

#[test]
fn plants_from_the_firmware_example_configs_match_the_examples() {
    let dji = Plant::dji_from_config(&firmware::Config::dji_m3508_example()).expect("valid");
    assert_eq!(dji.inverted(), [false, true, false, true]);
    let w = dji.chassis().params().wheels;
    assert!((w[1].y + 0.18).abs() < 1e-6 && (w[1].radius - 0.076).abs() < 1e-6);
    assert!((dji.drive(Wheel::FrontLeft).gear_ratio() - 3591.0 / 187.0).abs() < 1e-5);

    let od = Plant::odrive_from_config(&firmware::Config::odrive_example()).expect("valid");
    assert_eq!(od.inverted(), [false, true, false, true]);
    assert_eq!(od.drive(Wheel::RearRight).gear_ratio(), 5.0);
    assert_eq!(
        Plant::odrive_from_config(&firmware::Config::dji_m3508_example())
            .expect_err("not an ODrive config")
            .field,
        "drive"
    );
}

/// Cost of the plant: 60 s of the DJI example with the wheel loop at 1 kHz, and the same with
/// the ODrive example. Run with `cargo test --release -p hostsim --test plant -- --ignored
/// --nocapture`.
#[test]
#[ignore = "timing, run in release by hand"]
fn cost_of_a_60_s_run() {
    let setpoints = kin().inverse(ChassisVelocity::new(0.8, 0.3, 0.5)).0;
    let mut plant = Plant::dji_m3508_example().expect("valid");
    let mut pi = WheelPi::new();
    let start = std::time::Instant::now();
    let mut frames = 0;
    for _ in 0..60_000 {
        pi.control(&mut plant, &setpoints, 1e-3);
        plant.step(1e-3).expect("valid");
        frames += plant.take_feedback().len();
    }
    let dji = start.elapsed();

    let mut plant = Plant::odrive_example().expect("valid");
    for w in Wheel::ALL {
        plant
            .drive_mut(w)
            .apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    }
    let start = std::time::Instant::now();
    for _ in 0..12_000 {
        odrive_command(&mut plant, setpoints);
        plant.step(5e-3).expect("valid");
        frames += plant.take_feedback().len();
    }
    let odrive = start.elapsed();
    println!(
        "60 s simulated, substep {} ns: DJI {:?} ({:.2} µs per simulated ms), ODrive {:?} \
         ({:.2} µs per simulated ms); {frames} feedback messages",
        plant.substep_ns(),
        dji,
        dji.as_secs_f64() * 1e6 / 60_000.0,
        odrive,
        odrive.as_secs_f64() * 1e6 / 60_000.0
    );
}
