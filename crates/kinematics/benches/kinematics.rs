//! Per-call cost of the kinematics primitives on the host, in `f32` and `f64`.
//!
//! `full_step` is what a control period does with them: inverse kinematics of the command,
//! forward kinematics of the measured increments, one odometry step. Figures go to
//! `docs/benchmarks.md`.

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use kinematics::{ChassisVelocity, MecanumKinematics, Odometry, Pose2, Real, WheelSpeeds};

fn bench_type<T: Real>(c: &mut Criterion, name: &str) {
    let kin = MecanumKinematics::<T, 4>::standard(T::lit(0.2), T::lit(0.15), T::lit(0.076))
        .expect("valid layout");
    let v = ChassisVelocity::new(T::lit(0.8), T::lit(-0.3), T::lit(0.5));
    let w = WheelSpeeds::new(T::lit(9.0), T::lit(14.0), T::lit(7.5), T::lit(12.0));
    let dt = T::lit(1e-3);
    let mut group = c.benchmark_group(name);
    group.bench_function("inverse", |b| b.iter(|| kin.inverse(black_box(v))));
    group.bench_function("forward", |b| b.iter(|| kin.forward(black_box(&w))));
    group.bench_function("forward_with_residual", |b| {
        b.iter(|| kin.forward_with_residual(black_box(&w)))
    });
    group.bench_function("desaturate", |b| {
        b.iter(|| black_box(w).desaturate(black_box(T::lit(10.0))))
    });
    let deltas = w.times(dt);
    let mut odo = Odometry::new(Pose2::default());
    group.bench_function("odometry_step", |b| {
        b.iter(|| odo.update(&kin, black_box(&deltas)))
    });
    let mut odo = Odometry::new(Pose2::default());
    group.bench_function("full_step", |b| {
        b.iter(|| {
            let cmd = kin.inverse(black_box(v)).desaturate(T::lit(50.0));
            let pose = odo.update(&kin, black_box(&deltas));
            (cmd, pose)
        })
    });
    group.finish();
}

fn benches(c: &mut Criterion) {
    bench_type::<f32>(c, "f32");
    bench_type::<f64>(c, "f64");
}

criterion_group!(kinematics_benches, benches);
criterion_main!(kinematics_benches);
