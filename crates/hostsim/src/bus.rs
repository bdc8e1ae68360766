//! A simulated CAN bus: bit-accurate frame timing, arbitration by id, bus load, and seeded
//! fault injection.
//!
//! # Timing
//!
//! A classic CAN data frame with an 11-bit id is SOF, id, RTR, IDE, r0, DLC, data and CRC-15,
//! all subject to bit stuffing (after five equal bits the transmitter inserts the complement),
//! then CRC delimiter, ACK slot and delimiter, seven EOF bits and three bits of intermission.
//! [`frame_bits`] builds that bit sequence for the actual frame, CRC included, and counts the
//! stuff bits, so a frame's duration is exact, not a worst-case estimate: at 1 Mbit/s an
//! 8-byte frame takes 111 to 135 µs depending on its content.
//!
//! # Arbitration
//!
//! Each node queues the frames it wants to send and offers its lowest id first, as a CAN
//! controller with priority-ordered mailboxes does. When the bus goes idle, the lowest id on
//! offer from any node wins; the others wait. A frame is received by every other node at
//! the end of its transmission.
//!
//! # Faults
//!
//! Each [`Fault`] applies to frames whose transmission ends inside its time window and, if
//! given, that come from one node: random drops, total loss (a burst), extra delivery delay,
//! a flipped byte. Random choices come from a SplitMix64 generator seeded by the scenario, so
//! the same seed gives the same faults on every run and every machine.

use embedded_can::{Frame, Id};
use firmware::CanFrame;

/// Who is on the bus.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub enum Node {
    /// The firmware core.
    Controller,
    /// The motor drives (all of them: they share one node here for simplicity of ordering).
    Drives,
    /// The host that commands the robot.
    Host,
    /// An IMU node sending its gyro's yaw rate ([`crate::imu`]).
    Imu,
    /// A tracking-pod node sending its pods' encoder counts ([`crate::pods`]).
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

/// What a fault does to a frame.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum FaultKind {
    /// Each frame is lost with this probability (0..=1).
    Drop {
        /// Probability of losing a frame.
        rate: f64,
    },
    /// Every frame is lost (a burst of losses for the length of the window).
    Burst,
    /// Frames are delivered this much later than their end of transmission, µs (a slow path
    /// from the sender, such as a gateway): a sender's frames still arrive in the order they
    /// went on the wire, so a frame after a delayed one waits for it. Other senders' frames
    /// are not held up.
    Delay {
        /// Extra latency, µs.
        micros: u64,
    },
    /// With this probability a frame arrives with one data byte XORed by a random nonzero
    /// mask (a faulty node's data; a bus error would have been caught by the CRC).
    Corrupt {
        /// Probability of corrupting a frame.
        rate: f64,
    },
}

/// A fault active in a time window.
#[derive(Clone, Copy, PartialEq, Debug)]
pub struct Fault {
    /// What it does.
    pub kind: FaultKind,
    /// Window start, µs of simulated time (inclusive).
    pub from_us: u64,
    /// Window end, µs (exclusive).
    pub until_us: u64,
    /// Only frames sent by this node, or all.
    pub sender: Option<Node>,
}

/// What happened to a frame on the bus.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Fate {
    /// Received intact by the other nodes.
    Delivered,
    /// Lost (drop or burst fault).
    Dropped,
    /// Received with a corrupted byte.
    Corrupted,
}

