//! The controller driven through its registers as the board's firmware drives it.

use embedded_can::{ExtendedId, Frame, StandardId};
use firmware::CanFrame;

use super::registers::{mcr, msr};
use super::*;

fn std_frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
}

/// The controller as embassy-stm32 configures it for the board: initialisation, bank 0
/// accepting every standard id into FIFO 0, 1 Mbit/s, TXFP, then normal mode.
fn board_can() -> BxCan {
    let mut c = BxCan::new(4);
    c.write(reg::MCR, 4, mcr::INRQ, 0);
    assert_eq!(
        c.read(reg::MSR, 4).unwrap() & 3,
        msr::INAK,
        "initialisation"
    );
    c.write(reg::IER, 4, 0x8F13, 0);
    c.write(reg::FMR, 4, FMR_RESET, 0);
    c.write(reg::FA1R, 4, 1, 0);
    c.write(reg::FS1R, 4, 1, 0);
    c.write(reg::F0R1, 4, 0, 0);
    c.write(reg::F0R1 + 4, 4, 0x4, 0);
    c.write(reg::FMR, 4, FMR_RESET & !1, 0);
    c.write(reg::BTR, 4, 2 | 9 << 16 | 2 << 20, 0);
    c.write(reg::MCR, 4, mcr::TXFP | mcr::TTCM, 0);
    assert!(c.online());
    c
}

fn request(c: &mut BxCan, mailbox: u32, id: u16, data: &[u8]) {
    let base = reg::TI0R + 16 * mailbox;
    let mut bytes = [0u8; 8];
    bytes[..data.len()].copy_from_slice(data);
    c.write(base + 4, 4, data.len() as u32, 0);
    c.write(
        base + 8,
        4,
        u32::from_le_bytes(bytes[..4].try_into().unwrap()),
        0,
    );
    c.write(
        base + 12,
        4,
        u32::from_le_bytes(bytes[4..].try_into().unwrap()),
        0,
    );
    c.write(base, 4, u32::from(id) << 21 | 1, 0);
}

#[test]
fn reset_values_are_rm0090s() {
    let c = BxCan::new(4);
    assert_eq!(c.read(reg::MCR, 4), Some(MCR_RESET));
    assert_eq!(c.read(reg::MSR, 4), Some(MSR_RESET));
    assert_eq!(c.read(reg::TSR, 4), Some(0x1C00_0000));
    assert_eq!(c.read(reg::BTR, 4), Some(BTR_RESET));
    assert_eq!(c.read(reg::FMR, 4), Some(FMR_RESET));
    assert_eq!((c.read(reg::FMR, 4).unwrap() >> 8) & 0x3F, 14, "CAN2SB");
    assert!(!c.online(), "sleep after reset");
}

#[test]
fn init_and_sleep_handshakes_follow_mcr() {
    let mut c = BxCan::new(4);
    c.write(reg::MCR, 4, mcr::INRQ, 0);
    assert_eq!(c.read(reg::MSR, 4).unwrap() & 3, msr::INAK);
    c.write(reg::MCR, 4, mcr::SLEEP, 0);
    let msr = c.read(reg::MSR, 4).unwrap();
    assert_eq!(msr & 3, msr::SLAK);
    assert_ne!(msr & msr::SLAKI, 0, "SLAKI on entering sleep");
    c.write(reg::MSR, 4, msr::SLAKI, 0);
    assert_eq!(c.read(reg::MSR, 4).unwrap() & msr::SLAKI, 0, "rc_w1");
    c.write(reg::MCR, 4, 0, 0);
    assert!(c.online());
    // BTR is write-protected outside initialisation.
    c.write(reg::BTR, 4, 0, 0);
    assert_eq!(c.read(reg::BTR, 4), Some(BTR_RESET));
}

