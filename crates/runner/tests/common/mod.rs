//! What the runner's loop tests share: the scripted clock and bus (`mecanum_linux::testing`)
//! set up as they use them, and the frames of a session.

#![allow(dead_code)] // each test file uses its part

use std::collections::VecDeque;
use std::rc::Rc;
use std::sync::atomic::AtomicUsize;

use embedded_can::StandardId;
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};
use firmware::{CanFrame, Config, Controller};
use mecanum_linux::testing::{ScriptedBus, ScriptedClock};
use mecanum_linux::{ParamStore, Recorder, Report, RunOptions, run_recorded};

/// Where simulated time starts, µs.
pub const T0: u64 = 5_000_000;

/// A clock at [`T0`] whose wake-ups are late by `lateness`, one value per sleep; with `pace`
/// n > 0 it also sleeps 1/n of the simulated wait (a log's hand-overs are due to log time, as
/// in a real run, and its writer keeps up).
pub fn clock(lateness: impl IntoIterator<Item = u64>, pace: u64) -> Rc<ScriptedClock> {
    ScriptedClock::new(T0, lateness, pace)
}

/// A bus on `clock` that delivers `incoming`; every send takes 7 µs.
pub fn bus(clock: &Rc<ScriptedClock>, incoming: VecDeque<(u64, CanFrame)>) -> ScriptedBus {
    let mut bus = ScriptedBus::new(clock, incoming);
    bus.send_cost_us = 7;
    bus
}

/// Runs the core of `config` on `bus` for `duration_us` of `clock` time (no stop signal),
/// telling `recorder` what the loop does.
pub fn run_for(
    config: &Config,
    clock: &ScriptedClock,
    bus: &mut ScriptedBus,
    duration_us: u64,
    recorder: &mut impl Recorder,
) -> Report {
    let mut controller = Controller::new(config).unwrap();
    run_core(&mut controller, clock, bus, duration_us, recorder, &mut ())
}

/// [`run_for`] with the core `controller`, saving its parameters to `store`.
pub fn run_core(
    controller: &mut Controller,
    clock: &ScriptedClock,
    bus: &mut ScriptedBus,
    duration_us: u64,
    recorder: &mut impl Recorder,
    store: &mut dyn ParamStore,
) -> Report {
    let options = RunOptions {
        duration_us: Some(duration_us),
        ..RunOptions::default()
    };
    let stop = AtomicUsize::new(0);
    run_recorded(controller, bus, clock, &options, &stop, recorder, store)
}

/// A standard data frame.
pub fn std_frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
}

/// The four ESCs' feedback every millisecond of `ms` (wheels turning), a few µs apart.
pub fn esc_feedback(ms: std::ops::Range<u64>) -> Vec<(u64, CanFrame)> {
    let mut frames = Vec::new();
    for ms in ms {
        let angle = ((ms * 37) % 8192) as u16;
        for esc in 0..4u16 {
            let mut data = [0u8; 8];
            data[..2].copy_from_slice(&angle.to_be_bytes());
            data[2..4].copy_from_slice(&300i16.to_be_bytes());
            data[6] = 30;
            frames.push((
                T0 + ms * 1000 + 100 + u64::from(esc) * 3,
                std_frame(0x201 + esc, &data),
            ));
        }
    }
    frames
}

/// MODE_CMD enable at `ms`.
pub fn enable_at(ms: u64) -> (u64, CanFrame) {
    (
        T0 + ms * 1000,
        Command::Mode(ModeRequest::Enable).to_can_frame(),
    )
}

/// A host driving (0.5, 0.1, 0.2) with a TWIST_CMD every 20 ms of `ms`, `seq` counting.
pub fn twists(ms: std::ops::Range<u64>) -> impl Iterator<Item = (u64, CanFrame)> {
    ms.step_by(20).enumerate().map(|(seq, ms)| {
        let twist = TwistCmd {
            vx: 0.5,
            vy: 0.1,
            wz: 0.2,
            seq: seq as u8,
        };
        (T0 + ms * 1000 + 50, Command::Twist(twist).to_can_frame())
    })
}
