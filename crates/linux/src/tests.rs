//! The loop's tests: a real core on a [`ScriptedBus`] in [`ScriptedClock`] time.

use super::*;
use crate::testing::{ScriptedBus, ScriptedClock};
use core::fmt;
use core::sync::atomic::{AtomicUsize, Ordering};
use std::io;

use embedded_can::Frame as _;

use firmware::CanFrame;
use firmware::control::Controller;

use firmware::config::Config;
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};
use std::collections::VecDeque;
use std::rc::Rc;

/// The frames `bus` sent: (time, standard id).
fn sent_ids(bus: &ScriptedBus) -> Vec<(u64, u16)> {
    bus.sent.iter().map(|(t, f)| (*t, raw_id(f))).collect()
}

fn raw_id(f: &CanFrame) -> u16 {
    match f.id() {
        embedded_can::Id::Standard(id) => id.as_raw(),
        embedded_can::Id::Extended(_) => u16::MAX,
    }
}

fn dji() -> Controller {
    Controller::new(&Config::dji_m3508_example()).unwrap()
}

/// A clock at [`T0`] and an empty bus on it.
fn scripted() -> (Rc<ScriptedClock>, ScriptedBus) {
    let clock = ScriptedClock::new(T0, [], 0);
    let bus = ScriptedBus::new(&clock, []);
    (clock, bus)
}

/// [`run`] of the DJI example's core on `bus`, with no stop signal.
fn run_dji<B: Bus>(bus: &mut B, clock: &ScriptedClock, options: &RunOptions) -> Report {
    run(&mut dji(), bus, clock, options, &AtomicUsize::new(0))
}

fn for_ms(ms: u64) -> RunOptions {
    RunOptions {
        duration_us: Some(ms * 1000),
        ..RunOptions::default()
    }
}

const T0: u64 = 7_000_000;

/// Times of the DJI command frames (0x200), one per step.
fn motor_times(bus: &ScriptedBus) -> Vec<u64> {
    sent_ids(bus)
        .into_iter()
        .filter(|&(_, id)| id == 0x200)
        .map(|(t, _)| t)
        .collect()
}

#[test]
fn steps_at_absolute_deadlines() {
    let (clock, mut bus) = scripted();
    let r = run_dji(&mut bus, &clock, &for_ms(10));
    assert_eq!(r.stop, StopReason::Duration);
    assert_eq!(r.period_us, 1000);
    assert_eq!(r.steps, 10);
    assert_eq!(r.node.controller.steps, 10);
    assert_eq!(r.overruns, 0);
    // 10 steps + the shutdown frame.
    let expected: Vec<u64> = (0..10).map(|k| T0 + k * 1000).chain([T0 + 9000]).collect();
    assert_eq!(motor_times(&bus), expected);
    assert_eq!(r.jitter.samples, 10);
    assert_eq!(r.jitter.max_us, Some(0));
    // Step 0: motor command, odometry (2), status, status counters, heartbeat; steps 1-9:
    // motor command.
    assert_eq!(r.frames_sent, 6 + 9);
    let first: Vec<u16> = sent_ids(&bus).iter().take(6).map(|x| x.1).collect();
    assert_eq!(first, [0x200, 0x310, 0x311, 0x312, 0x313, 0x31F]);
    assert_eq!(r.send_errors, 0);
    assert_eq!(r.node.shutdown.sent, 1);
}

#[test]
fn a_late_wake_up_does_not_shift_the_schedule() {
    let (clock, mut bus) = scripted();
    clock.push_lateness([0, 300, 0, 999, 0]);
    let r = run_dji(&mut bus, &clock, &for_ms(5));
    let t = motor_times(&bus);
    assert_eq!(&t[..5], &[T0, T0 + 1300, T0 + 2000, T0 + 3999, T0 + 4000]);
    assert_eq!(r.overruns, 0);
    assert_eq!(r.jitter.max_us, Some(999));
    assert_eq!(r.jitter.p50_us, Some(0));
}

