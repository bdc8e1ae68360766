//! Drives a 1 m square through the whole kinematics chain, with no plant: commanded twist ->
//! inverse kinematics -> desaturation -> ideal wheels -> 13-bit DJI rotor counters (wrapping)
//! -> encoder integration -> forward kinematics -> SE(2) odometry, at 1 kHz in f32 as on the
//! MCU. Prints the pose at each corner and the closing error, which with ideal wheels is
//! only rounding.
//!
//! `cargo run --release -p kinematics --example drive`

use kinematics::{
    ChassisVelocity, Encoder, EncoderConfig, MecanumKinematics, Odometry, Pose2, WheelDeltas,
    WheelSpeeds,
};

/// A DJI M3508 wheel as the firmware sees it: a 13-bit rotor angle that wraps.
struct RotorCounter {
    /// Rotor angle in counts, unwrapped, as an f64 "true" value.
    counts: f64,
}

impl RotorCounter {
    fn raw(&self) -> u32 {
        (self.counts.rem_euclid(8192.0)) as u32
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    const DT: f32 = 1e-3;
    const MAX_WHEEL: f32 = 40.0; // rad/s at the wheel, a little under the M3508's 482 rpm
    let kin = MecanumKinematics::<f32, 4>::standard(0.20, 0.18, 0.076)?;
    let gear = 3591.0_f64 / 187.0;
    let mut counters: Vec<RotorCounter> = (0..4).map(|_| RotorCounter { counts: 100.0 }).collect();
    let mut encoders = [Encoder::new(&EncoderConfig::<f32>::dji_m3508(false))?; 4];
    for (e, c) in encoders.iter_mut().zip(&counters) {
        e.update(c.raw())?;
    }
    let mut odo = Odometry::new(Pose2::default());
    let mut residual_peak = 0.0f32;

    // A square: forward, strafe left, backward, strafe right, 2 s each at 0.5 m/s.
    let legs = [
        ("forward", ChassisVelocity::new(0.5, 0.0, 0.0)),
        ("strafe left", ChassisVelocity::new(0.0, 0.5, 0.0)),
        ("backward", ChassisVelocity::new(-0.5, 0.0, 0.0)),
        ("strafe right", ChassisVelocity::new(0.0, -0.5, 0.0)),
    ];
    println!(
        "{:<14} {:>9} {:>9} {:>10}",
        "leg", "x [m]", "y [m]", "heading"
    );
    for (name, twist) in legs {
        let wheels = kin.inverse(twist).desaturate(MAX_WHEEL);
        for _ in 0..2000 {
            // The ideal plant turns each rotor by wheel angle x gear ratio.
            let mut deltas = [0.0f32; 4];
            for (i, (c, e)) in counters.iter_mut().zip(encoders.iter_mut()).enumerate() {
                c.counts +=
                    f64::from(wheels.0[i]) * f64::from(DT) * gear * 8192.0 / std::f64::consts::TAU;
                let counts = e.update(c.raw())?;
                deltas[i] = e.counts_to_radians(counts);
            }
            let speeds = WheelSpeeds(deltas.map(|x| x / DT));
            let (_, residual) = kin.forward_with_residual(&speeds);
            residual_peak = residual_peak.max(residual.max_abs());
            odo.update(&kin, &WheelDeltas(deltas));
        }
        let p = odo.pose();
        println!(
            "{name:<14} {:>9.4} {:>9.4} {:>9.4}°",
            p.x,
            p.y,
            p.heading.to_degrees()
        );
    }
    let p = odo.pose();
    println!(
        "closing error {:.2} mm, peak wheel residual {:.3} rad/s (wheel disagreement)",
        1000.0 * p.x.hypot(p.y),
        residual_peak
    );
    Ok(())
}
