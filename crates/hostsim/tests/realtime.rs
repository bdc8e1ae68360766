//! The real-time loops without a CAN interface: the firmware runner's loop
//! (`mecanum_linux::run`), the plant loop (`hostsim::realtime::run_plant`) and a scripted
//! host, each on its own thread, on one in-memory bus, in virtual time. Deterministic: the
//! loops run at phases offset within the period, so no two run at the same virtual instant.

use std::cell::Cell;
use std::io;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::thread;

use firmware::control::Snapshot;
use firmware::protocol::robot::{Command, ModeRequest, RobotState, Telemetry, TwistCmd};
use firmware::{CanFrame, Config, Controller};
use hostsim::nodes::SimPlant;
use hostsim::nodes::drives::SimDrives;
use hostsim::nodes::imu::{ImuParams, WithImu};
use hostsim::realtime::{PlantOptions, PlantReport, PlayOptions, play_frames, run_plant};
use hostsim::replay::TimedFrame;
use mecanum_linux::testing::{MemoryBus, MemoryPort, VirtualClock, VirtualClockHandle};
use mecanum_linux::{self as linux, Bus, Clock, RunOptions, StopReason};

const T0: u64 = 5_000_000;

/// What the host saw of the firmware's telemetry.
#[derive(Debug, Default, Clone, Copy)]
struct HostView {
    odom_x: Option<f32>,
    state: Option<RobotState>,
    frames: u64,
}

/// The host: enable at 50 ms, then a forward twist every 20 ms from 100 ms until `until_us`;
/// drains its port every millisecond and keeps the last odometry and state.
fn run_host(mut port: MemoryPort, clock: &VirtualClockHandle, vx: f32, until_us: u64) -> HostView {
    let mut view = HostView::default();
    let start = clock.now_micros();
    let mut seq = 0u8;
    let mut t = 250; // phase: between the firmware (0) and the plant (500)
    while t < until_us {
        clock.sleep_until(start + t);
        while let Ok(Some(f)) = port.try_recv() {
            view.frames += 1;
            match Telemetry::decode(&f) {
                Ok(Telemetry::OdomPosition(p)) => view.odom_x = Some(p.x),
                Ok(Telemetry::Status(s)) => view.state = Some(s.state),
                Ok(Telemetry::Heartbeat(h)) => view.state = Some(h.state),
                _ => {}
            }
        }
        let ms = t / 1000;
        if ms == 50 {
            port.send(&Command::Mode(ModeRequest::Enable).to_can_frame())
                .unwrap();
        }
        if ms >= 100 && ms.is_multiple_of(20) {
            let twist = Command::Twist(TwistCmd {
                vx,
                vy: 0.0,
                wz: 0.0,
                seq,
            });
            seq = seq.wrapping_add(1);
            port.send(&twist.to_can_frame()).unwrap();
        }
        t += 1000;
    }
    view
}

/// What the three loops of [`run_together`] report.
struct Together {
    fw_report: linux::Report,
    snapshot: Snapshot,
    plant_report: PlantReport,
    view: HostView,
}

/// The firmware runner of `config`, the plant loop (its drives, and an IMU node with `imu`)
/// and the host driving at `vx` ([`run_host`]), each on its own thread for `duration_us` of
/// virtual time on one bus.
fn run_together(config: Config, duration_us: u64, vx: f32, imu: Option<ImuParams>) -> Together {
    let bus = MemoryBus::new();
    let clock = VirtualClock::new(T0);
    let (fw_clock, plant_clock, host_clock) = (clock.join(), clock.join(), clock.join());
    let (mut fw_port, mut plant_port, host_port) = (bus.port(), bus.port(), bus.port());

    let fw = thread::spawn(move || {
        let mut ctl = Controller::new(&config).unwrap();
        let options = RunOptions {
            duration_us: Some(duration_us),
            ..RunOptions::default()
        };
        let r = linux::run(
            &mut ctl,
            &mut fw_port,
            &fw_clock,
            &options,
            &AtomicUsize::new(0),
        );
        (r, ctl.snapshot())
    });
    let plant = thread::spawn(move || {
        let mut drives = SimDrives::new(&config).unwrap();
        // Half a period after the firmware: a command sent at a step is applied at the
        // next tick, feedback sent at a tick is read at the next step.
        plant_clock.sleep_until(T0 + 500);
        let options = PlantOptions {
            duration_us: Some(duration_us),
            ..PlantOptions::default()
        };
        let stop = AtomicUsize::new(0);
        match imu {
            Some(imu) => {
                let mut plant = WithImu::new(&mut drives, Some(&imu), 0);
                run_plant(&mut plant, &mut plant_port, &plant_clock, &options, &stop)
            }
            None => run_plant(&mut drives, &mut plant_port, &plant_clock, &options, &stop),
        }
    });
    let host = thread::spawn(move || run_host(host_port, &host_clock, vx, duration_us));

    let (fw_report, snapshot) = fw.join().unwrap();
    Together {
        fw_report,
        snapshot,
        plant_report: plant.join().unwrap(),
        view: host.join().unwrap(),
    }
}