#[test]
fn an_overrun_is_counted_and_re_anchors() {
    let (clock, mut bus) = scripted();
    clock.push_lateness([0, 0, 2500, 0, 0]);
    let r = run_dji(&mut bus, &clock, &for_ms(7));
    let t = motor_times(&bus);
    // Step 2 was due at +2000 and ran at +4500; the next steps follow it by one period,
    // with no catch-up burst.
    assert_eq!(&t[..5], &[T0, T0 + 1000, T0 + 4500, T0 + 5500, T0 + 6500]);
    assert_eq!(r.overruns, 1);
    assert_eq!(r.jitter.max_us, Some(2500));
}

#[test]
fn slow_steps_within_one_period_are_not_overruns() {
    let clock = ScriptedClock::new(T0, [], 0);
    // Every step takes 1.2 periods in sends: each starts late, the lateness grows by
    // 200 µs a step until it passes one period (step 6, 1200 µs late), then re-anchors.
    struct Slow(ScriptedBus);
    impl Bus for Slow {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            self.0.try_recv()
        }
        fn send(&mut self, f: &CanFrame) -> io::Result<()> {
            let sent = self.0.send(f);
            if raw_id(f) == 0x200 {
                self.0.clock.advance(1200);
            }
            sent
        }
    }
    let mut slow = Slow(ScriptedBus::new(&clock, []));
    let r = run_dji(&mut slow, &clock, &for_ms(8));
    assert_eq!(r.steps, 7);
    assert_eq!(r.overruns, 1);
    assert_eq!(r.jitter.max_us, Some(1200));
    assert_eq!(r.step_time.p50_us, Some(1200));
    // Step 6 was due at +6000 and started at +7200.
    let t = motor_times(&slow.0);
    assert_eq!(t[6], T0 + 7200);
}

#[test]
fn frames_received_before_a_step_are_fed_to_it() {
    let (clock, mut bus) = scripted();
    let status_req = Command::StatusRequest.to_can_frame();
    bus.incoming.push_back((T0 + 2500, status_req));
    let r = run_dji(&mut bus, &clock, &for_ms(5));
    let status: Vec<u64> = sent_ids(&bus)
        .into_iter()
        .filter(|&(_, id)| id == 0x312)
        .map(|(t, _)| t)
        .collect();
    // The periodic status of step 0, then the requested one at the first step after the
    // request arrived.
    assert_eq!(status, [T0, T0 + 3000]);
    assert_eq!(r.frames_received, 1);
}

#[test]
fn every_waiting_frame_is_drained_up_to_the_cap() {
    let (clock, mut bus) = scripted();
    // Unknown ids: counted by the controller as rejected.
    let junk = CanFrame::standard(embedded_can::StandardId::new(0x123).unwrap(), &[1]).unwrap();
    for _ in 0..10 {
        bus.incoming.push_back((T0 + 500, junk));
    }
    let options = RunOptions {
        max_rx_per_step: 4,
        ..for_ms(5)
    };
    let r = run_dji(&mut bus, &clock, &options);
    assert_eq!(r.frames_received, 10);
    assert_eq!(r.node.controller.rx_errors.unknown_id, 10);
    // Steps 1 and 2 took 4 frames each, step 3 the last 2.
    assert_eq!(r.rx_capped_steps, 2);
}

fn drive_frames(t: u64) -> [(u64, CanFrame); 2] {
    [
        (t, Command::Mode(ModeRequest::Enable).to_can_frame()),
        (
            t + 1,
            Command::Twist(TwistCmd {
                vx: 1.0,
                vy: 0.0,
                wz: 0.0,
                seq: 0,
            })
            .to_can_frame(),
        ),
    ]
}

