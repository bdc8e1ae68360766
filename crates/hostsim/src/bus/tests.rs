//! The bus's arbitration, timing of transmissions, and faults.

use super::*;
use embedded_can::{Frame, Id, StandardId};

fn frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
}

/// A fault of `kind` on the frames that end in `[from_us, until_us)`, from `sender` or all.
fn fault(kind: FaultKind, from_us: u64, until_us: u64, sender: Option<Node>) -> Fault {
    Fault {
        kind,
        from_us,
        until_us,
        sender,
    }
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
    let window = |kind| fault(kind, 0, 300, Some(Node::Drives));
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
        fault(
            FaultKind::Drop { rate: 0.5 },
            0,
            100_000,
            Some(Node::Drives),
        ),
        fault(FaultKind::Burst, 200_000, 300_000, None),
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
        fault(FaultKind::Corrupt { rate: 1.0 }, 0, u64::MAX, None),
        fault(FaultKind::Delay { micros: 250 }, 0, u64::MAX, None),
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
    let faults = vec![fault(
        FaultKind::Delay { micros: 900 },
        0,
        300,
        Some(Node::Drives),
    )];
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
