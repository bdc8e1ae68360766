//! The board as the firmware node on hostsim's bit-timed bus, in one virtual time.
//!
//! The bus ([`hostsim::bus::Bus`], the engine's) times every frame bit for bit and arbitrates by id. The
//! board's CAN1 offers one frame at a time (its next mailbox, as the controller does): it is
//! queued on the bus when the board requests it, started when it wins arbitration, and
//! completes (TXOK) at its end of frame. Frames of the other nodes, queued by the caller at
//! their times, reach the board's FIFOs at their delivery time. The board runs between those
//! events, and stops early when its controller has something new to send.
//!
//! Time: the bus counts ns, the board cycles at 168 MHz; conversions round so that a wake-up
//! is never before the event. The bus's time 0, where a scenario starts, is the timer tick of
//! the board's first control step ([`Lockstep::power_on`]): the board boots on a quiet bus,
//! and its steps then fall where the in-process core's do, one period apart from time 0 (a
//! step's frames leave after its computation, some µs later), so that its runs compare with
//! the core's.

use hostsim::bus::{Bus, Fate, Node, Transmission};

use crate::board::{Board, BoardError, CPU_HZ};
use crate::bxcan::Lec;

/// A fault of the board's connection to the bus, over a window of bus time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WireFault {
    /// The board's connector unplugged: its frames meet no acknowledgment (an ACK error each;
    /// retransmitted, and, for simplicity, still timed on the shared bus), nobody receives
    /// them, and it receives nothing.
    NoAck,
    /// The bus corrupted (a CANH/CANL short, a broken terminator): every frame fails with a
    /// bit error; nobody receives any. The board's transmit error counter climbs by 8 a
    /// frame to bus-off.
    BitErrors,
}

/// ns of virtual time at board cycle `c` (rounded down).
#[must_use]
pub const fn cycles_to_ns(c: u64) -> u64 {
    c * 1_000_000_000 / CPU_HZ
}

/// The first board cycle at or after `ns`.
#[must_use]
pub const fn ns_to_cycles(ns: u64) -> u64 {
    (ns * CPU_HZ).div_ceil(1_000_000_000)
}

/// The board on a bus. See the [module documentation](self).
#[derive(Debug)]
pub struct Lockstep {
    /// The board.
    pub board: Board,
    /// The board's cycle at the bus's time 0 ([`power_on`](Self::power_on)).
    epoch: u64,
    /// A fault on the wire and its window `[from, until)` of bus time, ns.
    wire_fault: Option<(WireFault, u64, u64)>,
    /// Transmissions started and not yet completed (at most a few: one on the wire, the
    /// ones delivered late by a delay fault).
    in_flight: Vec<Transmission>,
    /// A frame of the board is on the bus (queued or on the wire).
    board_queued: bool,
    /// Every transmission completed, in order, for the caller to log and take.
    pub completed: Vec<Transmission>,
    scratch: Vec<Transmission>,
}

impl Lockstep {
    /// `board`, for a bus whose time 0 is set by [`power_on`](Self::power_on).
    #[must_use]
    pub const fn new(board: Board) -> Self {
        Self {
            board,
            epoch: 0,
            wire_fault: None,
            in_flight: Vec::new(),
            board_queued: false,
            completed: Vec::new(),
            scratch: Vec::new(),
        }
    }

    /// Boots the board alone until it offers its first frame (its first control step), or
    /// for `limit_ns` if it offers none, and starts the bus's time at the timer compare that
    /// woke that step (at the frame's request if no compare came within 1 ms before it).
    /// Returns the boot time, ns from power-on.
    ///
    /// # Errors
    /// The board stopped ([`BoardError`]).
    pub fn power_on(&mut self, limit_ns: u64) -> Result<u64, BoardError> {
        let limit = ns_to_cycles(limit_ns);
        // A request to transmit stops the board's run (every MMIO write does), so this
        // stops at the first frame's request.
        while self.board.can_offer().is_none() && self.board.now() < limit {
            self.board.run_until(limit)?;
        }
        let request = self.board.now();
        self.epoch = self
            .board
            .tim2()
            .last_compare_at
            .filter(|&tick| tick <= request && request - tick < CPU_HZ / 1000)
            .unwrap_or(request);
        Ok(cycles_to_ns(self.epoch))
    }

    /// Virtual time, ns from the bus's time 0.
    #[must_use]
    pub fn now_ns(&self) -> u64 {
        self.board_ns(self.board.now())
    }

