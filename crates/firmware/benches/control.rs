//! One control period of the core on the host: four DJI feedback frames decoded and
//! integrated, watchdog and limits, inverse kinematics, desaturation, four PI loops, the
//! current frame encoded, odometry (and, every 10th / 100th step, the telemetry frames).

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};
use firmware::protocol::dji::{EscId, EscModel, Feedback};
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};

fn feedback(esc: u8, angle: u16, rpm: i16) -> CanFrame {
    Feedback {
        model: EscModel::C620,
        esc: EscId::new(esc).unwrap(),
        rotor_angle: angle,
        rotor_speed_rpm: rpm,
        torque_current: 1200,
        temperature_c: 35,
    }
    .to_can_frame()
}

fn bench(c: &mut Criterion) {
    let config = Config::dji_m3508_example();
    let mut ctl = Controller::new(&config).unwrap();
    let mut t = 0u64;
    let twist = Command::Twist(TwistCmd {
        vx: 0.8,
        vy: -0.3,
        wz: 0.5,
        seq: 0,
    })
    .to_can_frame();
    for esc in 1..=4 {
        ctl.on_frame(Instant::from_micros(t), &feedback(esc, 0, 0));
    }
    ctl.step(Instant::from_micros(t));
    ctl.on_frame(
        Instant::from_micros(t),
        &Command::Mode(ModeRequest::Enable).to_can_frame(),
    );
    let mut angle = [0u16; 4];
    let rpm = [2400i16, -2600, 2100, -2300];
    c.bench_function("control_step_4_wheels_dji", |b| {
        b.iter(|| {
            t += 1000;
            let now = Instant::from_micros(t);
            // Keep the watchdog fed without a per-iteration branch cost worth measuring.
            ctl.on_frame(now, &twist);
            for w in 0..4 {
                angle[w] = (angle[w] + (rpm[w].unsigned_abs() / 8)) % 8192;
                ctl.on_frame(now, &feedback(w as u8 + 1, angle[w], rpm[w]));
            }
            black_box(ctl.step(now))
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