#[test]
fn a_stop_sends_the_shutdown_frames() {
    let (clock, mut bus) = scripted();
    bus.incoming.extend(drive_frames(T0 + 100));
    let stop = Rc::new(AtomicUsize::new(0));
    bus.stop_at = Some((T0 + 5000, Rc::clone(&stop)));
    let mut ctl = dji();
    let r = run(&mut ctl, &mut bus, &*clock, &RunOptions::default(), &stop);
    assert_eq!(r.stop, StopReason::Signal(15));
    assert_eq!(r.stop.to_string(), "SIGTERM");
    assert_eq!(r.steps, 6);
    assert_eq!(r.node.controller.state_at_stop, "ENABLED");
    assert_eq!(r.node.controller.state_after_shutdown, "DISABLED");
    let motor: Vec<&CanFrame> = bus
        .sent
        .iter()
        .filter(|(_, f)| raw_id(f) == 0x200)
        .map(|(_, f)| f)
        .collect();
    assert_eq!(motor.len(), 7);
    // Driving before the stop; zero current after it.
    assert_ne!(motor[5].data(), &[0; 8]);
    assert_eq!(motor[6].data(), &[0; 8]);
    assert_eq!(bus.sent.last().map(|(_, f)| *f), Some(*motor[6]));
    assert_eq!(
        r.node.shutdown,
        ShutdownReport {
            frames: 1,
            sent: 1,
            failed: 0
        }
    );
}

#[test]
fn odrive_shutdown_is_zero_velocity_then_idle_per_axis() {
    let (clock, mut bus) = scripted();
    let mut ctl = Controller::new(&Config::odrive_example()).unwrap();
    let r = run(
        &mut ctl,
        &mut bus,
        &*clock,
        &for_ms(3),
        &AtomicUsize::new(0),
    );
    assert_eq!(r.node.shutdown.frames, 8);
    let tail: Vec<u16> = sent_ids(&bus)[bus.sent.len() - 8..]
        .iter()
        .map(|x| x.1)
        .collect();
    // node << 5 | 0x0D (Set_Input_Vel), node << 5 | 0x07 (Set_Axis_State).
    assert_eq!(tail, [0x0D, 0x07, 0x2D, 0x27, 0x4D, 0x47, 0x6D, 0x67]);
}

#[test]
fn busy_sends_are_retried() {
    let (clock, mut bus) = scripted();
    bus.busy = 3;
    let r = run_dji(&mut bus, &clock, &for_ms(3));
    assert_eq!(r.send_retries, 3);
    assert_eq!(r.send_errors, 0);
    assert_eq!(r.frames_sent, 6 + 2);
    // The first frame went out after three 20 µs back-offs.
    assert_eq!(bus.sent[0], (T0 + 60, bus.sent[0].1));
    assert!(r.errors.first.is_none());
}

#[test]
fn a_bus_that_stays_busy_drops_frames_and_keeps_the_schedule() {
    let (clock, mut bus) = scripted();
    bus.busy = u64::MAX;
    let r = run_dji(&mut bus, &clock, &for_ms(4));
    assert_eq!(r.steps, 4);
    assert_eq!(r.overruns, 0);
    assert_eq!(r.frames_sent, 0);
    assert_eq!(r.send_errors, 6 + 3);
    // Retries end half a period after the deadline.
    assert!(r.jitter.max_us.unwrap() < 1000, "{r:?}");
    assert_eq!(r.node.shutdown.failed, 1);
    let e = r.errors.first.as_deref().unwrap();
    assert!(e.starts_with("send 0x200: "), "{e}");
    // The shutdown was retried for its whole budget.
    assert!(r.elapsed_us >= 3000 + RunOptions::default().shutdown_budget_us - 20);
}

