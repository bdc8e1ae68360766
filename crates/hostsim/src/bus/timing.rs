//! A frame's timing on the wire. A classic CAN data frame with an 11-bit id is SOF, id, RTR,
//! IDE, r0, DLC, data and CRC-15, all subject to bit stuffing (after five equal bits the
//! transmitter inserts the complement), then CRC delimiter, ACK slot and delimiter, seven EOF
//! bits and three bits of intermission. [`frame_bits`] builds that bit sequence for the
//! actual frame, CRC included, and counts the stuff bits, so a frame's duration is exact, not
//! a worst-case estimate: at 1 Mbit/s an 8-byte frame takes 111 to 135 µs depending on its
//! content.

use embedded_can::{Frame, Id};
use firmware::CanFrame;

/// The bits a frame arbitrates with, in wire order, left-aligned in 32 bits: the base id,
/// RTR (standard) or SRR (extended, recessive), IDE, then for an extended frame its 18 low
/// id bits and RTR. A data frame beats a remote frame of the same id, a standard frame an
/// extended one of the same base id.
pub(super) fn arbitration_field(frame: &CanFrame) -> u32 {
    let rtr = u32::from(frame.is_remote_frame());
    match frame.id() {
        Id::Standard(id) => (u32::from(id.as_raw()) << 21) | (rtr << 20),
        Id::Extended(id) => {
            let id = id.as_raw();
            ((id >> 18) << 21) | (0b11 << 19) | ((id & 0x3_FFFF) << 1) | rtr
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::SplitMix64;
    use embedded_can::StandardId;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
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
}
