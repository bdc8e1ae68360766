//! The candump grammar: write then parse is the identity, no input panics, and every
//! malformed line is a typed error naming its line.

use drivelog::candump::{self, Entry, ErrorKind, Writer};
use embedded_can::{ExtendedId, Frame as _, StandardId};
use firmware::CanFrame;
use proptest::prelude::*;

fn arb_frame() -> impl Strategy<Value = CanFrame> {
    let id = (0u16..=0x7FF).prop_map(|raw| StandardId::new(raw).unwrap());
    prop_oneof![
        (id.clone(), proptest::collection::vec(any::<u8>(), 0..=8))
            .prop_map(|(id, data)| CanFrame::standard(id, &data).unwrap()),
        (id, 0u8..=8).prop_map(|(id, dlc)| CanFrame::remote(id, dlc)),
        (
            0u32..=0x1FFF_FFFF,
            proptest::collection::vec(any::<u8>(), 0..=8)
        )
            .prop_map(|(raw, data)| CanFrame::new(ExtendedId::new(raw).unwrap(), &data).unwrap()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn write_then_parse_is_the_identity(
        t_us in 0u64..100_000_000_000_000,
        iface in "[a-z][a-z0-9_.-]{0,14}",
        frame in arb_frame(),
    ) {
        let t_ns = t_us * 1000;
        let line = candump::format_line(t_ns, &iface, &frame).unwrap();
        let e = candump::parse_line(&line, 1).unwrap().unwrap();
        prop_assert_eq!(e, Entry { t_ns, iface, frame, direction: None });
    }

    #[test]
    fn a_written_log_parses_back(frames in proptest::collection::vec((0u64..10_000_000, arb_frame()), 0..40)) {
        let mut w = Writer::new(Vec::new(), "vcan0").unwrap();
        for (t_us, f) in &frames {
            w.write(t_us * 1000, f).unwrap();
        }
        let bytes = w.finish().unwrap();
        let parsed = candump::parse_log_bytes(&bytes).unwrap();
        let got: Vec<(u64, CanFrame)> = parsed.iter().map(|e| (e.t_ns / 1000, e.frame)).collect();
        prop_assert_eq!(got, frames);
    }

    #[test]
    fn parse_never_panics_on_any_text(text in ".{0,200}") {
        let _ = candump::parse_line(&text, 7);
        let _ = candump::parse_log(&text);
    }

    #[test]
    fn parse_never_panics_on_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = candump::parse_log_bytes(&bytes);
        let _ = candump::looks_like_candump(&bytes);
    }

    #[test]
    fn parse_never_panics_on_near_candump_lines(
        line in r"\(?[0-9]{0,22}\.?[0-9]{0,12}\)? ?[a-z0-9#]{0,6} ?[0-9A-Fa-f]{0,9}#{0,4}[0-9A-Fa-fRr._#]{0,24}( [RTX])?",
        n in 1usize..100,
    ) {
        match candump::parse_line(&line, n) {
            Ok(Some(e)) => {
                // Whatever parses writes back and parses to the same thing (µs timestamps).
                let again = candump::format_line(e.t_ns, &e.iface, &e.frame).unwrap();
                let e2 = candump::parse_line(&again, n).unwrap().unwrap();
                prop_assert_eq!((e2.t_ns, e2.frame), (e.t_ns / 1000 * 1000, e.frame));
            }
            // Blank, or an error frame (skipped).
            Ok(None) => prop_assert!(
                line.trim().is_empty()
                    || line
                        .split_ascii_whitespace()
                        .nth(2)
                        .and_then(|t| t.split_once('#'))
                        .is_some_and(|(id, _)| candump::is_error_frame_id(id)),
                "{}",
                line
            ),
            Err(err) => {
                prop_assert_eq!(err.line, n);
                let shown = err.to_string();
                let expected_prefix = format!("line {n}: ");
                prop_assert!(shown.starts_with(&expected_prefix));
            }
        }
    }
}

#[test]
fn extended_lines_parse_and_fd_lines_are_typed_errors_naming_line_and_text() {
    let text = "(1700000000.000100) vcan0 201#0000000000000000\n\
                (1700000000.000200) vcan0 1F334455#1122\n";
    let entries = candump::parse_log(text).unwrap();
    assert_eq!(entries[1].frame.to_string(), "1F334455#1122");
    let e = candump::parse_log("\n\n(1.000000) can0 301##1AABB\n").unwrap_err();
    assert_eq!((e.line, &e.kind), (3, &ErrorKind::CanFd));
}