#[test]
fn other_send_errors_are_counted_without_retry() {
    struct Down;
    impl Bus for Down {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            Err(io::Error::from_raw_os_error(libc::EIO))
        }
        fn send(&mut self, _: &CanFrame) -> io::Result<()> {
            Err(io::Error::from_raw_os_error(libc::EIO))
        }
    }
    let clock = ScriptedClock::new(T0, [], 0);
    let r = run_dji(&mut Down, &clock, &for_ms(2));
    assert_eq!(r.steps, 2);
    assert_eq!(r.send_retries, 0);
    assert_eq!(r.send_errors, 6 + 1);
    assert_eq!(r.rx_errors, 2);
    assert!(r.errors.first.unwrap().starts_with("receive: "));
    assert!(r.errors.last.unwrap().starts_with("shutdown send 0x200: "));
    assert_eq!(r.node.shutdown.failed, 1);
    // The shutdown frame too.
    assert_eq!(r.send_errors_by_kind.other, 7 + 1);
    assert_eq!(r.rx_errors_by_kind.other, 2);
    assert_eq!(r.link, LinkReport::default());
}

/// What a recorder hears of the link: (core µs, "lost: error" / "back after N µs, try K").
#[derive(Default)]
struct LinkLog(Vec<(u64, String)>);

impl Recorder for LinkLog {
    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        let text = match event {
            LinkEvent::Lost { error } => format!("lost: {error}"),
            LinkEvent::Restored { down_us, attempts } => {
                format!("back after {down_us} µs, try {attempts}")
            }
        };
        self.0.push((t_us, text));
    }
}

#[test]
fn a_lost_link_keeps_the_core_stepping_and_resumes_when_it_is_back() {
    let (clock, mut bus) = scripted();
    // Down from 5 ms to 25 ms.
    bus.down = Some((T0 + 5_000, T0 + 25_000));
    let mut events = LinkLog::default();
    let mut ctl = dji();
    let r = run_recorded(
        &mut ctl,
        &mut bus,
        &*clock,
        &for_ms(60),
        &AtomicUsize::new(0),
        &mut events,
        &mut (),
    );
    // Every step ran, on schedule.
    assert_eq!((r.steps, r.overruns), (60, 0));
    // Lost at the first receive of the 5 ms step; reopen tried 10 ms later (15 ms,
    // down), then 20 ms after that (35 ms, up).
    assert_eq!(
        bus.reopens,
        [(T0 + 15_000, false), (T0 + 35_000, true)],
        "reopen attempts"
    );
    assert_eq!(
        events.0,
        [
            (
                5_000,
                "lost: receive: Network is down (os error 100)".to_string()
            ),
            (35_000, "back after 30000 µs, try 2".to_string()),
        ]
    );
    let l = r.link;
    assert_eq!(
        (l.losses, l.recoveries, l.reopen_attempts, l.down_at_stop),
        (1, 1, 2, false)
    );
    assert_eq!((l.down_us, l.longest_down_us), (30_000, 30_000));
    // Steps 5..=34 (30 steps) sent nothing, none tried: 30 motor commands and the
    // odometry pairs of the 10, 20 and 30 ms steps.
    assert_eq!(l.frames_not_sent, 30 + 3 * 2);
    let times = motor_times(&bus);
    assert_eq!(times.len(), 60 - 30 + 1, "{times:?}");
    assert!(
        times
            .iter()
            .all(|&t| !(T0 + 5_000..T0 + 35_000).contains(&t))
    );
    assert_eq!(r.rx_errors_by_kind.link_down, 1);
    assert_eq!(r.send_errors, 0, "no send was tried while down");
    assert_eq!(r.node.shutdown.failed, 0);
    let text = r.to_string();
    assert!(
        text.contains("link: lost 1 time(s), back 1 time(s); down 0.030 s in total"),
        "{text}"
    );
}

