//! The simulated CAN bus: bit timing, arbitration by id, bus load and seeded faults.
//!
//! # Arbitration
//!
//! Each node queues the frames it wants to send and offers its lowest id first, as a CAN
//! controller with priority-ordered mailboxes does. When the bus goes idle, the lowest id on
//! offer from any node wins; the others wait. A frame is received by every other node at
//! the end of its transmission.
//!
//! A frame's length on the wire, stuff bits and CRC included, is [`frame_bits`] (`timing`);
//! what the faults do, and the seeded generator of their random choices, is in `fault`.

use firmware::CanFrame;

mod fault;
mod timing;

pub use fault::{Fate, Fault, FaultKind, SplitMix64};
pub use timing::frame_bits;

use timing::arbitration_field;

/// Who is on the bus.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub enum Node {
    /// The firmware core.
    Controller,
    /// The motor drives (all of them: they share one node here for simplicity of ordering).
    Drives,
    /// The host that commands the robot.
    Host,
    /// An IMU node sending its gyro's yaw rate.
    Imu,
    /// A tracking-pod node sending its pods' encoder counts.
    Pods,
}

impl Node {
    /// Lower-case name, as used in logs and scenarios.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::Controller => "controller",
            Self::Drives => "drives",
            Self::Host => "host",
            Self::Imu => "imu",
            Self::Pods => "pods",
        }
    }
}

/// One frame's transmission.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Transmission {
    /// Sender.
    pub from: Node,
    /// When the sender queued it, ns.
    pub queued_ns: u64,
    /// Start of frame on the wire, ns.
    pub start_ns: u64,
    /// End of frame on the wire (the last bit of its end-of-frame field), ns.
    pub end_ns: u64,
    /// When the receivers get it (end of frame plus any delay fault), ns.
    pub delivered_ns: u64,
    /// The frame as its sender queued it.
    pub sent: CanFrame,
    /// The frame as received (after any corruption); as sent if dropped.
    pub frame: CanFrame,
    /// Bits on the wire, stuff bits and intermission included.
    pub bits: u32,
    /// What happened to it.
    pub fate: Fate,
}

/// Bus statistics.
#[derive(Clone, Copy, PartialEq, Debug, Default)]
pub struct BusStats {
    /// Frames transmitted.
    pub frames: u64,
    /// Frames lost to faults.
    pub dropped: u64,
    /// Frames corrupted by faults.
    pub corrupted: u64,
    /// Time the bus was busy, ns.
    pub busy_ns: u64,
    /// Longest wait from queueing to start of frame, ns.
    pub max_queue_ns: u64,
}

/// The simulated bus. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Bus {
    bit_ns: u64,
    /// Frames waiting, all nodes: when each is ready, its arbitration key, the frame, its
    /// sender (parallel lists, so that the scans per frame read only what they compare).
    ready_ns: Vec<u64>,
    keys: Vec<u128>,
    frames: Vec<CanFrame>,
    /// The sender of each waiting frame (a list of its own: a 20-byte `(Node, CanFrame)`
    /// moved out of a list was read back through a store-forwarding stall).
    senders: Vec<Node>,
    /// Frames queued so far (the tie-break after id and node).
    queued: u64,
    /// The bus is busy until this time, ns.
    idle_at_ns: u64,
    faults: Vec<Fault>,
    /// Per sender ([`node_index`]), when its last frame is delivered: no later frame of the
    /// same sender is delivered before it.
    last_delivered_ns: [u64; NODES],
    rng: SplitMix64,
    stats: BusStats,
}

/// The arbitration key of a queued frame, lowest wins: the arbitration field as it goes on
/// the wire (dominant 0 first), then the node order, then the order of queueing.
fn arbitration_key(frame: &CanFrame, from: Node, seq: u64) -> u128 {
    // The node order takes 3 bits (64..67): five nodes.
    (u128::from(arbitration_field(frame)) << 67)
        | ((node_index(from) as u128) << 64)
        | u128::from(seq)
}

/// How many nodes there are ([`node_index`] is below).
const NODES: usize = 5;

fn node_index(n: Node) -> usize {
    match n {
        Node::Controller => 0,
        Node::Drives => 1,
        Node::Host => 2,
        Node::Imu => 3,
        Node::Pods => 4,
    }
}

impl Bus {
    /// A bus at `bitrate` bit/s with the given faults and fault seed.
    ///
    /// # Panics
    /// Never; a zero bitrate is treated as 1 Mbit/s.
    #[must_use]
    pub fn new(bitrate: u32, faults: Vec<Fault>, seed: u64) -> Self {
        let bitrate = if bitrate == 0 { 1_000_000 } else { bitrate };
        Self {
            bit_ns: 1_000_000_000 / u64::from(bitrate),
            ready_ns: Vec::new(),
            keys: Vec::new(),
            frames: Vec::new(),
            senders: Vec::new(),
            queued: 0,
            idle_at_ns: 0,
            faults,
            last_delivered_ns: [0; NODES],
            rng: SplitMix64(seed),
            stats: BusStats::default(),
        }
    }

