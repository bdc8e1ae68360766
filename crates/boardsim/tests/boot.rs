//! The flashed image boots: clocks, CAN1, the 1 kHz loop, its log lines and its frames, with
//! hostsim's simulated C620 ESCs answering on the bus; twice the same, bit for bit.

use boardsim::CPU_HZ;
use boardsim::rtt::LogLine;
use boardsim::run::{BoardRun, Harness};
use embedded_can::Frame;
use hostsim::scenario::Scenario;

mod common;
use common::board_run;

/// The image alone with the example robot's four C620s answering: no host acts.
fn boot(seconds: f64) -> BoardRun {
    let s = Scenario::from_toml(
        &format!("duration_s = {seconds}"),
        std::path::Path::new("boot.toml"),
    );
    board_run(&s.unwrap(), Harness::default())
}

fn seconds(cycles: u64) -> f64 {
    cycles as f64 / CPU_HZ as f64
}

#[test]
fn the_flashed_image_boots_to_its_1_khz_loop() {
    let run = boot(2.05);
    for l in &run.lines {
        eprintln!("{:.6} {} {}", seconds(l.at), l.level, l.text);
    }
    let find = |text: &str| {
        run.lines
            .iter()
            .find(|l| l.text.contains(text))
            .unwrap_or_else(|| panic!("no log line with {text:?}"))
    };
    find("board-stm32f407: SYSCLK 168 MHz, APB1 42 MHz, CAN1 1 Mbit/s on PD0/PD1");
    // The configuration the image was built with (the default: config/dji_m3508.toml).
    find(&format!(
        "drive configuration dji_m3508.toml, id {:#06x}",
        firmware::Config::dji_m3508_example().id()
    ));
    find("CAN1 enabled (bus idle seen)");
    let looping = find("control loop: 1000 us period");
    assert!(
        seconds(looping.at) < 0.01,
        "boot took {} s",
        seconds(looping.at)
    );
    assert!(
        run.lines
            .iter()
            .all(|l| l.level != "error" && l.level != "warn")
    );

    // The clock tree the image programmed, and CAN1's bit time.
    let c = run.board.rcc().clocks();
    assert_eq!(
        (c.sysclk, c.pclk1, c.tim_apb1),
        (168_000_000, 42_000_000, 84_000_000)
    );
    assert_eq!(run.board.can1().cycles_per_bit(), 168, "1 Mbit/s");
    let unknown: Vec<String> = run
        .board
        .unknown_registers()
        .iter()
        .map(|u| u.to_string())
        .collect();
    assert!(unknown.is_empty(), "{unknown:#?}");

    // The once-a-second counters: 1000 and 2000 steps, a second apart, motors all online.
    let reports: Vec<&LogLine> = run
        .lines
        .iter()
        .filter(|l| l.text.starts_with("steps "))
        .collect();
    assert_eq!(reports.len(), 2, "{reports:#?}");
    assert!(
        reports[0].text.starts_with("steps 1000 state 0 "),
        "{}",
        reports[0].text
    );
    assert!(reports[0].text.contains("fault 0 "), "{}", reports[0].text);
    assert!(
        reports[0].text.contains("motors 1111"),
        "{}",
        reports[0].text
    );
    assert!(
        reports[1].text.starts_with("steps 2000 "),
        "{}",
        reports[1].text
    );
    assert!(
        reports[1].text.contains("overruns 0 ") && reports[1].text.ends_with("dropped 0 stale 0"),
        "{}",
        reports[1].text
    );
    let apart = seconds(reports[1].at - reports[0].at);
    assert!((apart - 1.0).abs() < 1e-3, "{apart} s between the reports");

    // On the bus: the motor command 0x200 at 1 kHz, odometry 0x310/0x311 at 100 Hz, STATUS
    // 0x312 and HEARTBEAT 0x31F at 10 Hz, in the second after the first report.
    let (t0, t1) = (seconds(reports[0].at), seconds(reports[0].at) + 1.0);
    let count = |id: u16| {
        run.sent
            .iter()
            .filter(|(t, f)| {
                f.id() == embedded_can::Id::Standard(embedded_can::StandardId::new(id).unwrap())
                    && (t0..t1).contains(&(*t as f64 * 1e-9))
            })
            .count()
    };
    assert!(
        (999..=1001).contains(&count(0x200)),
        "0x200: {}",
        count(0x200)
    );
    assert!(
        (99..=101).contains(&count(0x310)),
        "0x310: {}",
        count(0x310)
    );
    assert!(
        (99..=101).contains(&count(0x311)),
        "0x311: {}",
        count(0x311)
    );
    assert!((9..=11).contains(&count(0x312)), "0x312: {}", count(0x312));
    assert!((9..=11).contains(&count(0x31F)), "0x31f: {}", count(0x31F));
    let s = run.board.stats();
    eprintln!(
        "{} instructions, {} slices, {} exceptions, {} MMIO, asleep {:.1} %",
        s.instructions,
        s.slices,
        s.exceptions,
        s.mmio,
        100.0 * s.sleep_cycles as f64 / run.board.now() as f64
    );
}

#[test]
fn the_same_run_twice_is_the_same_bit_for_bit() {
    let (a, b) = (boot(0.3), boot(0.3));
    assert_eq!(a.lines, b.lines);
    // Every frame on the bus, all senders, at the same ns; the board's frames listed.
    assert_eq!(a.bus_hash, b.bus_hash);
    assert_eq!(a.sent, b.sent);
    assert_eq!(a.frames_received, b.frames_received);
    assert_eq!(a.board.stats(), b.board.stats());
    let frames = a.sent.len() as u64 + a.frames_received;
    assert!(frames > 1000, "{frames} frames");
}

/// The same scenario twice writes the same log, byte for byte: a host that enables, drives,
/// and e-stops, with the board's log lines on `/rosout` and every frame.
#[test]
fn the_same_scenario_twice_writes_the_same_log() {
    let s = Scenario::from_toml(
        "duration_s = 0.6\n[[actions]]\nat_s = 0.05\nenable = true\n[[actions]]\nat_s = 0.1\n\
         twist = [0.5, 0.2, 0.3]\n[[actions]]\nat_s = 0.4\nestop = true\n",
        std::path::Path::new("determinism.toml"),
    )
    .unwrap();
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("boardsim-determinism");
    std::fs::create_dir_all(&dir).unwrap();
    let image = boardsim::Image::read(&common::elf()).unwrap();
    let logs: Vec<Vec<u8>> = ["a", "b"]
        .iter()
        .map(|name| {
            let path = dir.join(format!("{name}.mcap"));
            let mut log =
                drivelog::McapLog::create(&path, &boardsim::run::run_metadata(&s, &image)).unwrap();
            let board = boardsim::Board::new(image.clone()).unwrap();
            boardsim::run::run_scenario(
                &s,
                board,
                Some(&mut log),
                hostsim::engine::LogOptions::default(),
                Harness::default(),
                |_| {},
            )
            .unwrap();
            log.finish().unwrap();
            std::fs::read(&path).unwrap()
        })
        .collect();
    eprintln!("two logs of {} and {} bytes", logs[0].len(), logs[1].len());
    assert!(logs[0].len() > 50_000, "{} bytes", logs[0].len());
    assert!(logs[0] == logs[1], "the logs differ");
}