#[test]
fn a_link_lost_on_a_send_backs_off_up_to_the_limit() {
    let (clock, mut bus) = scripted();
    // The receive of the first down step already happened: the send sees it first.
    bus.down = Some((T0 + 2_000, T0 + 1_000_000));
    bus.down_reported = true;
    let options = RunOptions {
        link_retry_min_us: 10_000,
        link_retry_max_us: 40_000,
        ..for_ms(200)
    };
    let r = run_dji(&mut bus, &clock, &options);
    let tries: Vec<u64> = bus.reopens.iter().map(|&(t, _)| t - T0).collect();
    // 10, 20, 40, 40, 40 ms apart; then the one try before the shutdown.
    assert_eq!(
        tries,
        [12_000, 32_000, 72_000, 112_000, 152_000, 192_000, 199_000]
    );
    assert_eq!(r.send_errors_by_kind.link_down, 1 + 1);
    assert!(r.link.down_at_stop);
    assert_eq!(r.link.down_us, 199_000 - 2_000);
    assert_eq!(r.node.shutdown.failed, 1);
}

#[test]
fn exit_on_link_loss_stops_the_loop_with_the_reason() {
    let (clock, mut bus) = scripted();
    bus.down = Some((T0 + 3_000, u64::MAX));
    let options = RunOptions {
        exit_on_link_loss: true,
        ..for_ms(50)
    };
    let r = run_dji(&mut bus, &clock, &options);
    // The step that saw the loss ran (the core is never skipped); the next one stops.
    assert_eq!((r.stop, r.steps), (StopReason::LinkLost, 4));
    assert_eq!(r.stop.to_string(), "link lost (exit on link loss)");
    assert!(r.link.down_at_stop);
    assert_eq!(r.link.losses, 1);
    // The one reopen before the shutdown failed; the shutdown frame was tried.
    assert_eq!(r.link.reopen_attempts, 1);
    assert_eq!(
        r.link_error.as_deref(),
        Some("receive: Network is down (os error 100)")
    );
    assert_eq!(r.node.shutdown.failed, 1);
    assert_eq!(
        serde_json::to_value(r.stop).unwrap(),
        serde_json::json!("link_lost")
    );
}

#[test]
fn bus_errors_are_classified_for_the_link() {
    let e = io::Error::from_raw_os_error;
    assert_eq!(classify(&e(libc::ENOBUFS)), ErrorKind::Busy);
    assert_eq!(classify(&e(libc::EAGAIN)), ErrorKind::Busy);
    assert_eq!(classify(&e(libc::ENETDOWN)), ErrorKind::LinkDown);
    assert_eq!(classify(&e(libc::ENODEV)), ErrorKind::NoDevice);
    assert_eq!(classify(&e(libc::ENXIO)), ErrorKind::NoDevice);
    assert_eq!(classify(&e(libc::EIO)), ErrorKind::Other);
}

#[test]
fn bus_error_frames_are_counted_and_the_frames_behind_them_still_read() {
    /// Two twist commands with a controller error frame between them, then nothing.
    struct Noisy(VecDeque<io::Result<Option<CanFrame>>>);
    impl Bus for Noisy {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            self.0.pop_front().unwrap_or(Ok(None))
        }
        fn send(&mut self, _: &CanFrame) -> io::Result<()> {
            Ok(())
        }
    }
    let twist = |seq| {
        Command::Twist(TwistCmd {
            vx: 0.1,
            vy: 0.0,
            wz: 0.0,
            seq,
        })
        .to_can_frame()
    };
    let error = io::Error::other(BusErrorFrame("bus-off".into()));
    assert!(is_bus_error_frame(&error));
    assert!(!is_bus_error_frame(&io::Error::from_raw_os_error(
        libc::ENETDOWN
    )));
    let mut bus = Noisy(VecDeque::from([
        Ok(Some(twist(0))),
        Err(error),
        Ok(Some(twist(1))),
    ]));
    let clock = ScriptedClock::new(T0, [], 0);
    let r = run_dji(&mut bus, &clock, &for_ms(2));
    assert_eq!(
        (r.frames_received, r.bus_error_frames, r.rx_errors),
        (2, 1, 0)
    );
    assert_eq!(
        r.errors.first.as_deref(),
        Some("receive: error frame: bus-off")
    );
    assert!(r.to_string().contains("1 bus error frames"), "{r}");
}

