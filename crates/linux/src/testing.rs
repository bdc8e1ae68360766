//! Test doubles of the [`Bus`] and the [`Clock`], for one loop or several:
//!
//! - [`ScriptedClock`] and [`ScriptedBus`]: one loop on one thread, frames arriving at
//!   scripted times, wake-ups late by scripted amounts, sends busy or the link down when the
//!   script says (the loop's own tests and the runner's log tests);
//! - [`MemoryBus`] and [`VirtualClock`]: several loops on several threads (the runner's loop,
//!   the simulated drives, a scripted host) on one bus in memory, advancing together in
//!   virtual time.
//!
//! No CAN interface, no real time, no flakiness.

use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::io;
use std::rc::Rc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};

use firmware::CanFrame;

use crate::bus::Bus;
use crate::clock::Clock;

// ---------------------------------------------------------------------------------------------
// One loop: scripted time and frames

/// Scripted time for one loop: [`Clock::sleep_until`] jumps to the deadline plus the next
/// scripted lateness (0 when the script is used up). With `pace` n > 0 it also really
/// sleeps 1/n of each wait (for a log writer on another thread that must keep up).
#[derive(Debug)]
pub struct ScriptedClock {
    now: Cell<u64>,
    lateness: RefCell<VecDeque<u64>>,
    pace: u64,
}

impl ScriptedClock {
    /// A clock at `start_us` whose wake-ups are late by `lateness`, one value per sleep.
    #[must_use]
    pub fn new(start_us: u64, lateness: impl IntoIterator<Item = u64>, pace: u64) -> Rc<Self> {
        Rc::new(Self {
            now: Cell::new(start_us),
            lateness: RefCell::new(lateness.into_iter().collect()),
            pace,
        })
    }

    /// Moves the time on by `us` (work that takes time).
    pub fn advance(&self, us: u64) {
        self.now.set(self.now.get() + us);
    }

    /// Appends wake-up latenesses to the script.
    pub fn push_lateness(&self, lateness: impl IntoIterator<Item = u64>) {
        self.lateness.borrow_mut().extend(lateness);
    }
}

impl Clock for ScriptedClock {
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

/// A bus for one loop on a [`ScriptedClock`]: `incoming` frames arrive at their times, sends
/// are recorded with theirs. The script's faults:
///
/// - `busy`: the next that many sends fail with `ENOBUFS`;
/// - `down`: in this interval of the clock the link is down: sends fail with `ENETDOWN`, the
///   first receive in it too (as SocketCAN does), and [`Bus::reopen`] fails;
/// - `stop_at`: the first send at or after that time stores 15 (SIGTERM) in the flag, a
///   signal arriving while the loop runs;
/// - `send_cost_us`: every send moves the clock on by that much.
#[derive(Debug)]
pub struct ScriptedBus {
    /// The clock the times are read from.
    pub clock: Rc<ScriptedClock>,
    /// Frames to receive, each from its time on, in order.
    pub incoming: VecDeque<(u64, CanFrame)>,
    /// Frames sent, with the time of the send.
    pub sent: Vec<(u64, CanFrame)>,
    /// Sends still to fail with `ENOBUFS`.
    pub busy: u64,
    /// Send attempts, failed ones included.
    pub attempts: u64,
    /// When to set the stop flag, and the flag.
    pub stop_at: Option<(u64, Rc<AtomicUsize>)>,
    /// The link is down from the first to the second time, µs of the clock.
    pub down: Option<(u64, u64)>,
    /// The receive error of the current outage was reported.
    pub down_reported: bool,
    /// Each [`Bus::reopen`]: its time and whether it succeeded.
    pub reopens: Vec<(u64, bool)>,
    /// What a send costs, µs of the clock.
    pub send_cost_us: u64,
}

impl ScriptedBus {
    /// A bus on `clock` that delivers `incoming`, with no faults.
    #[must_use]
    pub fn new(
        clock: &Rc<ScriptedClock>,
        incoming: impl IntoIterator<Item = (u64, CanFrame)>,
    ) -> Self {
        Self {
            clock: Rc::clone(clock),
            incoming: incoming.into_iter().collect(),
            sent: Vec::new(),
            busy: 0,
            attempts: 0,
            stop_at: None,
            down: None,
            down_reported: false,
            reopens: Vec::new(),
            send_cost_us: 0,
        }
    }