#[test]
fn the_firmware_runner_drives_the_real_time_plant_forward() {
    let vx = 0.5f32;
    let Together {
        fw_report,
        snapshot,
        plant_report,
        view,
    } = run_together(Config::dji_m3508_example(), 2_000_000, vx, None);

    // The firmware ran 2000 steps, on time, enabled, with all four motors online.
    assert_eq!(fw_report.stop, StopReason::Duration);
    assert_eq!((fw_report.steps, fw_report.overruns), (2000, 0));
    assert_eq!(fw_report.node.controller.state_at_stop, "ENABLED");
    assert_eq!(fw_report.node.controller.motors_online, 0b1111);
    assert_eq!(fw_report.send_errors, 0);
    // The plant: 2000 ticks, no lateness in virtual time, 4 feedback frames a millisecond.
    assert_eq!(plant_report.stop, StopReason::Duration);
    assert_eq!((plant_report.steps, plant_report.overruns), (2000, 0));
    assert_eq!(plant_report.jitter.max_us, Some(0));
    assert!(
        (1.998..=2.0).contains(&plant_report.node.simulated_s),
        "{plant_report:?}"
    );
    assert!(
        plant_report.frames_sent >= 4 * 1990,
        "{}",
        plant_report.frames_sent
    );
    assert!(plant_report.frames_received > 2000);

    eprintln!(
        "truth {:?}, velocity {:?}, firmware odometry x {}",
        plant_report.node.truth, plant_report.node.velocity, snapshot.pose.x
    );
    // Driving forward from 0.1 s: truth x ≈ vx · 1.9 s within 20 %.
    let expected = f64::from(vx) * 1.9;
    let x = plant_report.node.truth.x;
    assert!(
        (x - expected).abs() <= 0.2 * expected,
        "truth x {x:.3} m, expected {expected:.3} m ± 20 %: {plant_report}"
    );
    assert!(plant_report.node.truth.y.abs() < 0.02 && plant_report.node.truth.heading.abs() < 0.02);
    assert!(
        (plant_report.node.velocity.vx - f64::from(vx)).abs() < 0.1,
        "{:?}",
        plant_report.node.velocity
    );
    // The firmware's odometry follows the truth, and the host saw it.
    let odom_x = f64::from(snapshot.pose.x);
    assert!((odom_x - x).abs() < 0.05, "odometry {odom_x}, truth {x}");
    assert_eq!(view.state, Some(RobotState::Enabled));
    let seen = f64::from(view.odom_x.unwrap());
    assert!(
        (seen - odom_x).abs() < 0.02,
        "host saw {seen}, core {odom_x}"
    );
}