#[test]
fn a_stop_before_the_first_step_still_shuts_down() {
    let (clock, mut bus) = scripted();
    let r = run(
        &mut dji(),
        &mut bus,
        &*clock,
        &RunOptions::default(),
        &AtomicUsize::new(2),
    );
    assert_eq!((r.stop, r.steps), (StopReason::Signal(2), 0));
    assert_eq!(r.stop.to_string(), "SIGINT");
    assert_eq!(r.jitter.p99_us, None);
    assert_eq!(sent_ids(&bus), [(T0, 0x200)]);
    assert_eq!(r.node.controller.rx_errors.unknown_id, 0);
    let text = r.to_string();
    assert!(
        text.contains("jitter (step start - deadline): no samples"),
        "{text}"
    );
    assert!(text.contains("shutdown: 1 of 1 frames sent"), "{text}");
}

#[test]
fn the_report_serialises_to_json() {
    let (clock, mut bus) = scripted();
    let r = run_dji(&mut bus, &clock, &for_ms(2));
    let v: serde_json::Value = serde_json::to_value(&r).unwrap();
    assert_eq!(v["stop"], "duration");
    assert_eq!(v["steps"], 2);
    assert_eq!(v["jitter"]["p99_us"], 0);
    assert_eq!(v["controller"]["state_at_stop"], "DISABLED");
    assert_eq!(v["controller"]["rx_errors"]["wrong_dlc"], 0);
    assert_eq!(v["controller"]["repeated_seq"], 0);
    assert_eq!(v["shutdown"]["sent"], 1);
    let stopped = serde_json::to_value(StopReason::Signal(2)).unwrap();
    assert_eq!(stopped, serde_json::json!({ "signal": 2 }));
}

#[test]
fn busy_errors_are_enobufs_and_eagain() {
    assert!(is_busy(&io::Error::from_raw_os_error(libc::ENOBUFS)));
    assert!(is_busy(&io::Error::from_raw_os_error(libc::EAGAIN)));
    assert!(!is_busy(&io::Error::from_raw_os_error(libc::ENETDOWN)));
}

#[test]
fn opening_a_missing_interface_names_it() {
    let e = SocketCanBus::open("nosuchcan9").unwrap_err();
    let text = e.to_string();
    assert!(text.contains("\"nosuchcan9\""), "{text}");
}

#[test]
fn monotonic_clock_never_wakes_early() {
    for spin in [0, 200] {
        let c = MonotonicClock::new(spin);
        let deadline = c.now_micros() + 1500;
        c.sleep_until(deadline);
        assert!(c.now_micros() >= deadline);
        // A past deadline returns at once.
        c.sleep_until(0);
    }
}

/// The only test in this process that installs the handlers or raises a signal: a
/// second SIGTERM would end the test binary, by design.
#[test]
fn the_first_stop_signal_sets_the_flag_to_its_number() {
    let stop = stop_on_signals().unwrap();
    assert_eq!(stop.load(Ordering::Relaxed), 0);
    signal_hook::low_level::raise(signal_hook::consts::SIGTERM).unwrap();
    assert_eq!(stop.load(Ordering::Relaxed), 15);
}

#[test]
fn an_error_line_names_each_cause_once() {
    #[derive(Debug)]
    struct Outer(io::Error, &'static str);
    impl fmt::Display for Outer {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str(self.1)
        }
    }
    impl std::error::Error for Outer {
        fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
            Some(&self.0)
        }
    }
    let cause = || io::Error::other("disk full");
    let e = Outer(cause(), "writing log.mcap");
    assert_eq!(error_line(&e), "writing log.mcap: disk full");
    let e = Outer(cause(), "writing log.mcap: disk full");
    assert_eq!(error_line(&e), "writing log.mcap: disk full");
}