    fn is_down(&self) -> bool {
        let now = self.clock.now_micros();
        self.down
            .is_some_and(|(from, to)| (from..to).contains(&now))
    }
}

impl Bus for ScriptedBus {
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
        if self.is_down() {
            if !self.down_reported {
                self.down_reported = true;
                return Err(io::Error::from_raw_os_error(libc::ENETDOWN));
            }
            return Ok(None);
        }
        match self.incoming.front() {
            Some(&(t, f)) if t <= self.clock.now_micros() => {
                self.incoming.pop_front();
                Ok(Some(f))
            }
            _ => Ok(None),
        }
    }

    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        self.attempts += 1;
        let now = self.clock.now_micros();
        if let Some((t, flag)) = &self.stop_at
            && now >= *t
        {
            flag.store(15, Ordering::Relaxed);
        }
        if self.is_down() {
            return Err(io::Error::from_raw_os_error(libc::ENETDOWN));
        }
        if self.busy > 0 {
            self.busy -= 1;
            return Err(io::Error::from_raw_os_error(libc::ENOBUFS));
        }
        self.clock.advance(self.send_cost_us);
        self.sent.push((now, *frame));
        Ok(())
    }

    fn reopen(&mut self) -> io::Result<()> {
        let ok = !self.is_down();
        self.reopens.push((self.clock.now_micros(), ok));
        if ok {
            Ok(())
        } else {
            Err(io::Error::from_raw_os_error(libc::ENETDOWN))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// In-memory bus

/// A CAN bus in memory, shared by [`MemoryPort`]s: a frame one port sends is received by
/// every other port (not by the sender), in sending order, like nodes on one wire. Thread
/// safe; nothing blocks except the short internal lock.
#[derive(Debug, Clone, Default)]
pub struct MemoryBus {
    queues: Arc<Mutex<Vec<VecDeque<CanFrame>>>>,
}

/// One node's connection to a [`MemoryBus`]; implements [`Bus`].
#[derive(Debug)]
pub struct MemoryPort {
    queues: Arc<Mutex<Vec<VecDeque<CanFrame>>>>,
    index: usize,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panicking holder cannot leave these simple states inconsistent.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl MemoryBus {
    /// An empty bus.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Connects a new node. It receives the frames sent after this call.
    #[must_use]
    pub fn port(&self) -> MemoryPort {
        let mut queues = lock(&self.queues);
        queues.push(VecDeque::new());
        MemoryPort {
            queues: Arc::clone(&self.queues),
            index: queues.len() - 1,
        }
    }
}

impl MemoryPort {
    /// Frames waiting to be received by this port.
    #[must_use]
    pub fn pending(&self) -> usize {
        lock(&self.queues).get(self.index).map_or(0, VecDeque::len)
    }
}

impl Bus for MemoryPort {
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
        Ok(lock(&self.queues)
            .get_mut(self.index)
            .and_then(VecDeque::pop_front))
    }

    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        let mut queues = lock(&self.queues);
        for (i, q) in queues.iter_mut().enumerate() {
            if i != self.index {
                q.push_back(*frame);
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Virtual time

/// Virtual time for several loops on several threads, each with its own
/// [`VirtualClockHandle`].
///
/// Time stands still while any participant is running; when every participant is asleep in
/// [`Clock::sleep_until`], time jumps to the earliest deadline and the participants due
/// then wake up. A loop therefore sees exactly the times it asked for (zero lateness), the
/// loops interleave as they would in real time, and a run takes as long as its computation,
/// not its virtual duration.
///
/// Create every handle ([`join`](Self::join)) before starting the threads, give each
/// thread its own, and drop a handle when its loop ends (its thread then no longer holds time
/// back). Loops due at the same instant run concurrently; offset their phases (a first
/// `sleep_until(start + offset)`) for a deterministic order.
#[derive(Debug, Clone)]
pub struct VirtualClock {
    shared: Arc<VcShared>,
}

#[derive(Debug)]
struct VcShared {
    state: Mutex<VcState>,
    wake: Condvar,
}

#[derive(Debug)]
struct VcState {
    now: u64,
    members: usize,
    sleeping: Vec<u64>,
}

/// One participant of a [`VirtualClock`]; implements [`Clock`]. Dropping it leaves.
#[derive(Debug)]
pub struct VirtualClockHandle {
    shared: Arc<VcShared>,
}

impl VirtualClock {
    /// A clock at `start_us` with no participants.
    #[must_use]
    pub fn new(start_us: u64) -> Self {
        Self {
            shared: Arc::new(VcShared {
                state: Mutex::new(VcState {
                    now: start_us,
                    members: 0,
                    sleeping: Vec::new(),
                }),
                wake: Condvar::new(),
            }),
        }
    }

    /// Adds a participant.
    #[must_use]
    pub fn join(&self) -> VirtualClockHandle {
        lock(&self.shared.state).members += 1;
        VirtualClockHandle {
            shared: Arc::clone(&self.shared),
        }
    }

    /// The current virtual time, µs.
    #[must_use]
    pub fn now_micros(&self) -> u64 {
        lock(&self.shared.state).now
    }
}

impl Clock for VirtualClockHandle {
    fn now_micros(&self) -> u64 {
        lock(&self.shared.state).now
    }

    fn sleep_until(&self, deadline_us: u64) {
        let mut st = lock(&self.shared.state);
        if st.now >= deadline_us {
            return;
        }
        st.sleeping.push(deadline_us);
        loop {
            if st.sleeping.len() >= st.members
                && let Some(&earliest) = st.sleeping.iter().min()
                && earliest > st.now
            {
                st.now = earliest;
                self.shared.wake.notify_all();
            }
            if st.now >= deadline_us {
                if let Some(i) = st.sleeping.iter().position(|&d| d == deadline_us) {
                    st.sleeping.swap_remove(i);
                }
                return;
            }
            st = self
                .shared
                .wake
                .wait(st)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }
}

impl Drop for VirtualClockHandle {
    fn drop(&mut self) {
        let mut st = lock(&self.shared.state);
        st.members = st.members.saturating_sub(1);
        drop(st);
        self.shared.wake.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::StandardId;

    fn frame(id: u16) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), &[id as u8]).unwrap()
    }

    #[test]
    fn memory_bus_delivers_to_every_other_port_in_order() {
        let bus = MemoryBus::new();
        let (mut a, mut b, mut c) = (bus.port(), bus.port(), bus.port());
        a.send(&frame(1)).unwrap();
        b.send(&frame(2)).unwrap();
        assert_eq!(a.try_recv().unwrap(), Some(frame(2)));
        assert_eq!(a.try_recv().unwrap(), None);
        assert_eq!(b.try_recv().unwrap(), Some(frame(1)));
        assert_eq!(c.pending(), 2);
        assert_eq!(c.try_recv().unwrap(), Some(frame(1)));
        assert_eq!(c.try_recv().unwrap(), Some(frame(2)));
    }

    #[test]
    fn a_single_participant_jumps_to_its_deadlines() {
        let clock = VirtualClock::new(100);
        let h = clock.join();
        h.sleep_until(50);
        assert_eq!(h.now_micros(), 100);
        h.sleep_until(1234);
        assert_eq!((h.now_micros(), clock.now_micros()), (1234, 1234));
    }

    #[test]
    fn participants_interleave_in_virtual_time() {
        let clock = VirtualClock::new(0);
        let log = Arc::new(Mutex::new(Vec::new()));
        // Every handle first, then the threads (see the type's documentation).
        let handles = [(300u64, 'a', clock.join()), (500, 'b', clock.join())];
        let threads: Vec<_> = handles
            .into_iter()
            .map(|(period, name, h)| {
                let log = Arc::clone(&log);
                std::thread::spawn(move || {
                    for k in 1..=3 {
                        h.sleep_until(k * period);
                        lock(&log).push((h.now_micros(), name));
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().unwrap();
        }
        let mut got = lock(&log).clone();
        got.sort_unstable();
        assert_eq!(
            got,
            [
                (300, 'a'),
                (500, 'b'),
                (600, 'a'),
                (900, 'a'),
                (1000, 'b'),
                (1500, 'b')
            ]
        );
    }
}