#[test]
fn the_plant_stops_on_the_flag_and_reports_json() {
    let clock = VirtualClock::new(T0);
    let h = clock.join();
    let bus = MemoryBus::new();
    let port = bus.port();
    let mut tap = bus.port();
    let mut drives = SimDrives::new(&Config::dji_m3508_example()).unwrap();

    /// Sets the stop flag once the clock passes a time.
    struct StopAt<'a, B> {
        inner: B,
        clock: &'a VirtualClockHandle,
        at: u64,
        flag: &'a AtomicUsize,
    }
    impl<B: Bus> Bus for StopAt<'_, B> {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            if self.clock.now_micros() >= self.at {
                self.flag.store(15, Ordering::Relaxed);
            }
            self.inner.try_recv()
        }
        fn send(&mut self, f: &CanFrame) -> io::Result<()> {
            self.inner.send(f)
        }
    }
    let flag = AtomicUsize::new(0);
    let mut bus = StopAt {
        inner: port,
        clock: &h,
        at: T0 + 10_000,
        flag: &flag,
    };
    let r = run_plant(&mut drives, &mut bus, &h, &PlantOptions::default(), &flag);
    assert_eq!(r.stop, StopReason::Signal(15));
    assert_eq!(r.stop.to_string(), "SIGTERM");
    // Ticks at 0..=10 ms; the flag is seen at the top of the next one.
    assert_eq!(r.steps, 11);
    // DJI feedback from 1 ms: ten ticks of four frames.
    assert_eq!(r.frames_sent, 40);
    assert_eq!(tap.pending(), 40);
    let first = tap.try_recv().unwrap().unwrap();
    assert_eq!(
        embedded_can::Frame::id(&first),
        embedded_can::Id::Standard(embedded_can::StandardId::new(0x201).unwrap())
    );
    let v = serde_json::to_value(&r).unwrap();
    assert_eq!(v["stop"], serde_json::json!({ "signal": 15 }));
    assert_eq!(v["steps"], 11);
    assert_eq!(v["frames_sent"], 40);
    assert_eq!(v["truth"]["x"], 0.0);
    assert!(v["velocity"]["vx"].is_number());
    assert!(v["jitter"]["p99_us"].is_number());
    let text = r.to_string();
    assert!(text.contains("ground truth: x +0.0000 m"), "{text}");
}

/// A clock that wakes up late by a scripted amount, then jumps.
struct LateClock {
    now: Cell<u64>,
    late: Vec<u64>,
    calls: Cell<usize>,
}

impl LateClock {
    /// At `T0`; the n-th sleep wakes `late[n]` µs after its deadline (on time past the list).
    fn new(late: Vec<u64>) -> Self {
        Self {
            now: Cell::new(T0),
            late,
            calls: Cell::new(0),
        }
    }
}

impl Clock for LateClock {
    fn now_micros(&self) -> u64 {
        self.now.get()
    }
    fn sleep_until(&self, deadline_us: u64) {
        let i = self.calls.get();
        self.calls.set(i + 1);
        let late = self.late.get(i).copied().unwrap_or(0);
        self.now.set(self.now.get().max(deadline_us) + late);
    }
}

/// Counts plant steps.
struct CountingPlant {
    steps: u64,
}

impl SimPlant for CountingPlant {
    fn on_frame(&mut self, _: u64, _: &CanFrame) {}
    fn feedback(&mut self, _: u64, _: &mut Vec<(u64, CanFrame)>) {}
    fn advance(&mut self, _: f64) {
        self.steps += 1;
    }
    fn truth(&self) -> [f64; 3] {
        [self.steps as f64, 0.0, 0.0]
    }
    fn truth_velocity(&self) -> [f64; 3] {
        [0.0; 3]
    }
    fn set_faults(&mut self, _: u64, _: [bool; 4], _: [bool; 4]) {}
}

#[test]
fn late_ticks_catch_up_and_overruns_re_anchor() {
    // Tick 2 wakes 2.5 ms late (an overrun); tick 5 wakes 300 ms late, beyond the 100-step
    // catch-up cap.
    let clock = LateClock::new(vec![0, 0, 2500, 0, 0, 300_000]);
    let mut plant = CountingPlant { steps: 0 };
    let bus = MemoryBus::new();
    let mut port = bus.port();
    let options = PlantOptions {
        duration_us: Some(310_000),
        ..PlantOptions::default()
    };
    let r = run_plant(
        &mut plant,
        &mut port,
        &clock,
        &options,
        &AtomicUsize::new(0),
    );
    assert_eq!(r.overruns, 2);
    assert_eq!(r.jitter.max_us, Some(300_000));
    // Simulated time follows the clock up to the cap: tick 5 was due at 7.5 ms (6.5 ms after
    // the re-anchoring) and woke at 307.5 ms with the plant at 6 ms; it caught up 100 steps
    // to 106 ms and skipped the remaining 201 ms.
    let elapsed_sim = r.elapsed_us - r.node.skipped_us;
    assert_eq!(r.node.skipped_us, 201_000);
    assert!(
        (r.node.simulated_s * 1e6 - elapsed_sim as f64).abs() <= 1000.0,
        "{r:?}"
    );
    assert_eq!(plant.steps as f64, (r.node.simulated_s * 1000.0).round());
}

