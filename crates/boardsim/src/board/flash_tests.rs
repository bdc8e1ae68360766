//! The flash on the board: tiny Thumb programs (assembled with `llvm-mc`, listed beside them)
//! program and erase it as embassy-stm32's F4 driver does, and the tests read the bytes, the
//! registers and the clock.

use std::collections::HashMap;

use unicorn_engine::RegisterARM;

use super::Board;
use crate::elf::Image;
use crate::flash::{self, FlashOp, Operation, Sector, Timing, reg, sr};

/// An image of `code` (Thumb halfwords, literal pool included) at 0x0800_0008 after a vector
/// table whose reset vector points at it, and the segments `data`.
fn image(code: &[u16], data: &[(u32, Vec<u8>)]) -> Image {
    let mut flash: Vec<u8> = [0x2000_1000u32, 0x0800_0009]
        .iter()
        .flat_map(|w| w.to_le_bytes())
        .collect();
    flash.extend(code.iter().flat_map(|h| h.to_le_bytes()));
    let mut segments = vec![(flash::BASE, flash)];
    segments.extend(data.iter().cloned());
    Image {
        path: "test.elf".into(),
        bytes: Vec::new(),
        segments,
        symbols: HashMap::new(),
        hints: HashMap::new(),
    }
}

/// The word at `addr` (in 0x0800_0000..) of a flash image.
fn word(flash: &[u8], addr: u32) -> u32 {
    let at = (addr - flash::BASE) as usize;
    u32::from_le_bytes(flash[at..at + 4].try_into().unwrap())
}

/// Runs the board until a flash operation is in flight.
fn run_to_op(board: &mut Board) -> FlashOp {
    for _ in 0..1000 {
        if let Some(op) = board.flash().op() {
            return *op;
        }
        board.run_until(board.now() + 100).unwrap();
    }
    panic!("no flash operation started");
}

/// Cycles per ms.
const MS: u64 = super::CPU_HZ / 1000;

/// Unlock, PSIZE x32 + PG, program 0x0000_FFFF at 0x0800_4000, wait on BSY, read it back
/// (r5) and through the boot alias (r6), lock:
/// ```text
///     ldr r0, =0x40023C00      ; FLASH
///     ldr r1, =0x45670123
///     str r1, [r0, #4]         ; KEYR
///     ldr r1, =0xCDEF89AB
///     str r1, [r0, #4]
///     movw r1, #0x201          ; PSIZE x32 | PG
///     str r1, [r0, #0x10]      ; CR
///     ldr r2, =0x08004000
///     movw r3, #0xFFFF
///     str r3, [r2]
/// 1:  ldr r4, [r0, #0xC]       ; SR
///     tst r4, #0x10000         ; BSY
///     bne 1b
///     ldr r5, [r2]
///     mov.w r6, #0x4000
///     ldr r6, [r6]
///     mov r1, #0x80000000      ; LOCK
///     str r1, [r0, #0x10]
/// 2:  b 2b
/// ```
const PROGRAM: [u16; 32] = [
    0x480B, 0x490C, 0x6041, 0x490C, 0x6041, 0xF240, 0x2101, 0x6101, 0x4A0A, 0xF64F, 0x73FF, 0x6013,
    0x68C4, 0xF414, 0x3F80, 0xD1FB, 0x6815, 0xF44F, 0x4680, 0x6836, 0xF04F, 0x4100, 0x6101, 0xE7FE,
    0x3C00, 0x4002, 0x0123, 0x4567, 0x89AB, 0xCDEF, 0x4000, 0x0800,
];

