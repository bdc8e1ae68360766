//! The parts of one lockstep period (1 ms of simulated time), for the floor of a run's speed
//! (docs/benchmarks.md, "One run's floor"):
//!
//! - `frame_bits`: one frame's exact length on the wire (CRC-15 and stuff bits), over a mix
//!   of the frames a DJI run puts on the bus; a period has about 5.3 of them.
//! - `chassis_step`: one implicit step of the chassis on its rollers (the 7 × 7 arrowhead
//!   solve with frozen friction coefficients); a period has at least two, split at the
//!   delivery of the firmware's current command, and one more at each other delivery.
//! - `dji_plant_period`: one period of the DJI plant as the loop drives it: to the command's
//!   delivery 130 µs in, the four new currents, to the period's end (two chassis steps,
//!   eight drive steps), the four feedback frames encoded.
//! - `run/square`: the built-in `square` scenario end to end without a log (9.1 s, 9,101
//!   periods, firmware included).

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::CanFrame;
use firmware::protocol::dji::{CurrentCommand, EscGroup, EscId, EscModel, Feedback};
use firmware::protocol::robot::{Command, OdomVelocity, Telemetry, TwistCmd};
use hostsim::nodes::plant::{Chassis, ChassisParams, Plant, Wheel, WheelInput};

/// A deterministic mix of DJI feedback, current commands and robot-protocol frames.
fn frames() -> Vec<CanFrame> {
    let mut out = Vec::new();
    let mut x = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    for i in 0..64u16 {
        let r = next();
        let frame = match i % 8 {
            0..=3 => Feedback {
                model: EscModel::C620,
                esc: EscId::new(i as u8 % 4 + 1).unwrap(),
                rotor_angle: (r % 8192) as u16,
                rotor_speed_rpm: (r >> 16) as i16 / 8,
                torque_current: (r >> 32) as i16 / 4,
                temperature_c: 35,
            }
            .to_can_frame(),
            4 | 5 => CurrentCommand {
                model: EscModel::C620,
                group: EscGroup::Esc1To4,
                raw: core::array::from_fn(|k| (r >> (16 * k)) as i16 / 4),
            }
            .to_can_frame(),
            6 => Command::Twist(TwistCmd {
                vx: 0.5,
                vy: -0.2,
                wz: 0.1,
                seq: i as u8,
            })
            .to_can_frame(),
            _ => Telemetry::OdomVelocity(OdomVelocity {
                heading: 0.3,
                vx: 0.49,
                vy: -0.21,
                wz: 0.1,
            })
            .to_can_frame(),
        };
        out.push(frame);
    }
    out
}

fn bench(c: &mut Criterion) {
    let frames = frames();
    let mut i = 0;
    c.bench_function("frame_bits", |b| {
        b.iter(|| {
            i = (i + 1) % frames.len();
            black_box(hostsim::bus::frame_bits(black_box(&frames[i])))
        })
    });

    let mut chassis = Chassis::new(ChassisParams::default()).unwrap();
    let torques = [1.5, 1.4, 1.6, 1.45].map(WheelInput::Torque);
    c.bench_function("chassis_step", |b| {
        b.iter(|| {
            chassis.step(black_box(0.000_5), &torques).unwrap();
            black_box(chassis.state().pose)
        })
    });

    let mut plant = Plant::dji_m3508_example().unwrap();
    let mut k = 0i16;
    c.bench_function("dji_plant_period", |b| {
        b.iter(|| {
            plant.advance_ns(130_000);
            k = (k + 37) % 4000;
            for w in Wheel::ALL {
                plant.drive_mut(w).set_current_raw(2000 + k);
            }
            plant.advance_ns(870_000);
            for f in plant.drain_feedback() {
                black_box(
                    f.feedback
                        .to_firmware(EscId::new(1).unwrap())
                        .to_can_frame(),
                );
            }
        })
    });

    let square = hostsim::scenario::Scenario::builtin("square").unwrap();
    let mut group = c.benchmark_group("run");
    group.sample_size(10);
    group.bench_function("square", |b| {
        b.iter(|| {
            let mut plant = hostsim::engine::plant_for(&square).unwrap();
            let options = hostsim::engine::LogOptions::default();
            black_box(hostsim::engine::run(&square, &mut plant, None, options, |_| {}).unwrap())
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