    /// Queues `frame` for transmission by `from` at time `now_ns`.
    pub fn send(&mut self, now_ns: u64, from: Node, frame: CanFrame) {
        self.ready_ns.push(now_ns);
        self.keys.push(arbitration_key(&frame, from, self.queued));
        self.frames.push(frame);
        self.senders.push(from);
        self.queued += 1;
    }

    /// Frames waiting to be sent, all nodes.
    #[must_use]
    pub fn pending(&self) -> usize {
        self.frames.len()
    }

    /// When the next transmission starts if nothing else is queued: the earliest time a
    /// waiting frame is ready, not before the bus is idle. `None` with nothing waiting. (A
    /// node that offers one frame at a time, as a CAN controller's mailbox does, runs to
    /// this time before it offers the next.)
    #[must_use]
    pub fn next_start_ns(&self) -> Option<u64> {
        self.ready_ns.iter().min().map(|&r| r.max(self.idle_at_ns))
    }

    /// Statistics so far.
    #[must_use]
    pub const fn stats(&self) -> BusStats {
        self.stats
    }

    /// Bus load over `[0, until_ns)`: busy time over elapsed time.
    #[must_use]
    pub fn load(&self, until_ns: u64) -> f64 {
        if until_ns == 0 {
            0.0
        } else {
            self.stats.busy_ns as f64 / until_ns as f64
        }
    }

    /// Runs the bus up to `until_ns`: every transmission that *starts* before then happens,
    /// in arbitration order. Returns them in the order they went on the wire.
    pub fn advance(&mut self, until_ns: u64) -> Vec<Transmission> {
        let mut out = Vec::new();
        self.advance_into(until_ns, &mut out);
        out
    }

    /// [`Self::advance`], appending to `out` (no allocation once `out` has grown).
    pub fn advance_into(&mut self, until_ns: u64, out: &mut Vec<Transmission>) {
        // The earliest time a frame is on offer, not before the bus is idle.
        while let Some(&ready_ns) = self.ready_ns.iter().min() {
            let start_ns = ready_ns.max(self.idle_at_ns);
            if start_ns >= until_ns {
                break;
            }
            // Arbitration among the frames on offer at start_ns: each node offers its lowest
            // id; the lowest id on the bus wins (ties: node order, i.e. a fixed priority;
            // then a node's own queueing order).
            let mut best: Option<(u128, usize)> = None;
            for (i, (&ready, &key)) in self.ready_ns.iter().zip(&self.keys).enumerate() {
                if ready <= start_ns && best.is_none_or(|(k, _)| key < k) {
                    best = Some((key, i));
                }
            }
            let Some((_, i)) = best else { break };
            // Measured in place: on a copy just moved out of the list, the first loads
            // waited on the stores of the move (a quarter of this function's cycles).
            let bits = frame_bits(&self.frames[i]);
            // The key carries the queueing order, so the list order may change.
            let queued_ns = self.ready_ns.swap_remove(i);
            self.keys.swap_remove(i);
            let frame = self.frames.swap_remove(i);
            let from = self.senders.swap_remove(i);
            let end_ns = start_ns + u64::from(bits) * self.bit_ns;
            self.idle_at_ns = end_ns;
            self.stats.frames += 1;
            self.stats.busy_ns += end_ns - start_ns;
            self.stats.max_queue_ns = self.stats.max_queue_ns.max(start_ns - queued_ns);
            let sent = frame;
            let (frame, fate, delay_ns) =
                fault::apply(&self.faults, &mut self.rng, end_ns, from, frame);
            match fate {
                Fate::Dropped => self.stats.dropped += 1,
                Fate::Corrupted => self.stats.corrupted += 1,
                Fate::Delivered => {}
            }
            // A sender's frames reach the receivers in their wire order (a delay does not let a
            // later one overtake); a dropped frame reaches nobody and holds nothing back.
            let last = &mut self.last_delivered_ns[node_index(from)];
            let delivered_ns = (end_ns + delay_ns).max(*last);
            if fate != Fate::Dropped {
                *last = delivered_ns;
            }
            out.push(Transmission {
                from,
                queued_ns,
                start_ns,
                end_ns,
                delivered_ns,
                sent,
                frame,
                bits,
                fate,
            });
        }
    }
}

#[cfg(test)]
mod tests;