/// Unlock, SER + SNB 1 + PSIZE x32, then STRT, wait on BSY, r7 = 1:
/// ```text
///     ldr r0, =0x40023C00
///     ldr r1, =0x45670123
///     str r1, [r0, #4]
///     ldr r1, =0xCDEF89AB
///     str r1, [r0, #4]
///     movw r1, #0x20A          ; PSIZE x32 | SNB 1 | SER
///     str r1, [r0, #0x10]
///     orr r1, r1, #0x10000     ; STRT
///     str r1, [r0, #0x10]
/// 1:  ldr r4, [r0, #0xC]
///     tst r4, #0x10000
///     bne 1b
///     movs r7, #1
/// 2:  b 2b
/// ```
const ERASE: [u16; 24] = [
    0x4808, 0x4909, 0x6041, 0x4909, 0x6041, 0xF240, 0x210A, 0x6101, 0xF441, 0x3180, 0x6101, 0x68C4,
    0xF414, 0x3F80, 0xD1FB, 0x2701, 0xE7FE, 0x0000, 0x3C00, 0x4002, 0x0123, 0x4567, 0x89AB, 0xCDEF,
];

/// Sector 1 all zeros, and words either side of it.
fn sector_1_programmed() -> Vec<(u32, Vec<u8>)> {
    vec![
        (0x0800_4000, vec![0; 0x4000]),
        (0x0800_8000, 0x1234_5678u32.to_le_bytes().to_vec()),
        (0x0800_3FFC, 0xA5A5_A5A5u32.to_le_bytes().to_vec()),
    ]
}

#[test]
fn a_word_programs_as_old_and_value_in_both_copies_after_16_us() {
    let data = [(0x0800_4000, 0xFFFF_00FFu32.to_le_bytes().to_vec())];
    let mut board = Board::new(image(&PROGRAM, &data)).unwrap();
    let op = run_to_op(&mut board);
    let value = 0xFFFF;
    let program = Operation::Program {
        addr: 0x0800_4000,
        size: 4,
        value,
    };
    assert_eq!(op.operation, program);
    assert_eq!(op.end - op.start, 16 * 168, "16 µs at 168 MHz");
    assert_eq!(board.flash().read(reg::SR), Some(sr::BSY));
    // In flight: the bytes are the old ones, the CPU waits at its next fetch from the flash.
    assert_eq!(word(&board.flash_image(), 0x0800_4000), 0xFFFF_00FF);
    let executed = board.stats().instructions;
    board.run_until(op.end - 1).unwrap();
    assert_eq!(board.stats().instructions, executed, "stalled");
    board.run_until(op.end + 1000).unwrap();
    assert!(board.flash().op().is_none());
    // 0x0000_FFFF AND 0xFFFF_00FF. Had Unicorn let the CPU's own write through (the hook
    // claims it), the word would read 0x0000_FFFF.
    assert_eq!(word(&board.flash_image(), 0x0800_4000), 0x0000_00FF);
    assert_eq!(board.reg(RegisterARM::R5), 0x0000_00FF);
    assert_eq!(board.reg(RegisterARM::R6), 0x0000_00FF, "the boot alias");
    assert_eq!(board.stats().flash_stall_cycles, 16 * 168);
    assert_eq!(board.flash().read(reg::SR), Some(0));
    assert_eq!(
        board.flash().read(reg::CR),
        Some(0x8000_0000),
        "locked again"
    );

    let mut board = Board::new(image(&PROGRAM, &data)).unwrap();
    board.set_flash_timing(Timing::Maximum);
    let op = run_to_op(&mut board);
    assert_eq!(op.end - op.start, 100 * 168, "100 µs");
}

