//! The test doubles of the runner's loop tests: a clock and a bus in memory, and the frames
//! of a session.

#![allow(dead_code)] // each test file uses its part

use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::io;
use std::rc::Rc;

use embedded_can::StandardId;
use firmware::CanFrame;
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};
use mecanum_linux::{Bus, Clock};

/// Where simulated time starts, µs.
pub const T0: u64 = 5_000_000;

/// Simulated time: `sleep_until` jumps to the deadline plus a scripted lateness. With
/// `pace` n > 0 it also sleeps 1/n of the simulated wait (a log's hand-overs are due to log
/// time, as in a real run, and its writer keeps up).
pub struct FakeClock {
    pub now: Cell<u64>,
    pub lateness: RefCell<VecDeque<u64>>,
    pub pace: u64,
}

impl FakeClock {
    /// A clock at [`T0`] whose wake-ups are late by `lateness`, one value per sleep.
    pub fn new(lateness: impl IntoIterator<Item = u64>, pace: u64) -> Rc<Self> {
        Rc::new(Self {
            now: Cell::new(T0),
            lateness: RefCell::new(lateness.into_iter().collect()),
            pace,
        })
    }
}

impl Clock for FakeClock {
    fn now_micros(&self) -> u64 {
        self.now.get()
    }
    fn sleep_until(&self, deadline_us: u64) {
        let late = self.lateness.borrow_mut().pop_front().unwrap_or(0);
        let ahead = deadline_us.saturating_sub(self.now.get());
        if let Some(wait) = ahead.checked_div(self.pace) {
            std::thread::sleep(std::time::Duration::from_micros(wait));
        }
        self.now.set(self.now.get().max(deadline_us) + late);
    }
}

/// Frames arrive at given times; every send takes 7 µs.
pub struct MemoryBus {
    pub clock: Rc<FakeClock>,
    pub incoming: VecDeque<(u64, CanFrame)>,
    pub sent: Vec<CanFrame>,
}

impl MemoryBus {
    /// A bus on `clock` that delivers `incoming`.
    pub fn new(clock: &Rc<FakeClock>, incoming: VecDeque<(u64, CanFrame)>) -> Self {
        Self {
            clock: Rc::clone(clock),
            incoming,
            sent: Vec::new(),
        }
    }
}

impl Bus for MemoryBus {
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
        match self.incoming.front() {
            Some(&(t, f)) if t <= self.clock.now_micros() => {
                self.incoming.pop_front();
                Ok(Some(f))
            }
            _ => Ok(None),
        }
    }
    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        self.clock.now.set(self.clock.now.get() + 7);
        self.sent.push(*frame);
        Ok(())
    }
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
