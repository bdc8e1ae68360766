//! Hand-written JSON for the messages written most often: the CAN frames of `/can/rx`,
//! `/can/tx` and `/can/bus` (about ten per simulated millisecond).
//!
//! `core::fmt` (`write!`) costs a dynamic dispatch per argument and per piece of literal text;
//! these messages are fixed text around a few unsigned integers and booleans, so they are
//! appended as byte strings, with a small integer formatter. The output is the same JSON text
//! `write!` gave.

use embedded_can::{Frame, Id};
use firmware::CanFrame;

use crate::bus::{Fate, Node};

/// "00" to "99", for two digits at a time.
const DIGIT_PAIRS: &[u8; 200] = b"\
    0001020304050607080910111213141516171819\
    2021222324252627282930313233343536373839\
    4041424344454647484950515253545556575859\
    6061626364656667686970717273747576777879\
    8081828384858687888990919293949596979899";

/// 10^i for i in 0..20.
const POWERS_OF_10: [u64; 20] = {
    let mut p = [1u64; 20];
    let mut i = 1;
    while i < 20 {
        p[i] = p[i - 1] * 10;
        i += 1;
    }
    p
};

/// Decimal digits of `n` (1 to 20).
#[inline]
fn decimal_len(n: u64) -> usize {
    // log10(2) is about 1233 / 4096: an estimate from the bit length, off by at most one.
    let bits = 64 - (n | 1).leading_zeros() as usize;
    let estimate = (bits * 1233) >> 12;
    estimate + 1 - usize::from((n | 1) < POWERS_OF_10[estimate])
}

/// Appends `n` in decimal.
#[inline(always)]
pub(crate) fn push_u64(buf: &mut Vec<u8>, mut n: u64) {
    let len = decimal_len(n);
    let start = buf.len();
    // A fixed-size append and a truncation rather than a copy of a variable length: no call
    // to memcpy for a few bytes.
    buf.extend_from_slice(&[b'0'; 20]);
    let digits = &mut buf[start..start + len];
    let mut at = len;
    while n >= 100 {
        let pair = (n % 100) as usize * 2;
        n /= 100;
        at -= 2;
        digits[at..at + 2].copy_from_slice(&DIGIT_PAIRS[pair..pair + 2]);
    }
    if n >= 10 {
        let pair = n as usize * 2;
        digits[at - 2..at].copy_from_slice(&DIGIT_PAIRS[pair..pair + 2]);
    } else {
        digits[at - 1] = b'0' + n as u8;
    }
    buf.truncate(start + len);
}

/// Every byte in decimal followed by a separator byte (patched in by [`push_u8_then`]),
/// padded to four bytes, and the length of each without the padding.
const BYTE_TEXT: ([[u8; 4]; 256], [u8; 256]) = {
    let mut text = [[0u8; 4]; 256];
    let mut len = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let b = i as u8;
        if b >= 100 {
            text[i] = [b'0' + b / 100, b'0' + b / 10 % 10, b'0' + b % 10, 0];
            len[i] = 4;
        } else if b >= 10 {
            text[i] = [b'0' + b / 10, b'0' + b % 10, 0, 0];
            len[i] = 3;
        } else {
            text[i] = [b'0' + b, 0, 0, 0];
            len[i] = 2;
        }
        i += 1;
    }
    (text, len)
};

/// Appends a byte in decimal followed by `sep`.
#[inline]
fn push_u8_then(buf: &mut Vec<u8>, n: u8, sep: u8) {
    let start = buf.len();
    let len = usize::from(BYTE_TEXT.1[usize::from(n)]);
    buf.extend_from_slice(&BYTE_TEXT.0[usize::from(n)]);
    buf[start + len - 1] = sep;
    buf.truncate(start + len);
}

#[inline]
fn push_bool(buf: &mut Vec<u8>, b: bool) {
    buf.extend_from_slice(if b { b"true" } else { b"false" });
}