#[test]
fn refused_writes_set_their_flag_change_nothing_and_do_not_stop_the_board() {
    // ```text
    //     ldr r0, =0x40023C00
    //     ldr r2, =0x08004000
    //     movs r3, #0
    //     str r3, [r2]             ; locked: PGSERR
    //     ldr r7, [r0, #0xC]
    //     str r7, [r0, #0xC]       ; clear it
    //     ldr r1, =0x45670123
    //     str r1, [r0, #4]
    //     ldr r1, =0xCDEF89AB
    //     str r1, [r0, #4]
    //     movw r1, #0x201          ; PSIZE x32 | PG
    //     str r1, [r0, #0x10]
    //     strh r3, [r2]            ; a half-word: PGPERR
    //     str.w r3, [r2, #2]       ; misaligned: PGAERR
    //     ldr r6, [r0, #0xC]
    //     ldr r5, [r2]
    // 2:  b 2b
    // ```
    let code = [
        0x4809, 0x4A0A, 0x2300, 0x6013, 0x68C7, 0x60C7, 0x4908, 0x6041, 0x4908, 0x6041, 0xF240,
        0x2101, 0x6101, 0x8013, 0xF8C2, 0x3002, 0x68C6, 0x6815, 0xE7FE, 0x0000, 0x3C00, 0x4002,
        0x4000, 0x0800, 0x0123, 0x4567, 0x89AB, 0xCDEF,
    ];
    let data = [(0x0800_4000, 0xFFFF_00FFu32.to_le_bytes().to_vec())];
    let mut board = Board::new(image(&code, &data)).unwrap();
    board.run_until(10_000).unwrap();
    assert_eq!(board.reg(RegisterARM::R7), sr::PGSERR);
    assert_eq!(board.reg(RegisterARM::R6), sr::PGPERR | sr::PGAERR);
    assert_eq!(board.reg(RegisterARM::R5), 0xFFFF_00FF);
    assert_eq!(word(&board.flash_image(), 0x0800_4000), 0xFFFF_00FF);
    assert_eq!(word(&board.flash_image(), 0x0800_4004), 0xFFFF_FFFF);
    assert!(board.flash().op().is_none());
    assert_eq!(board.stats().flash_stall_cycles, 0);
}

#[test]
fn a_sector_erase_is_busy_250_ms_and_the_next_fetch_waits_for_its_end() {
    let mut board = Board::new(image(&ERASE, &sector_1_programmed())).unwrap();
    let op = run_to_op(&mut board);
    assert_eq!(op.operation, Operation::Erase(Sector::new(1).unwrap()));
    assert_eq!(op.end - op.start, 250 * MS, "16 KiB at x32, typical");
    let executed = board.stats().instructions;
    board.run_until(op.start + 125 * MS).unwrap();
    assert_eq!(board.flash().read(reg::SR), Some(sr::BSY));
    assert_eq!(board.stats().instructions, executed, "stalled");
    assert!(board.flash_image()[0x4000..0x8000].iter().all(|&b| b == 0));
    board.run_until(op.end + 1000).unwrap();
    assert!(board.flash().op().is_none());
    // The loop's first fetch after STRT waited the whole erase, and then ran on.
    assert_eq!(board.stats().flash_stall_cycles, 250 * MS);
    assert_eq!(board.reg(RegisterARM::R7), 1);
    let image = board.flash_image();
    assert!(image[0x4000..0x8000].iter().all(|&b| b == 0xFF));
    assert_eq!(word(&image, 0x0800_3FFC), 0xA5A5_A5A5, "sector 0 kept");
    assert_eq!(word(&image, 0x0800_8000), 0x1234_5678, "sector 2 kept");
    let alias = board.uc.mem_read_as_vec(0x4000, 0x4000).unwrap();
    assert!(alias.iter().all(|&b| b == 0xFF), "the boot alias");
}

#[test]
fn a_data_read_of_the_flash_during_an_erase_waits_and_runs_again() {
    // ERASE with a load from the flash right after STRT, in the same translated block:
    // ```text
    //     ldr r0, =0x40023C00
    //     ldr r1, =0x45670123
    //     str r1, [r0, #4]
    //     ldr r1, =0xCDEF89AB
    //     str r1, [r0, #4]
    //     ldr r2, =0x08008000
    //     movw r1, #0x20A
    //     str r1, [r0, #0x10]
    //     orr r1, r1, #0x10000
    //     str r1, [r0, #0x10]      ; STRT
    //     ldr r5, [r2]             ; stalls
    //     ldr r4, [r0, #0xC]       ; SR
    //     movs r7, #1
    // 2:  b 2b
    // ```
    let code = [
        0x4807, 0x4908, 0x6041, 0x4908, 0x6041, 0x4A08, 0xF240, 0x210A, 0x6101, 0xF441, 0x3180,
        0x6101, 0x6815, 0x68C4, 0x2701, 0xE7FE, 0x3C00, 0x4002, 0x0123, 0x4567, 0x89AB, 0xCDEF,
        0x8000, 0x0800,
    ];
    let mut board = Board::new(image(&code, &sector_1_programmed())).unwrap();
    let op = run_to_op(&mut board);
    board.run_until(op.end + 1000).unwrap();
    assert_eq!(board.stats().flash_stall_cycles, 250 * MS);
    assert_eq!(board.reg(RegisterARM::R5), 0x1234_5678);
    assert_eq!(board.reg(RegisterARM::R4), 0, "not busy once the load ran");
    assert_eq!(board.reg(RegisterARM::R7), 1);
    assert!(
        board.flash_image()[0x4000..0x8000]
            .iter()
            .all(|&b| b == 0xFF)
    );
}