#[test]
fn txfp_sends_in_request_order_and_tsr_reports_it() {
    let mut c = board_can();
    request(&mut c, 0, 0x300, &[1]);
    request(&mut c, 2, 0x100, &[2]);
    request(&mut c, 1, 0x200, &[3]);
    let tsr = c.read(reg::TSR, 4).unwrap();
    assert_eq!(tsr >> 26 & 7, 0, "no empty mailbox");
    assert_eq!(
        tsr >> 24 & 3,
        1,
        "CODE: the lowest-priority (last requested) mailbox"
    );
    let (m, f) = c.offer().unwrap();
    assert_eq!((m, f.data()), (0, &[1][..]), "request order, not id");
    c.started(m, 0);
    assert_eq!(c.offer(), None, "one frame on the wire at a time");
    c.transmitted(m);
    let tsr = c.read(reg::TSR, 4).unwrap();
    assert_eq!(tsr & 3, 3, "RQCP0 and TXOK0");
    assert_eq!(tsr >> 26 & 7, 1, "TME0");
    assert_eq!(tsr >> 24 & 3, 0, "CODE: the free mailbox");
    assert_eq!(c.irq_lines(), [true, false, false, false]);
    c.write(reg::TSR, 4, 1, 0);
    assert_eq!(c.read(reg::TSR, 4).unwrap() & 0xF, 0);
    assert_eq!(c.offer().unwrap().0, 2);
    // Without TXFP: the lowest identifier first.
    c.write(reg::MCR, 4, 0, 0);
    request(&mut c, 0, 0x050, &[]);
    assert_eq!(c.offer().unwrap().0, 0);
}

#[test]
fn a_pending_mailbox_is_write_protected_and_abort_empties_it() {
    let mut c = board_can();
    request(&mut c, 0, 0x200, &[1, 2]);
    c.write(reg::TI0R + 8, 4, 0xFFFF_FFFF, 0);
    assert_eq!(c.offer().unwrap().1.data(), &[1, 2]);
    c.write(reg::TSR, 4, 1 << 7, 0);
    assert_eq!(c.offer(), None);
    assert_eq!(c.read(reg::TSR, 4).unwrap() & 0xF, 1, "RQCP without TXOK");
}

#[test]
fn fifo_holds_three_then_overruns_and_fmp_counts() {
    let mut c = board_can();
    for i in 0..3u8 {
        assert_eq!(
            c.receive(&std_frame(0x201, &[i]), 0),
            Received::Stored { fifo: 0, fmi: 0 }
        );
    }
    let rf0r = c.read(reg::RF0R, 4).unwrap();
    assert_eq!((rf0r & 3, rf0r >> 3 & 1), (3, 1), "FMP 3, FULL");
    assert_eq!(
        c.receive(&std_frame(0x202, &[9]), 0),
        Received::Overrun { fifo: 0 }
    );
    assert_eq!(c.read(reg::RF0R, 4).unwrap() >> 4 & 1, 1, "FOVR");
    // RFLM = 0: the newest was overwritten by the new frame.
    c.write(reg::RF0R, 4, 1 << 5, 0);
    c.write(reg::RF0R, 4, 1 << 5, 0);
    assert_eq!(c.read(reg::RI0R, 4), Some(0x202 << 21));
    assert_eq!(c.read(reg::RI0R + 8, 4), Some(9));
    assert_eq!(c.read(reg::RI0R + 4, 4).unwrap() & 0xF, 1, "DLC");
    c.write(reg::RF0R, 4, 1 << 4, 0);
    assert_eq!(
        c.read(reg::RF0R, 4).unwrap(),
        1,
        "FOVR cleared by writing 1"
    );
    assert_eq!(c.overruns, [1, 0]);
    // FMPIE0 with a frame: RX0 line.
    assert!(c.irq_lines()[1]);
}