    /// The bus time of board cycle `c`, ns (0 for a cycle before it: the board's boot).
    #[must_use]
    pub const fn board_ns(&self, c: u64) -> u64 {
        cycles_to_ns(c.saturating_sub(self.epoch))
    }

    /// `fault` on the wire for the frames that start in `[from_ns, until_ns)`.
    pub const fn set_wire_fault(&mut self, fault: WireFault, from_ns: u64, until_ns: u64) {
        self.wire_fault = Some((fault, from_ns, until_ns));
    }

    /// The wire fault, if any, for a frame that started at `start_ns`.
    fn wire_fault_at(&self, start_ns: u64) -> Option<WireFault> {
        self.wire_fault
            .filter(|&(_, from, until)| (from..until).contains(&start_ns))
            .map(|(fault, ..)| fault)
    }

    /// Withholds the board's CAN RX0 interrupt until bus time `until_ns`
    /// ([`Board::hold_can_rx`]).
    pub fn hold_can_rx(&mut self, until_ns: u64) {
        let until = self.cycles_at(until_ns);
        self.board.hold_can_rx(until);
    }

    /// The first board cycle at or after bus time `ns`.
    const fn cycles_at(&self, ns: u64) -> u64 {
        self.epoch + ns_to_cycles(ns)
    }

    /// Runs board and `bus` to `until_ns` (the other nodes' frames are queued on the bus by
    /// the caller).
    ///
    /// # Errors
    /// The board stopped ([`BoardError`]).
    pub fn run_until(&mut self, bus: &mut Bus, until_ns: u64) -> Result<(), BoardError> {
        loop {
            let now_ns = self.now_ns();
            // The board's next frame, once its previous one is off the bus.
            if !self.board_queued
                && let Some(frame) = self.board.can_offer()
            {
                bus.send(now_ns, Node::Controller, frame);
                self.board_queued = true;
            }
            // Transmissions that start by now.
            self.scratch.clear();
            bus.advance_into(now_ns + 1, &mut self.scratch);
            for tx in self.scratch.drain(..) {
                if tx.from == Node::Controller {
                    self.board
                        .can_started(self.epoch + ns_to_cycles(tx.start_ns));
                }
                self.in_flight.push(tx);
            }
            // Completions due by now, in time order.
            self.in_flight.sort_by_key(|t| (t.delivered_ns, t.end_ns));
            while let Some(tx) = self.in_flight.first() {
                let due = if tx.from == Node::Controller {
                    tx.end_ns
                } else {
                    tx.delivered_ns
                };
                if due > now_ns {
                    break;
                }
                let mut tx = self.in_flight.remove(0);
                let wire = self.wire_fault_at(tx.start_ns);
                if tx.from == Node::Controller {
                    match wire {
                        // A bus fault (drop, corruption) is the receivers' loss: the frame was
                        // acknowledged by the bus's other nodes in this model.
                        None => self.board.can_transmitted(),
                        Some(WireFault::NoAck) => self.board.can_tx_error(Lec::Ack),
                        Some(WireFault::BitErrors) => self.board.can_tx_error(Lec::BitDominant),
                    }
                    if wire.is_some() {
                        tx.fate = Fate::Dropped;
                    }
                    self.board_queued = false;
                } else if wire == Some(WireFault::BitErrors) {
                    tx.fate = Fate::Dropped;
                } else if wire.is_none() && tx.fate != Fate::Dropped {
                    self.board
                        .can_receive(&tx.frame, self.cycles_at(tx.start_ns));
                }
                self.completed.push(tx);
            }
            if now_ns >= until_ns {
                return Ok(());
            }
            let next = self
                .in_flight
                .iter()
                .map(|t| {
                    if t.from == Node::Controller {
                        t.end_ns
                    } else {
                        t.delivered_ns
                    }
                })
                .chain(bus.next_start_ns())
                .filter(|&t| t > now_ns)
                .min()
                .map_or(until_ns, |t| t.min(until_ns));
            self.board.run_until(self.cycles_at(next))?;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions_never_wake_before_the_event() {
        for ns in [0, 1, 5, 6, 999, 1000, 1_000_001, 123_456_789] {
            let c = ns_to_cycles(ns);
            assert!(cycles_to_ns(c) >= ns, "{ns} ns -> {c} cycles");
            assert!(
                c == 0 || cycles_to_ns(c - 1) < ns,
                "{ns} ns: {c} is the first"
            );
        }
        assert_eq!(ns_to_cycles(1000), 168);
        assert_eq!(cycles_to_ns(168), 1000);
    }
}
