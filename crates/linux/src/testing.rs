//! Test doubles of the [`Bus`] and the [`Clock`]: a CAN bus in memory ([`MemoryBus`]) and
//! virtual time for several loops on several threads ([`VirtualClock`]). With them the
//! runner's loop, the simulated drives and a scripted host run together in tests with no CAN
//! interface, no real time and no flakiness.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};

use firmware::CanFrame;

use crate::bus::Bus;
use crate::clock::Clock;

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