#[test]
fn filters_match_in_all_four_modes_with_priority_and_fmi() {
    let mut c = board_can();
    c.write(reg::FMR, 4, FMR_RESET, 0);
    // Bank 0: 32-bit mask accepting 0x200..=0x20F into FIFO 0 (number 0).
    // Bank 1: 16-bit list of 0x201, 0x300, 0x301, 0x302 into FIFO 1 (numbers 0..3).
    // Bank 2: 32-bit list 0x205 and 0x206 into FIFO 1 (numbers 4, 5).
    // Bank 3: 16-bit masks, FIFO 0 (numbers 1, 2): exactly 0x400; 0x500..=0x5FF.
    c.write(reg::FS1R, 4, 0b0101, 0);
    c.write(reg::FM1R, 4, 0b0110, 0);
    c.write(reg::FFA1R, 4, 0b0110, 0);
    c.write(reg::F0R1, 4, 0x200 << 21, 0);
    c.write(reg::F0R1 + 4, 4, 0x7F0 << 21 | 0b110, 0);
    c.write(reg::F0R1 + 8, 4, 0x300 << 5 << 16 | 0x201 << 5, 0);
    c.write(reg::F0R1 + 12, 4, 0x302 << 5 << 16 | 0x301 << 5, 0);
    c.write(reg::F0R1 + 16, 4, 0x205 << 21, 0);
    c.write(reg::F0R1 + 20, 4, 0x206 << 21, 0);
    c.write(reg::F0R1 + 24, 4, 0xFFF8 << 16 | 0x400 << 5, 0);
    c.write(reg::F0R1 + 28, 4, 0xE018 << 16 | 0x500 << 5, 0);
    c.write(reg::FA1R, 4, 0b1111, 0);
    c.write(reg::FMR, 4, FMR_RESET & !1, 0);
    let at = |id| c.filter(&std_frame(id, &[]));
    // 0x201: bank 0 (32-bit mask) and bank 1 (16-bit list): 32-bit wins.
    assert_eq!(at(0x201), Some((0, 0)));
    // 0x205: bank 0 (32-bit mask) and bank 2 (32-bit list): the list wins.
    assert_eq!(at(0x205), Some((1, 4)));
    assert_eq!(at(0x206), Some((1, 5)));
    assert_eq!(at(0x301), Some((1, 2)));
    assert_eq!(at(0x302), Some((1, 3)));
    assert_eq!(at(0x400), Some((0, 1)));
    assert_eq!(at(0x4F1), None);
    assert_eq!(at(0x5AB), Some((0, 2)));
    assert_eq!(at(0x600), None);
    // An extended id never matches bank 0's IDE=0 mask.
    let ext = CanFrame::new(ExtendedId::new(0x200 << 18).unwrap(), &[]).unwrap();
    assert_eq!(c.filter(&ext), None);
    // In filter initialisation mode nothing is received.
    c.write(reg::FMR, 4, FMR_RESET, 0);
    assert_eq!(c.receive(&std_frame(0x201, &[]), 0), Received::Filtered);
}

#[test]
fn no_ack_makes_the_sender_error_passive_and_bit_errors_bus_off_with_abom_recovery() {
    let mut c = board_can();
    c.write(reg::MCR, 4, mcr::INRQ, 0);
    c.write(reg::IER, 4, ier::ERRIE | ier::BOFIE | ier::EPVIE, 0);
    c.write(reg::MCR, 4, mcr::TXFP | mcr::ABOM, 0);
    request(&mut c, 0, 0x200, &[1]);
    for _ in 0..40 {
        let (m, _) = c.offer().unwrap();
        c.started(m, 0);
        c.tx_error(m, Lec::Ack, 0);
    }
    // 16 ACK errors reach 128 (error passive); ACK errors then no longer count.
    assert_eq!(c.error_counters().0, 128);
    assert_eq!(c.read(reg::ESR, 4).unwrap() & 7, 0b011, "EWGF and EPVF");
    assert_eq!(c.read(reg::ESR, 4).unwrap() >> 4 & 7, Lec::Ack as u32);
    assert!(c.irq_lines()[3], "SCE: ERRI with EPVIE");
    for _ in 0..16 {
        let (m, _) = c.offer().unwrap();
        c.started(m, 0);
        c.tx_error(m, Lec::BitDominant, 1000);
    }
    assert!(c.bus_off());
    assert_eq!(c.offer(), None);
    assert_eq!(c.receive(&std_frame(0x201, &[]), 0), Received::Offline);
    let due = 1000 + BUS_OFF_RECOVERY_BITS * c.cycles_per_bit();
    assert_eq!(c.next_event(), Some(due));
    c.advance(due - 1);
    assert!(c.bus_off());
    c.advance(due);
    assert!(!c.bus_off() && c.online());
    assert_eq!(c.error_counters(), (0, 0));
    // The mailbox is still pending (NART = 0): it is sent after the recovery.
    assert_eq!(c.offer().map(|(m, _)| m), Some(0));
}

#[test]
fn the_boards_bit_time_is_one_microsecond() {
    let c = board_can();
    // 168 MHz core, 42 MHz APB1: 3 x 14 quanta of 4 cycles.
    assert_eq!(c.cycles_per_bit(), 168);
}