impl Fate {
    /// Lower-case name, as used in logs.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::Delivered => "delivered",
            Self::Dropped => "dropped",
            Self::Corrupted => "corrupted",
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

/// The bits a frame arbitrates with, in wire order, left-aligned in 32 bits: the base id,
/// RTR (standard) or SRR (extended, recessive), IDE, then for an extended frame its 18 low
/// id bits and RTR. A data frame beats a remote frame of the same id, a standard frame an
/// extended one of the same base id.
fn arbitration_field(frame: &CanFrame) -> u32 {
    let rtr = u32::from(frame.is_remote_frame());
    match frame.id() {
        Id::Standard(id) => (u32::from(id.as_raw()) << 21) | (rtr << 20),
        Id::Extended(id) => {
            let id = id.as_raw();
            ((id >> 18) << 21) | (0b11 << 19) | ((id & 0x3_FFFF) << 1) | rtr
        }
    }
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
            let (frame, fate, delay_ns) = self.apply_faults(end_ns, from, frame);
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

    fn apply_faults(&mut self, end_ns: u64, from: Node, sent: CanFrame) -> (CanFrame, Fate, u64) {
        let end_us = end_ns / 1000;
        let mut frame = sent;
        let mut fate = Fate::Delivered;
        let mut delay_ns = 0;
        for f in &self.faults {
            if end_us < f.from_us || end_us >= f.until_us || f.sender.is_some_and(|s| s != from) {
                continue;
            }
            match f.kind {
                FaultKind::Burst => fate = Fate::Dropped,
                FaultKind::Drop { rate } => {
                    if self.rng.unit() < rate {
                        fate = Fate::Dropped;
                    }
                }
                FaultKind::Delay { micros } => delay_ns += micros * 1000,
                FaultKind::Corrupt { rate } => {
                    let dlc = frame.dlc();
                    if dlc > 0 && self.rng.unit() < rate && fate == Fate::Delivered {
                        let r = self.rng.next_u64();
                        let byte = (r % dlc as u64) as usize;
                        let mask = ((r >> 8) % 255 + 1) as u8;
                        let mut data = [0u8; 8];
                        data[..dlc].copy_from_slice(frame.data());
                        data[byte] ^= mask;
                        if let Id::Standard(id) = frame.id() {
                            frame = CanFrame::from_buffer(id, data, dlc as u8);
                        }
                        fate = Fate::Corrupted;
                    }
                }
            }
        }
        // A frame a later fault dropped after an earlier one corrupted it: as sent.
        if fate == Fate::Dropped {
            frame = sent;
        }
        (frame, fate, delay_ns)
    }
}

/// Length of `frame` on the wire in bits, stuff bits and the 13 fixed trailing bits (CRC
/// delimiter, ACK slot and delimiter, EOF, intermission) included.
///
/// Works on whole bytes with tables built at compile time. The header bits are padded
/// in front to whole bytes, with zeros for the CRC (leading zeros leave a zero CRC register
/// zero) and, for the stuff count, with bits that end like the idle bus so that the SOF
/// starts a fresh run: `10101` before the 19 bits of a standard header (SOF, id, RTR, IDE,
/// r0, DLC; alternating bits never stuff), `1` before the 39 of an extended one (SOF, base
/// id, SRR, IDE, extended id, RTR, r1, r0, DLC).
///
/// Hand-written rather than a CRC crate's CRC-15/CAN because the bit stream is not whole
/// bytes and the stuff count rides on the same pass. It was a sixth of a lockstep run's
/// cycles, bound by the latency of two chains of table lookups (CRC and stuffing state), so
/// the CRC is a sum of independent per-position lookups and the stuffing state indexes its
/// table without arithmetic (docs/benchmarks.md).
#[must_use]
pub fn frame_bits(frame: &CanFrame) -> u32 {
    let len = if frame.is_remote_frame() {
        0
    } else {
        frame.dlc().min(8)
    };
    let data = frame.buffer();
    // The arbitration field, then IDE / r1 and r0 (dominant) and the DLC; SOF (dominant) is
    // the zero in front.
    let arbitration = arbitration_field(frame);
    let dlc = frame.dlc() as u32;
    if frame.is_extended() {
        // SOF base id(11) SRR IDE extended id(18) RTR r1 r0 DLC(4): 39 bits.
        let header = (u64::from(arbitration) << 6) | u64::from(dlc);
        let [_, _, _, a, b, c, d, e] = header.to_be_bytes();
        39 + stuffed_crc_bits([a, b, c, d, e], 0b1000_0000, &data, len)
    } else {
        // SOF id(11) RTR IDE r0 DLC(4): 19 bits.
        let header = ((arbitration >> 20) << 6) | dlc;
        let [_, a, b, c] = header.to_be_bytes();
        19 + stuffed_crc_bits([a, b, c], 0b1010_1000, &data, len)
    }
}

/// The bits after the header: `len` data bytes, the 15-bit CRC, the stuff bits from SOF to
/// the CRC's end, and the 13 fixed ones. `head` is the header padded in front to whole
/// bytes with zeros; `pad` holds the stuff-count pad bits (see [`frame_bits`]).
#[inline(always)]
fn stuffed_crc_bits<const N: usize>(head: [u8; N], pad: u8, data: &[u8; 8], len: usize) -> u32 {
    let data = &data[..len];
    // CRC-15 as the XOR of each byte's share, `b·x^(15 + 8q) mod g` for the byte q places
    // before the end (the CRC is linear): independent lookups instead of a chain.
    let mut crc = 0u16;
    let mut shares = CRC15_SHARE.iter();
    // The data first in the zip, so that its end does not use up a share.
    for (&b, share) in data.iter().rev().zip(shares.by_ref()) {
        crc ^= share[usize::from(b)];
    }
    for (&b, share) in head.iter().rev().zip(shares) {
        crc ^= share[usize::from(b)];
    }

    // Stuff bits: table entries hold the next state (low nibble) and the count (high).
    let eat = |(state, n): (u8, u32), byte: u8| {
        let entry = STUFF_TABLE[usize::from(state & 0x0F)][usize::from(byte)];
        (entry & 0x0F, n + u32::from(entry >> 4))
    };
    let mut acc = eat((IDLE, 0), head[0] | pad);
    acc = head[1..].iter().fold(acc, |a, &b| eat(a, b));
    acc = data.iter().fold(acc, |a, &b| eat(a, b));
    // The 15 CRC bits: eight, then the last seven through the 7-bit table.
    let (state, n) = eat(acc, (crc >> 7) as u8);
    let last = STUFF_TABLE_7[usize::from(state & 0x0F)][usize::from(crc & 0x7F)];
    let stuffed = n + u32::from(last >> 4);
    8 * len as u32 + 15 + stuffed + 13
}

/// The idle bus before SOF: recessive, no run counted (`last 1, run 0`).
const IDLE: u8 = StuffState { last: true, run: 0 }.index();

/// CRC-15/CAN (polynomial 0x4599) of each byte value, for a byte-at-a-time update.
const CRC15_TABLE: [u16; 256] = {
    let mut table = [0u16; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut c = (byte as u16) << 7;
        let mut bit = 0;
        while bit < 8 {
            c = if c & 0x4000 != 0 {
                ((c << 1) ^ 0x4599) & 0x7FFF
            } else {
                (c << 1) & 0x7FFF
            };
            bit += 1;
        }
        table[byte] = c;
        byte += 1;
    }
    table
};

/// Each byte value's share of the CRC, `b·x^(15 + 8q) mod g`, for the byte `q` places
/// before the end of the CRC's input (at most 13 bytes: an extended header, 8 data bytes).
const CRC15_SHARE: [[u16; 256]; 13] = {
    let mut table = [[0u16; 256]; 13];
    table[0] = CRC15_TABLE;
    let mut q = 1;
    while q < 13 {
        let mut byte = 0;
        while byte < 256 {
            // One more zero byte after it: the byte-at-a-time update with b = 0.
            let c = table[q - 1][byte];
            table[q][byte] = ((c << 8) ^ CRC15_TABLE[((c >> 7) & 0xFF) as usize]) & 0x7FFF;
            byte += 1;
        }
        q += 1;
    }
    table
};

/// For each stuffing state ([`StuffState::index`], 0..10; the rows above are padding, so a
/// state masked to four bits indexes without a bounds check) and byte: the state after the
/// byte in the low four bits, the stuff bits it causes in the high four.
const STUFF_TABLE: [[u8; 256]; 16] = stuff_table::<256>(8);

/// [`STUFF_TABLE`] for the last seven bits of the CRC.
const STUFF_TABLE_7: [[u8; 128]; 16] = stuff_table::<128>(7);

/// The stuffing table for `bits`-bit chunks (`N = 2^bits` entries per state).
const fn stuff_table<const N: usize>(bits: u32) -> [[u8; N]; 16] {
    let mut table = [[0u8; N]; 16];
    let mut index = 0;
    while index < 10 {
        let mut chunk = 0;
        while chunk < N {
            let mut s = StuffState::from_index(index as u8);
            let mut n = 0;
            let mut i = bits;
            while i > 0 {
                i -= 1;
                n += s.push((chunk >> i) & 1 == 1);
            }
            table[index][chunk] = s.index() | ((n as u8) << 4);
            chunk += 1;
        }
        index += 1;
    }
    table
}

/// Bit-stuffing state: the value of the last bit and how many equal bits end the stream so
/// far (0..=4).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct StuffState {
    last: bool,
    run: u8,
}