/// Appends one frame as can_msgs/Frame-shaped JSON (see
/// [`CAN_FRAME_SCHEMA`](super::CAN_FRAME_SCHEMA)), data padded to 8 bytes, with `sender` and
/// `fate` for the bus channel:
///
/// `{"header":{"stamp":{"sec":1,"nsec":5000},"frame_id":"can0"},"id":513,"is_rtr":false,
/// "is_extended":false,"is_error":false,"dlc":8,"data":[0,1,2,3,4,5,6,7],"sender":"drives",
/// "fate":"delivered"}` (on one line).
pub fn write_frame_json(
    buf: &mut Vec<u8>,
    t_ns: u64,
    frame: &CanFrame,
    extra: Option<(Node, Fate)>,
) {
    let (id, ext) = match frame.id() {
        Id::Standard(id) => (u32::from(id.as_raw()), false),
        Id::Extended(id) => (id.as_raw(), true),
    };
    let mut data = [0u8; 8];
    let d = frame.data();
    data[..d.len()].copy_from_slice(d);
    buf.reserve(256);
    buf.extend_from_slice(br#"{"header":{"stamp":{"sec":"#);
    push_u64(buf, t_ns / 1_000_000_000);
    buf.extend_from_slice(br#","nsec":"#);
    push_u64(buf, t_ns % 1_000_000_000);
    buf.extend_from_slice(br#"},"frame_id":"can0"},"id":"#);
    push_u64(buf, u64::from(id));
    buf.extend_from_slice(br#","is_rtr":"#);
    push_bool(buf, frame.is_remote_frame());
    buf.extend_from_slice(br#","is_extended":"#);
    push_bool(buf, ext);
    buf.extend_from_slice(br#","is_error":false,"dlc":"#);
    // A DLC is at most 8 (15 for CAN FD).
    push_u8_then(buf, frame.dlc() as u8, b',');
    buf.pop();
    buf.extend_from_slice(br#","data":["#);
    for &b in &data[..7] {
        push_u8_then(buf, b, b',');
    }
    push_u8_then(buf, data[7], b']');
    if let Some((sender, fate)) = extra {
        let fate = match fate {
            Fate::Delivered => "delivered",
            Fate::Dropped => "dropped",
            Fate::Corrupted => "corrupted",
        };
        buf.extend_from_slice(br#","sender":""#);
        buf.extend_from_slice(sender.name().as_bytes());
        buf.extend_from_slice(br#"","fate":""#);
        buf.extend_from_slice(fate.as_bytes());
        buf.push(b'"');
    }
    buf.push(b'}');
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use embedded_can::{ExtendedId, StandardId};

    use super::*;

    #[test]
    fn integers_match_display() {
        let mut buf = Vec::new();
        let mut n = 1u64;
        let mut values = vec![0, 9, 10, 99, 100, 101, 999, 1000, u64::MAX, u64::MAX - 1];
        while let Some(m) = n.checked_mul(7) {
            values.extend([n - 1, n, n + 1]);
            n = m;
        }
        values.extend(POWERS_OF_10.iter().flat_map(|&p| [p - 1, p, p + 1]));
        for v in values {
            buf.clear();
            push_u64(&mut buf, v);
            assert_eq!(buf, v.to_string().as_bytes());
        }
        for b in 0..=255u8 {
            buf.clear();
            push_u8_then(&mut buf, b, b',');
            assert_eq!(buf, format!("{b},").as_bytes());
        }
    }

    /// The text `write!` gave before the formatter was hand-written.
    fn with_fmt(t_ns: u64, frame: &CanFrame, extra: Option<(Node, Fate)>) -> Vec<u8> {
        let (id, ext) = match frame.id() {
            Id::Standard(id) => (u32::from(id.as_raw()), false),
            Id::Extended(id) => (id.as_raw(), true),
        };
        let mut d = [0u8; 8];
        d[..frame.data().len()].copy_from_slice(frame.data());
        let mut buf = Vec::new();
        write!(
            buf,
            r#"{{"header":{{"stamp":{{"sec":{},"nsec":{}}},"frame_id":"can0"}},"id":{},"is_rtr":{},"is_extended":{},"is_error":false,"dlc":{},"data":[{},{},{},{},{},{},{},{}]"#,
            t_ns / 1_000_000_000,
            t_ns % 1_000_000_000,
            id,
            frame.is_remote_frame(),
            ext,
            frame.dlc(),
            d[0],
            d[1],
            d[2],
            d[3],
            d[4],
            d[5],
            d[6],
            d[7],
        )
        .unwrap();
        if let Some((sender, fate)) = extra {
            let fate = format!("{fate:?}").to_lowercase();
            write!(buf, r#","sender":"{}","fate":"{fate}""#, sender.name()).unwrap();
        }
        buf.push(b'}');
        buf
    }

    #[test]
    fn frames_are_the_json_write_gave_and_parse() {
        let frames = [
            CanFrame::standard(
                StandardId::new(0x201).unwrap(),
                &[0, 9, 10, 99, 100, 255, 1, 7],
            )
            .unwrap(),
            CanFrame::standard(StandardId::new(0x7FF).unwrap(), &[3]).unwrap(),
            CanFrame::new(ExtendedId::new(0x1FFF_FFFF).unwrap(), &[]).unwrap(),
            CanFrame::new_remote(StandardId::ZERO, 4).unwrap(),
        ];
        let extras = [
            None,
            Some((Node::Drives, Fate::Delivered)),
            Some((Node::Host, Fate::Dropped)),
            Some((Node::Controller, Fate::Corrupted)),
        ];
        for (i, frame) in frames.iter().enumerate() {
            for extra in extras {
                for t_ns in [0, 999_999_999, 1_000_000_000, 61_234_567_890, u64::MAX] {
                    let mut buf = b"prefix".to_vec();
                    write_frame_json(&mut buf, t_ns, frame, extra);
                    let json = &buf[b"prefix".len()..];
                    assert_eq!(
                        json,
                        with_fmt(t_ns, frame, extra),
                        "frame {i}, {}",
                        String::from_utf8_lossy(json)
                    );
                    let v: serde_json::Value = serde_json::from_slice(json).unwrap();
                    assert_eq!(v["data"].as_array().unwrap().len(), 8);
                    assert_eq!(v["header"]["stamp"]["sec"], t_ns / 1_000_000_000);
                }
            }
        }
    }
}