#[test]
fn played_frames_reach_the_other_nodes_in_order_and_on_time() {
    let clock = VirtualClock::new(T0);
    let player_clock = clock.join();
    let bus = MemoryBus::new();
    let mut player = bus.port();
    let mut listener = bus.port();
    let frames: Vec<TimedFrame> = (0..50u16)
        .map(|i| TimedFrame {
            t_ns: 1_000_000_000 + u64::from(i) * 2_000_000,
            frame: CanFrame::standard(
                embedded_can::StandardId::new(0x201 + i % 4).unwrap(),
                &[i as u8],
            )
            .unwrap(),
        })
        .collect();
    let r = play_frames(
        &frames,
        &mut player,
        &player_clock,
        &PlayOptions::default(),
        &AtomicUsize::new(0),
    );
    assert_eq!((r.frames, r.sent, r.failed, r.busy_retries), (50, 50, 0, 0));
    assert_eq!(r.log_span_us, 98_000);
    assert_eq!(r.elapsed_us, 98_000);
    assert_eq!(r.lateness.max_us, Some(0));
    let got: Vec<CanFrame> = std::iter::from_fn(|| listener.try_recv().unwrap()).collect();
    let want: Vec<CanFrame> = frames.iter().map(|f| f.frame).collect();
    assert_eq!(got, want);
}

#[test]
fn the_plant_counts_bus_error_frames_apart_and_reads_the_frames_behind_them() {
    /// A DJI current command, a controller error frame, another command, then a failed read.
    struct Noisy(std::collections::VecDeque<io::Result<Option<CanFrame>>>);
    impl Bus for Noisy {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            self.0.pop_front().unwrap_or(Ok(None))
        }
        fn send(&mut self, _: &CanFrame) -> io::Result<()> {
            Ok(())
        }
    }
    let current = firmware::protocol::dji::CurrentCommand {
        model: firmware::protocol::dji::EscModel::C620,
        group: firmware::protocol::dji::EscGroup::Esc1To4,
        raw: [1000; 4],
    }
    .to_can_frame();
    let mut bus = Noisy(std::collections::VecDeque::from([
        Ok(Some(current)),
        Err(io::Error::other(linux::BusErrorFrame("bus-off".into()))),
        Ok(Some(current)),
        Err(io::Error::from_raw_os_error(libc::ENETDOWN)),
    ]));
    let clock = LateClock::new(vec![]);
    let mut drives = SimDrives::new(&Config::dji_m3508_example()).unwrap();
    let options = PlantOptions {
        duration_us: Some(2_000),
        ..PlantOptions::default()
    };
    let r = run_plant(
        &mut drives,
        &mut bus,
        &clock,
        &options,
        &AtomicUsize::new(0),
    );
    assert_eq!(
        (r.frames_received, r.bus_error_frames, r.rx_errors),
        (2, 1, 1),
        "{r:?}"
    );
    assert_eq!(
        r.errors.first.as_deref(),
        Some("receive: error frame: bus-off")
    );
    let text = r.to_string();
    assert!(
        text.contains("1 receive errors, 1 bus error frames"),
        "{text}"
    );
}

#[test]
fn the_real_time_plant_can_carry_the_imu_for_a_gyro_runner() {
    // As `hostsim plant --imu` and a runner with [odometry] heading_source = "gyro".
    let mut config = Config::dji_m3508_example();
    config.odometry.heading_source = firmware::config::HeadingMode::Gyro;
    let imu = hostsim::nodes::imu::ImuParams::default();
    let Together {
        fw_report,
        snapshot,
        plant_report,
        ..
    } = run_together(config, 1_000_000, 0.3, Some(imu));
    // 4 feedback frames a millisecond and an IMU frame every 5 ms.
    assert!(
        plant_report.frames_sent >= 4 * 990 + 198,
        "{}",
        plant_report.frames_sent
    );
    assert_eq!(fw_report.node.controller.state_at_stop, "ENABLED");
    assert_eq!(
        snapshot.heading_source,
        firmware::control::HeadingSource::Gyro
    );
    // It stood still from its first feedback to the twist at 100 ms: bias samples, close to
    // the IMU's 0.1 °/s (10 noisy samples).
    assert!(
        (5..=12).contains(&snapshot.gyro_bias_samples),
        "{snapshot:?}"
    );
    let bias = f64::from(snapshot.gyro_bias).to_degrees();
    assert!((bias - 0.1).abs() < 0.1, "bias {bias} °/s");
    // Driving straight: the gyro heading stays with the truth's.
    let heading = f64::from(snapshot.pose.heading);
    assert!(
        (heading - plant_report.node.truth.heading).abs() < 0.005,
        "heading {heading}, truth {}",
        plant_report.node.truth.heading
    );
}