impl StuffState {
    const fn index(self) -> u8 {
        self.last as u8 * 5 + self.run
    }

    const fn from_index(index: u8) -> Self {
        Self {
            last: index >= 5,
            run: index % 5,
        }
    }

    /// Adds one bit; returns 1 if a stuff bit follows it.
    const fn push(&mut self, b: bool) -> u32 {
        if b == self.last && self.run > 0 {
            self.run += 1;
        } else {
            self.last = b;
            self.run = 1;
        }
        if self.run == 5 {
            // The stuff bit is the complement and starts a new run of length 1.
            self.last = !b;
            self.run = 1;
            1
        } else {
            0
        }
    }
}

/// CAN CRC-15 (polynomial 0x4599) over a bit sequence (reference for the tests).
#[cfg(test)]
fn crc15(bits: &[bool]) -> u16 {
    let mut crc: u16 = 0;
    for &b in bits {
        let next = b ^ ((crc >> 14) & 1 == 1);
        crc = (crc << 1) & 0x7FFF;
        if next {
            crc ^= 0x4599;
        }
    }
    crc
}

/// SplitMix64: a tiny, fixed, seedable generator, so fault patterns never change with a
/// dependency's version.
#[derive(Debug, Clone)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::StandardId;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    fn raw_id(frame: &CanFrame) -> u16 {
        match frame.id() {
            Id::Standard(id) => id.as_raw(),
            Id::Extended(_) => u16::MAX,
        }
    }

    #[test]
    fn the_next_start_waits_for_the_ready_time_and_the_idle_bus() {
        let mut bus = Bus::new(1_000_000, vec![], 1);
        assert_eq!(bus.next_start_ns(), None);
        bus.send(5_000, Node::Drives, frame(0x201, &[0; 8]));
        bus.send(7_000, Node::Drives, frame(0x202, &[0; 8]));
        assert_eq!(bus.next_start_ns(), Some(5_000));
        let first = bus.advance(5_001);
        assert_eq!(first.len(), 1, "only the frame ready by then starts");
        // The second is ready at 7 µs but the bus is busy with the first until its end.
        assert!(first[0].end_ns > 7_000);
        assert_eq!(bus.next_start_ns(), Some(first[0].end_ns));
    }

    #[test]
    fn arbitration_follows_the_bits_on_the_wire() {
        use embedded_can::{ExtendedId, Frame as _};
        let mut bus = Bus::new(1_000_000, vec![], 1);
        // Queued in reverse order of priority, the controller (first in node order) last.
        let ext_low = CanFrame::new(ExtendedId::new(0x1).unwrap(), &[0]).unwrap();
        let std_high = frame(0x7FF, &[0]);
        let remote = CanFrame::new_remote(StandardId::new(0x123).unwrap(), 8).unwrap();
        let data = frame(0x123, &[0; 8]);
        let ext_same_base = CanFrame::new(ExtendedId::new(0x123 << 18).unwrap(), &[0]).unwrap();
        bus.send(0, Node::Host, std_high);
        bus.send(0, Node::Host, ext_same_base);
        bus.send(0, Node::Controller, remote);
        bus.send(0, Node::Host, data);
        bus.send(0, Node::Host, ext_low);
        let order: Vec<CanFrame> = bus.advance(10_000_000).iter().map(|t| t.frame).collect();
        // Extended 0x1 has base id 0: it wins. A data frame beats the remote frame of its id
        // (RTR is recessive), which beats the extended frame of the same base id (IDE).
        assert_eq!(order, [ext_low, data, remote, ext_same_base, std_high]);
    }

    #[test]
    fn a_dropped_frame_holds_nothing_back_and_is_logged_as_sent() {
        let window = |kind| Fault {
            kind,
            from_us: 0,
            until_us: 300,
            sender: Some(Node::Drives),
        };
        let mut bus = Bus::new(
            1_000_000,
            vec![
                window(FaultKind::Corrupt { rate: 1.0 }),
                window(FaultKind::Delay { micros: 5_000 }),
                window(FaultKind::Burst),
            ],
            1,
        );
        let sent = frame(0x201, &[0; 8]);
        bus.send(0, Node::Drives, sent);
        bus.send(1_000_000, Node::Drives, frame(0x202, &[0; 8]));
        let tx = bus.advance(20_000_000);
        // Corrupted, then dropped by the burst: recorded as it was sent, counted as dropped.
        assert_eq!((tx[0].fate, tx[0].frame), (Fate::Dropped, sent));
        assert_eq!((bus.stats().dropped, bus.stats().corrupted), (1, 0));
        // The next frame, outside every window, arrives at its end of frame, not after the
        // dropped frame's 5 ms delay.
        assert_eq!(tx[1].fate, Fate::Delivered);
        assert_eq!(tx[1].delivered_ns, 1_000_000 + u64::from(tx[1].bits) * 1000);
    }

    #[test]
    fn frame_lengths_match_hand_counts() {
        // All-zero 8-byte frame with id 0: 34 + 64 unstuffed header/data bits of long zero
        // runs; the exact count is what the stuffing rule gives.
        let zeros = frame(0x000, &[0; 8]);
        let n = frame_bits(&zeros);
        // Unstuffed: 1 + 11 + 3 + 4 + 64 + 15 = 98, + 13 fixed = 111; zeros stuff heavily.
        assert!(n > 111 + 15 && n <= 135, "{n}");
        // Alternating bits never stuff: 0x2AA id pattern and 0x55 data.
        let alt = frame(0x555, &[0x55; 8]);
        assert!(frame_bits(&alt) >= 111 && frame_bits(&alt) < 120);
        // A zero-length frame: 1 + 11 + 3 + 4 + 15 = 34 + 13 = 47 bits before stuffing.
        let empty = frame(0x303, &[]);
        assert!((47..=47 + 8).contains(&frame_bits(&empty)));
    }

    /// The obvious implementation: build the bit vector, CRC it, count stuff bits.
    fn reference_bits(frame: &CanFrame) -> u32 {
        let mut bits = Vec::new();
        let mut push = |v: u32, n: u32| {
            for i in (0..n).rev() {
                bits.push((v >> i) & 1 == 1);
            }
        };
        push(0, 1);
        match frame.id() {
            Id::Standard(id) => {
                push(u32::from(id.as_raw()), 11);
                push(u32::from(frame.is_remote_frame()), 1);
                push(0, 2);
            }
            Id::Extended(id) => {
                push(id.as_raw() >> 18, 11);
                push(0b11, 2);
                push(id.as_raw() & 0x3_FFFF, 18);
                push(u32::from(frame.is_remote_frame()), 1);
                push(0, 2);
            }
        }
        push(frame.dlc() as u32, 4);
        if !frame.is_remote_frame() {
            for &b in frame.data() {
                push(u32::from(b), 8);
            }
        }
        let crc = crc15(&bits);
        for i in (0..15).rev() {
            bits.push((crc >> i) & 1 == 1);
        }
        let (mut stuffed, mut run, mut last) = (0, 0, None);
        for &b in &bits {
            if Some(b) == last {
                run += 1;
            } else {
                run = 1;
                last = Some(b);
            }
            if run == 5 {
                stuffed += 1;
                last = Some(!b);
                run = 1;
            }
        }
        bits.len() as u32 + stuffed + 13
    }

    #[test]
    fn streaming_length_equals_the_reference_on_many_frames() {
        let mut rng = SplitMix64(11);
        for _ in 0..5000 {
            let r = rng.next_u64();
            let dlc = (r % 9) as usize;
            let data: Vec<u8> = (0..dlc).map(|_| rng.next_u64() as u8).collect();
            let f = frame((r >> 8) as u16 & 0x7FF, &data);
            assert_eq!(frame_bits(&f), reference_bits(&f), "{f:?}");
        }
        // Long runs, where stuff bits follow each other and a stuff bit starts the next run:
        // bytes from a palette of runs, ids with runs.
        let palette = [0x00, 0xFF, 0x0F, 0xF0, 0x07, 0xF8, 0x83, 0x7C, 0x01, 0xFE];
        let ids = [0x000, 0x7FF, 0x001, 0x7E0, 0x01F, 0x200, 0x3FF, 0x400];
        for _ in 0..20_000 {
            let r = rng.next_u64();
            let dlc = (r % 9) as usize;
            let data: Vec<u8> = (0..dlc)
                .map(|_| palette[(rng.next_u64() % palette.len() as u64) as usize])
                .collect();
            let f = frame(ids[((r >> 8) % ids.len() as u64) as usize], &data);
            assert_eq!(frame_bits(&f), reference_bits(&f), "{f:?}");
        }
        // Extended ids and remote frames, the same way.
        for _ in 0..5000 {
            let r = rng.next_u64();
            let dlc = (r % 9) as usize;
            let id = embedded_can::ExtendedId::new((r >> 8) as u32 & 0x1FFF_FFFF).unwrap();
            let data: Vec<u8> = (0..dlc).map(|_| rng.next_u64() as u8).collect();
            let f = <CanFrame as embedded_can::Frame>::new(id, &data).unwrap();
            assert_eq!(frame_bits(&f), reference_bits(&f), "{f:?}");
            let remote = <CanFrame as embedded_can::Frame>::new_remote(id, dlc).unwrap();
            assert_eq!(frame_bits(&remote), reference_bits(&remote), "{remote:?}");
            let std = StandardId::new((r >> 40) as u16 & 0x7FF).unwrap();
            let remote = <CanFrame as embedded_can::Frame>::new_remote(std, dlc).unwrap();
            assert_eq!(frame_bits(&remote), reference_bits(&remote), "{remote:?}");
        }
        // An extended frame of 8 bytes: 39 + 64 + 15 + 13 = 131 bits before stuffing.
        let ext = <CanFrame as embedded_can::Frame>::new(
            embedded_can::ExtendedId::new(0x0AAA_AAAA).unwrap(),
            &[0x55; 8],
        )
        .unwrap();
        assert!((131..131 + 25).contains(&frame_bits(&ext)));
        // Worst case for an 8-byte standard frame: 135 bits with intermission is the bound
        // usually quoted; no frame exceeds it.
        assert!(frame_bits(&frame(0, &[0; 8])) <= 135);
    }

    #[test]
    fn crc15_of_known_vector() {
        // CRC-15/CAN of the ASCII string "123456789" is 0x059E.
        let mut bits = Vec::new();
        for b in b"123456789" {
            for i in (0..8).rev() {
                bits.push((b >> i) & 1 == 1);
            }
        }
        assert_eq!(crc15(&bits), 0x059E);
    }

    #[test]
    fn lowest_id_wins_and_timing_is_exact() {
        let mut bus = Bus::new(1_000_000, vec![], 1);
        bus.send(0, Node::Drives, frame(0x201, &[1; 8]));
        bus.send(0, Node::Controller, frame(0x200, &[2; 8]));
        bus.send(0, Node::Host, frame(0x301, &[3; 8]));
        let tx = bus.advance(1_000_000);
        let ids: Vec<u16> = tx.iter().map(|t| raw_id(&t.frame)).collect();
        assert_eq!(ids, [0x200, 0x201, 0x301]);
        // Back to back: each starts when the previous ended.
        for w in tx.windows(2) {
            assert_eq!(w[1].start_ns, w[0].delivered_ns);
        }
        assert_eq!(tx[0].delivered_ns, u64::from(tx[0].bits) * 1000);
        assert_eq!(
            bus.stats().busy_ns,
            tx.iter().map(|t| u64::from(t.bits) * 1000).sum::<u64>()
        );
    }

    #[test]
    fn a_frame_queued_later_waits_for_the_bus_even_with_a_lower_id() {
        let mut bus = Bus::new(1_000_000, vec![], 1);
        bus.send(0, Node::Drives, frame(0x201, &[0; 8]));
        bus.send(10_000, Node::Controller, frame(0x100, &[0; 8]));
        let tx = bus.advance(1_000_000);
        assert_eq!(raw_id(&tx[0].frame), 0x201);
        assert_eq!(tx[1].start_ns, tx[0].delivered_ns);
        assert_eq!(
            tx[1].start_ns - tx[1].queued_ns,
            tx[0].delivered_ns - 10_000
        );
    }

    #[test]
    fn faults_are_seeded_and_windowed() {
        let faults = vec![
            Fault {
                kind: FaultKind::Drop { rate: 0.5 },
                from_us: 0,
                until_us: 100_000,
                sender: Some(Node::Drives),
            },
            Fault {
                kind: FaultKind::Burst,
                from_us: 200_000,
                until_us: 300_000,
                sender: None,
            },
        ];
        let run = |seed| {
            let mut bus = Bus::new(1_000_000, faults.clone(), seed);
            for k in 0..400u64 {
                bus.send(k * 1_000_000, Node::Drives, frame(0x201, &[k as u8; 8]));
                bus.send(k * 1_000_000, Node::Host, frame(0x301, &[0; 8]));
            }
            bus.advance(u64::MAX)
        };
        let a = run(7);
        assert_eq!(a, run(7), "same seed, same faults");
        assert_ne!(a, run(8));
        let dropped = |lo: u64, hi: u64, from: Node| {
            a.iter()
                .filter(|t| t.from == from && t.start_ns >= lo * 1000 && t.start_ns < hi * 1000)
                .filter(|t| t.fate == Fate::Dropped)
                .count()
        };
        // ~50 % of the 100 drive frames in the first window, none from the host.
        let d = dropped(0, 100_000, Node::Drives);
        assert!((30..=70).contains(&d), "{d}");
        assert_eq!(dropped(0, 100_000, Node::Host), 0);
        // Everything in the burst, nothing between the windows.
        assert_eq!(dropped(200_000, 299_000, Node::Host), 99);
        assert_eq!(dropped(100_000, 200_000, Node::Drives), 0);
    }

    #[test]
    fn corruption_flips_one_byte_and_delay_shifts_delivery() {
        let faults = vec![
            Fault {
                kind: FaultKind::Corrupt { rate: 1.0 },
                from_us: 0,
                until_us: u64::MAX,
                sender: None,
            },
            Fault {
                kind: FaultKind::Delay { micros: 250 },
                from_us: 0,
                until_us: u64::MAX,
                sender: None,
            },
        ];
        let mut bus = Bus::new(1_000_000, faults, 3);
        let sent = frame(0x201, &[0; 8]);
        bus.send(0, Node::Drives, sent);
        let tx = bus.advance(u64::MAX);
        let diff = sent
            .data()
            .iter()
            .zip(tx[0].frame.data())
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!((tx[0].fate, diff), (Fate::Corrupted, 1));
        assert_eq!(tx[0].delivered_ns, u64::from(tx[0].bits) * 1000 + 250_000);
    }

    #[test]
    fn a_delayed_sender_keeps_its_order_and_others_are_not_held_up() {
        let faults = vec![Fault {
            kind: FaultKind::Delay { micros: 900 },
            from_us: 0,
            until_us: 300,
            sender: Some(Node::Drives),
        }];
        let mut bus = Bus::new(1_000_000, faults, 1);
        // Drive frames at 0 and 400 µs: the first is delayed to about 1 ms, the second not
        // (its window is over), so it must wait for the first.
        bus.send(0, Node::Drives, frame(0x201, &[1; 8]));
        bus.send(400_000, Node::Drives, frame(0x202, &[2; 8]));
        bus.send(400_000, Node::Host, frame(0x301, &[3; 8]));
        let tx = bus.advance(u64::MAX);
        let at = |id: u16| {
            tx.iter()
                .find(|t| raw_id(&t.frame) == id)
                .map(|t| (t.start_ns, t.delivered_ns))
                .unwrap()
        };
        let (first, second, host) = (at(0x201), at(0x202), at(0x301));
        assert!(first.1 >= 900_000, "{first:?}");
        assert_eq!(
            second.1, first.1,
            "the later drive frame waits for the delayed one"
        );
        // The host frame went on the wire after the second drive frame's and is not held.
        assert!(
            host.0 > second.0 && host.1 < first.1,
            "{host:?} vs {first:?}"
        );
    }
}