#[test]
fn the_watchdog_resets_the_chip_during_an_erase_and_the_erase_is_lost() {
    // The IWDG started at 50 ms (unlock, PR /4, RLR 399, start), then ERASE:
    // ```text
    //     ldr r0, =0x40003000      ; IWDG
    //     movw r1, #0x5555
    //     str r1, [r0]
    //     movs r1, #0
    //     str r1, [r0, #4]
    //     movw r1, #399
    //     str r1, [r0, #8]
    //     movw r1, #0xCCCC
    //     str r1, [r0]
    //     (ERASE without r7)
    // ```
    let code = [
        0x480D, 0xF245, 0x5155, 0x6001, 0x2100, 0x6041, 0xF240, 0x118F, 0x6081, 0xF64C, 0x41CC,
        0x6001, 0x4808, 0x4909, 0x6041, 0x4909, 0x6041, 0xF240, 0x210A, 0x6101, 0xF441, 0x3180,
        0x6101, 0x68C4, 0xF414, 0x3F80, 0xD1FB, 0xE7FE, 0x3000, 0x4000, 0x3C00, 0x4002, 0x0123,
        0x4567, 0x89AB, 0xCDEF,
    ];
    let mut board = Board::new(image(&code, &sector_1_programmed())).unwrap();
    let first = run_to_op(&mut board);
    board.run_until(first.start + 60 * MS).unwrap();
    let stats = board.stats();
    assert_eq!(stats.watchdog_resets, 1);
    assert_eq!(stats.flash_ops_interrupted, 1);
    assert!(board.flash_image()[0x4000..0x8000].iter().all(|&b| b == 0));
    // Rebooted, the program started the erase again.
    let again = board.flash().op().unwrap();
    assert!(again.start > first.start + 50 * MS, "{again:?}");
}

#[test]
fn the_flash_is_erased_around_the_image_kept_across_resets_and_taken_out_and_back() {
    let mut board = Board::new(image(&PROGRAM, &[])).unwrap();
    let erased = board.flash_image();
    assert_eq!(erased.len(), flash::SIZE as usize);
    assert!(erased[0x100..].iter().all(|&b| b == 0xFF));
    let alias = board.uc.mem_read_as_vec(0x100, 0x100).unwrap();
    assert!(alias.iter().all(|&b| b == 0xFF));
    board.run_until(10_000).unwrap();
    assert_eq!(word(&board.flash_image(), 0x0800_4000), 0x0000_FFFF);
    board.reset().unwrap();
    let flash = board.flash_image();
    assert_eq!(
        word(&flash, 0x0800_4000),
        0x0000_FFFF,
        "kept across a reset"
    );

    // Another image, whose own flash segment says 0 there: the flash image is what loads.
    let other = image(&[0xE7FE], &[(0x0800_4000, vec![0; 4])]);
    let board = Board::with_flash_image(other.clone(), &flash).unwrap();
    assert!(board.flash_image() == flash);
    let alias = board.uc.mem_read_as_vec(0x4000, 4).unwrap();
    assert_eq!(alias, [0xFF, 0xFF, 0, 0]);
    let e = Board::with_flash_image(other, &[0xFF; 16]).unwrap_err();
    assert!(e.to_string().contains("16 bytes"), "{e}");
}
