//! Faults on the bus: each [`Fault`] applies to frames whose transmission ends inside its
//! time window and, if given, that come from one node: random drops, total loss (a burst),
//! extra delivery delay, a flipped byte. Random choices come from a [`SplitMix64`] generator
//! seeded by the scenario, so the same seed gives the same faults on every run and every
//! machine.

use embedded_can::{Frame, Id};
use firmware::CanFrame;
pub use firmware::rng::SplitMix64;

use super::Node;

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

/// What the `faults` active for a frame `from` a node whose transmission ends at `end_ns` do
/// to it (`sent`): the frame as received, its fate and the extra delivery delay, ns. Random
/// choices are drawn from `rng`, in the order of the faults.
pub(super) fn apply(
    faults: &[Fault],
    rng: &mut SplitMix64,
    end_ns: u64,
    from: Node,
    sent: CanFrame,
) -> (CanFrame, Fate, u64) {
    let end_us = end_ns / 1000;
    let mut frame = sent;
    let mut fate = Fate::Delivered;
    let mut delay_ns = 0;
    for f in faults {
        if end_us < f.from_us || end_us >= f.until_us || f.sender.is_some_and(|s| s != from) {
            continue;
        }
        match f.kind {
            FaultKind::Burst => fate = Fate::Dropped,
            FaultKind::Drop { rate } => {
                if rng.unit() < rate {
                    fate = Fate::Dropped;
                }
            }
            FaultKind::Delay { micros } => delay_ns += micros * 1000,
            FaultKind::Corrupt { rate } => {
                let dlc = frame.dlc();
                if dlc > 0 && rng.unit() < rate && fate == Fate::Delivered {
                    let r = rng.next_u64();
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
