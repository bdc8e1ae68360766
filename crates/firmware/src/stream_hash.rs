//! One hash of a frame stream, for bit-identity checks: the simulator's pinned runs, the
//! board under emulation and the cross-target check all mean this one by "outbound stream
//! hash".

use embedded_can::{Frame, Id};

/// FNV-1a 64 over a stream of timed CAN frames: equal hashes, equal streams.
///
/// [`add`](Self::add) feeds, for each frame and in this order:
/// 1. its time `t_us` as 8 bytes, little-endian;
/// 2. its id as a `u32`, 4 bytes little-endian: the raw 11- or 29-bit id, with bit 31 set
///    for an extended id and bit 30 for a remote frame (SocketCAN's `can_id` word:
///    `CAN_EFF_FLAG`, `CAN_RTR_FLAG`);
/// 3. its DLC, 1 byte;
/// 4. its data bytes, `dlc` of them (none for a remote frame).
///
/// For a standard data frame, the frames every pinned run sends, that is the time, the id,
/// the DLC and the data and nothing else. [`write`](Self::write) feeds raw bytes (a hash of
/// several streams' hashes, say). The hash starts at the FNV-1a 64 offset basis
/// `0xcbf29ce484222325` and multiplies by the prime `0x100000001b3`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamHash(u64);

impl Default for StreamHash {
    fn default() -> Self {
        Self::new()
    }
}

impl StreamHash {
    /// SocketCAN's `CAN_EFF_FLAG`: the id is extended.
    const EXTENDED: u32 = 0x8000_0000;
    /// SocketCAN's `CAN_RTR_FLAG`: a remote frame.
    const REMOTE: u32 = 0x4000_0000;

    /// The hash of nothing (the offset basis).
    #[must_use]
    pub const fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    /// Feeds raw bytes.
    pub fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01B3);
        }
    }

    /// Feeds one frame sent at `t_us` (the bytes are in the type's documentation).
    pub fn add<F: Frame>(&mut self, t_us: u64, frame: &F) {
        let mut id = match frame.id() {
            Id::Standard(id) => u32::from(id.as_raw()),
            Id::Extended(id) => id.as_raw() | Self::EXTENDED,
        };
        if frame.is_remote_frame() {
            id |= Self::REMOTE;
        }
        self.write(&t_us.to_le_bytes());
        self.write(&id.to_le_bytes());
        // A classic frame's DLC is at most 8 (15 for CAN FD): it fits a byte.
        self.write(&[frame.dlc() as u8]);
        if !frame.is_remote_frame() {
            self.write(frame.data());
        }
    }

    /// The hash so far.
    #[must_use]
    pub const fn value(self) -> u64 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use embedded_can::{ExtendedId, StandardId};

    use super::*;
    use crate::CanFrame;

    #[test]
    fn a_standard_data_frame_is_its_time_id_dlc_and_data() {
        let f = CanFrame::standard(StandardId::new(0x201).unwrap(), &[1, 2, 3]).unwrap();
        let mut h = StreamHash::new();
        h.add(1_000, &f);
        let mut bytes = StreamHash::new();
        bytes.write(&1_000u64.to_le_bytes());
        bytes.write(&[0x01, 0x02, 0, 0, 3, 1, 2, 3]);
        assert_eq!(h, bytes);
        // FNV-1a 64 of nothing, and of "a" (the published test vector).
        assert_eq!(StreamHash::new().value(), 0xcbf2_9ce4_8422_2325);
        let mut a = StreamHash::new();
        a.write(b"a");
        assert_eq!(a.value(), 0xaf63_dc4c_8601_ec8c);
    }

    #[test]
    fn extended_and_remote_frames_are_flagged_in_the_id_word() {
        let hash = |f: &CanFrame| {
            let mut h = StreamHash::new();
            h.add(7, f);
            h
        };
        let words = |id: u32, tail: &[u8]| {
            let mut h = StreamHash::new();
            h.write(&7u64.to_le_bytes());
            h.write(&id.to_le_bytes());
            h.write(tail);
            h
        };
        let ext = <CanFrame as Frame>::new(ExtendedId::new(0x201).unwrap(), &[9]).unwrap();
        assert_eq!(hash(&ext), words(0x8000_0201, &[1, 9]));
        let rtr = CanFrame::remote(StandardId::new(0x201).unwrap(), 8);
        assert_eq!(hash(&rtr), words(0x4000_0201, &[8]));
        let std = CanFrame::standard(StandardId::new(0x201).unwrap(), &[9]).unwrap();
        assert_ne!(hash(&ext), hash(&std));
    }
}
