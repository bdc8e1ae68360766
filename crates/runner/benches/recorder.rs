//! What `--log` costs the runner's control loop, per step, and how fast the log grows.
//!
//! Not criterion: the log's writer thread must keep up as it does in a real run (a step per
//! millisecond), or the loop's pushes would be dropped (non-blocking mode) and look cheaper
//! than they are. So this harness runs the loop's work at a paced 1 kHz, in one process:
//! for each step, four DJI C620 feedback frames into the core (and a twist every 20th step,
//! a 50 Hz host), the step, its frames "sent"; once with no recorder (`()`), once with the
//! runner's [`McapRecorder`] writing a real file (every hook the loop calls, including the
//! hand-over at the end of the step). It times the loop thread's share of each step
//! (`Instant` around the step's work, not the sleep) and prints the percentiles of both, the
//! difference (the logging cost per step), the log's size per hour at 1 kHz and the messages
//! dropped.
//!
//! `cargo bench -p mecanum-runner --bench recorder` (10,000 steps each, 20 s in all;
//! `RECORDER_BENCH_STEPS=N` to change).

use std::hint::black_box;
use std::time::{Duration, Instant as WallInstant};

use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};
use firmware::protocol::dji::{EscId, EscModel, Feedback};
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};
use mecanum_linux::Recorder;
use mecanum_runner::McapRecorder;

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

/// Per-step loop-thread times, ns.
struct Times(Vec<u64>);

impl Times {
    fn quantile(&self, q: f64) -> f64 {
        let mut v = self.0.clone();
        v.sort_unstable();
        let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        v[i] as f64 / 1e3
    }
    fn mean(&self) -> f64 {
        self.0.iter().sum::<u64>() as f64 / self.0.len() as f64 / 1e3
    }
    fn line(&self) -> String {
        format!(
            "mean {:.2} µs, p50 {:.2} µs, p99 {:.2} µs, max {:.1} µs",
            self.mean(),
            self.quantile(0.5),
            self.quantile(0.99),
            self.quantile(1.0)
        )
    }
}

/// Runs `steps` paced steps of an enabled DJI core, telling `recorder`.
fn run<R: Recorder + ?Sized>(steps: u64, recorder: &mut R) -> Times {
    let config = Config::dji_m3508_example();
    let mut ctl = Controller::new(&config).unwrap();
    let rpm = [2400i16, -2600, 2100, -2300];
    let mut angle = [0u16; 4];
    let mut times = Vec::with_capacity(steps as usize);
    let start = WallInstant::now();
    for k in 0..steps {
        let deadline = start + Duration::from_micros(k * 1000);
        if let Some(wait) = deadline.checked_duration_since(WallInstant::now()) {
            std::thread::sleep(wait);
        }
        let t0 = WallInstant::now();
        let t_us = k * 1000;
        let now = Instant::from_micros(t_us);
        let mut feed = |ctl: &mut Controller, frame: &CanFrame| {
            ctl.on_frame(now, frame);
            recorder.received(t_us, frame);
        };
        if k == 1 {
            feed(&mut ctl, &Command::Mode(ModeRequest::Enable).to_can_frame());
        }
        if k % 20 == 0 {
            let twist = Command::Twist(TwistCmd {
                vx: 0.8,
                vy: -0.3,
                wz: 0.5,
                seq: (k / 20) as u8,
            });
            feed(&mut ctl, &twist.to_can_frame());
        }
        for w in 0..4 {
            angle[w] = (angle[w] + (rpm[w].unsigned_abs() / 8)) % 8192;
            feed(&mut ctl, &feedback(w as u8 + 1, angle[w], rpm[w]));
        }
        let out = ctl.step(now);
        recorder.stepped(t_us, &ctl);
        for frame in &out {
            recorder.sent(t_us, t_us + 20, black_box(frame), true);
        }
        recorder.step_done();
        times.push(t0.elapsed().as_nanos() as u64);
    }
    Times(times)
}

fn main() {
    // `cargo bench` passes `--bench`; nothing else is taken.
    let steps: u64 = std::env::var("RECORDER_BENCH_STEPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10_000);
    let path = std::env::temp_dir().join(format!("recorder-bench-{}.mcap", std::process::id()));

    let bare = run(steps, &mut ());
    let mut log = McapRecorder::create(
        &path,
        &Controller::new(&Config::dji_m3508_example()).expect("the example"),
    )
    .expect("create the log");
    let logged = run(steps, &mut log);
    let (messages, dropped) = (log.messages(), log.dropped());
    log.finish().expect("finish the log");
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let _ = std::fs::remove_file(&path);

    println!("recorder bench: {steps} steps at 1 kHz, DJI C620 x 4, a 50 Hz host");
    println!("  loop thread per step, no log:   {}", bare.line());
    println!("  loop thread per step, --log:    {}", logged.line());
    println!(
        "  logging cost per step: mean {:+.2} µs, p50 {:+.2} µs, p99 {:+.2} µs",
        logged.mean() - bare.mean(),
        logged.quantile(0.5) - bare.quantile(0.5),
        logged.quantile(0.99) - bare.quantile(0.99)
    );
    let per_hour = bytes as f64 / steps as f64 * 3.6e6;
    println!(
        "  log: {bytes} bytes, {messages} messages, {dropped} dropped; {:.0} bytes/step = {:.0} MB per hour at 1 kHz",
        bytes as f64 / steps as f64,
        per_hour / 1e6
    );
}
