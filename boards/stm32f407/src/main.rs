//! The mecanum drive firmware on an STM32F407 (DJI RoboMaster development board type C).
//!
//! One embassy task runs the [`firmware`] control core at 1 kHz on CAN1:
//!
//! ```text
//! CAN1 RX FIFO 0 ──(RX0 interrupt wakes the task)──► on_frame(arrival time, frame)
//! TIM2 (embassy-time, 1 MHz) ──(1 kHz Ticker)──► drain FIFO 0 ─► step(now) ─► outbox
//! outbox ─► TX queue (29 frames, stamped) ─► TX task ─(a mailbox free; stale dropped)─►
//!           3 TX mailboxes (FIFO order) ─► CAN1
//! ```
//!
//! Saved parameters live in flash sectors 1 and 2 (`firmware::storage`): read at boot, the
//! stale sector erased before the watchdog starts, a save programmed a few words before each
//! step (never an erase while the loop runs).
//!
//! See the README for the pins, clocks, bounds and how to flash it.

#![no_std]
#![no_main]

mod clocks;
mod counters;

use core::num::{NonZeroU8, NonZeroU16};
use core::sync::atomic::{AtomicU32, Ordering};

use defmt::{info, warn};
use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_futures::select::{Either, select};
use embassy_stm32::bind_interrupts;
use embassy_stm32::can::enums::TryReadError;
use embassy_stm32::can::filter::Mask32;
use embassy_stm32::can::util::NominalBitTiming;
use embassy_stm32::can::{
    Can, CanRx, CanTx, Fifo, Mailbox, Rx0InterruptHandler, Rx1InterruptHandler,
    SceInterruptHandler, StandardId, TxInterruptHandler,
};
use embassy_stm32::flash::{Blocking, Flash};
use embassy_stm32::peripherals::CAN1;
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_time::{Duration, Ticker, Timer};
use firmware::protocol::robot::{Fault, RobotState};
use firmware::storage::{self, F407_LAYOUT, Store};
use firmware::{Config, Controller, Instant};
use panic_probe as _;

use crate::counters::Counters;

bind_interrupts!(struct Irqs {
    CAN1_RX0 => Rx0InterruptHandler<CAN1>;
    CAN1_RX1 => Rx1InterruptHandler<CAN1>;
    CAN1_SCE => SceInterruptHandler<CAN1>;
    CAN1_TX => TxInterruptHandler<CAN1>;
});

/// Frames waiting for a TX mailbox. One step emits at most
/// [`firmware::control::OUTBOX_CAPACITY`] (25) frames, so a whole outbox fits even when the
/// three mailboxes are still busy with the previous step's frames, with room for a few more.
const TX_QUEUE_LEN: usize = firmware::control::OUTBOX_CAPACITY + 4;

/// The outbox frames waiting for a mailbox, each with the time its step queued it.
static TX_QUEUE: Channel<
    CriticalSectionRawMutex,
    (Instant, embassy_stm32::can::Frame),
    TX_QUEUE_LEN,
> = Channel::new();

/// Frames the TX task dropped as stale (see [`transmit`]), for the report.
static TX_STALE: AtomicU32 = AtomicU32::new(0);

/// A frame still waiting for a mailbox this many control periods after its step is stale:
/// the bus was unavailable (unplugged, bus-off), and a motor command from before that must
/// not reach the drives when it is back. A healthy bus at its busiest (a STATUS step's
/// burst on a bus 65 % loaded by 1 kHz DJI traffic) sends a step's frames within 1.3 ms.
const TX_MAX_AGE_PERIODS: u64 = 3;

/// Log the counters once per this many steps (1 s at 1 kHz).
const REPORT_EVERY_STEPS: u64 = 1000;

/// The independent watchdog's period: a control loop that has not stepped for this long
/// (50 periods) resets the board, which then starts disabled (the core's initial state).
const WATCHDOG_TIMEOUT_US: u32 = 50_000;

/// CAN bit timing for 1 Mbit/s from the 42 MHz APB1 clock: 42 MHz / 3 = 14 MHz time quanta,
/// 1 + 10 + 3 = 14 quanta per bit, sample point at 11/14 = 78.6 %, SJW 1. The same values as
/// DJI's own examples for this board (CubeMX `MX_CAN1_Init`: prescaler 3, BS1 10 tq, BS2 3 tq).
fn bit_timing_1mbit() -> NominalBitTiming {
    const PRESCALER: NonZeroU16 = NonZeroU16::new(3).unwrap();
    const BS1: NonZeroU8 = NonZeroU8::new(10).unwrap();
    const BS2: NonZeroU8 = NonZeroU8::new(3).unwrap();
    const SJW: NonZeroU8 = NonZeroU8::new(1).unwrap();
    NominalBitTiming {
        prescaler: PRESCALER,
        seg1: BS1,
        seg2: BS2,
        sync_jump_width: SJW,
    }
}

/// The core's clock: the embassy-time driver on TIM2 at 1 MHz. The driver extends the 16-bit
/// counter with a 32-bit count of half-overflows (an interrupt every 32.768 ms), giving 64-bit
/// microseconds that are read race-free and wrap only after 2^47 µs (4.4 years of uptime).
fn now() -> Instant {
    Instant::from_micros(embassy_time::Instant::now().as_micros())
}

/// The core's time for a frame's arrival stamp (taken in the RX path when the frame left the
/// hardware FIFO).
fn instant_of(ts: embassy_time::Instant) -> Instant {
    Instant::from_micros(ts.as_micros())
}

/// The drive configuration the build read from `MECANUM_CONFIG` (see `build.rs`), encoded.
static CONFIG: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/config.bin"));

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let p = embassy_stm32::init(clocks::config());
    info!("board-stm32f407: SYSCLK 168 MHz, APB1 42 MHz, CAN1 1 Mbit/s on PD0/PD1");
    // RCC_CSR keeps the cause of the last reset until RMVF clears it.
    let csr = embassy_stm32::pac::RCC.csr().read();
    if csr.wdgrstf() {
        warn!("reset by the independent watchdog: the control loop had stalled");
    }
    embassy_stm32::pac::RCC.csr().modify(|w| w.set_rmvf(true));

    // Validated when the image was built; decoded and validated again here, so that an image
    // whose firmware crate disagrees with its build script stops with the reason.
    let builtin = match Config::decode(CONFIG) {
        Ok(c) => c,
        Err(e) => config_rejected(&e),
    };
    let mut flash = Flash::new_blocking(p.FLASH);
    let (mut store, mut ctl) = boot_parameters(&mut flash, &builtin);
    let period = ctl.period_micros();
    info!(
        "drive configuration {=str}, id {=u16:#06x}",
        env!("MECANUM_CONFIG_NAME"),
        ctl.builtin_id()
    );

    // CAN1: RX on PD0, TX on PD1 (AF9), as wired on the type C board's CAN1 connector.
    let mut can = Can::new(p.CAN1, p.PD0, p.PD1, Irqs);
    // Bank 0: every standard-id frame (data or remote) into FIFO 0; extended ids are dropped by
    // the hardware, none of the three protocols uses them.
    can.modify_filters().enable_bank(
        0,
        Fifo::Fifo0,
        Mask32::frames_with_std_id(StandardId::ZERO, StandardId::ZERO),
    );
    // Automatic retransmission stays on (MCR.NART = 0 after reset). Not through
    // `set_automatic_retransmit`: in embassy-stm32 0.6.0 `set_automatic_retransmit(true)`
    // *sets* NART (upstream issue #5944), and every frame that lost arbitration or met an
    // error would be sent once and lost. The check after `enable` holds it.
    can.modify_config()
        .set_bit_timing(bit_timing_1mbit())
        .set_loopback(false)
        .set_silent(false);
    // Send in the order the core emitted the frames, not by id priority.
    can.set_tx_fifo_scheduling(true);
    can.enable().await;
    defmt::assert!(
        !embassy_stm32::pac::CAN1.mcr().read().nart(),
        "CAN1: automatic retransmission is off (MCR.NART set)"
    );
    info!("CAN1 enabled (bus idle seen)");

    let (tx, mut rx) = can.split();
    match transmit(tx, TX_MAX_AGE_PERIODS * period) {
        Ok(task) => spawner.spawn(task),
        // One task, spawned once: its pool of one has room.
        Err(_) => defmt::panic!("the TX task could not be spawned"),
    }

    let mut counters = Counters::default();
    // The core boots disabled without a fault.
    let mut last_shown = (ctl.state(), ctl.fault());
    let mut ticker = Ticker::every(Duration::from_micros(period));
    // Started once the loop starts: only a step feeds it (frames arriving do not).
    let mut watchdog = IndependentWatchdog::new(p.IWDG, WATCHDOG_TIMEOUT_US);
    watchdog.unleash();
    info!(
        "control loop: {} us period; independent watchdog {} us",
        period, WATCHDOG_TIMEOUT_US
    );

    loop {
        // Before any read: reading a frame releases it with a read-modify-write of RF0R, which
        // writes back the overrun flag it read and so clears it.
        counters.check_fifo_overrun();
        match select(ticker.next(), rx.read()).await {
            Either::First(()) => {
                // Frames that arrived since the task last ran go in before the step.
                drain_fifo(&mut rx, &mut ctl, &mut counters);
                // A save asked for at the last step: a few words now (at most 300 µs of
                // stalled CPU), its end given to the core before this step.
                store.serve(&mut ctl, &mut flash, storage::WORDS_PER_STEP);
                let now = now();
                let outbox = ctl.step(now);
                for frame in &outbox {
                    let queued = frame
                        .convert::<embassy_stm32::can::Frame>()
                        .is_some_and(|f| TX_QUEUE.try_send((now, f)).is_ok());
                    counters.tx(queued);
                }
                log_state_change(&ctl, &mut last_shown, counters.steps);
                counters.steps += 1;
                watchdog.pet();
                if counters.steps.is_multiple_of(REPORT_EVERY_STEPS) {
                    report(&ctl, &counters);
                }
            }
            Either::Second(Ok(envelope)) => {
                let (frame, ts) = envelope.parts();
                ctl.on_frame(instant_of(ts), &frame);
                counters.rx();
            }
            Either::Second(Err(e)) => {
                counters.bus_error();
                if counters.bus_errors.is_power_of_two() {
                    warn!(
                        "CAN bus error {} (total {})",
                        defmt::Debug2Format(&e),
                        counters.bus_errors
                    );
                }
            }
        }
    }
}

/// The saved parameters at boot: the newest set saved for this image's configuration, if any,
/// and the controller running it; the sector that holds none of it erased now, while nothing
/// watches the loop (an erase stops the CPU for 400-800 ms at embassy's PSIZE x8).
fn boot_parameters(flash: &mut Flash<'_, Blocking>, builtin: &Config) -> (Store, Controller) {
    let (mut store, found) = match Store::mount(flash, F407_LAYOUT, builtin) {
        Ok(mounted) => mounted,
        Err(e) => defmt::panic!("parameter flash unreadable: {}", defmt::Debug2Format(&e)),
    };
    if found.foreign > 0 || found.garbage > 0 {
        info!(
            "parameter flash: {=u32} records for another configuration, {=u32} cut short",
            found.foreign, found.garbage
        );
    }
    if let Err(e) = store.erase_stale(flash) {
        warn!(
            "parameter flash: a stale sector could not be erased ({}): saves that need it are refused",
            defmt::Debug2Format(&e)
        );
    }
    let booted = Controller::new(builtin).and_then(|ctl| match found.saved {
        Some(saved) => ctl.with_saved(&saved.config, saved.seq),
        None => Ok(ctl),
    });
    let ctl = match booted {
        Ok(ctl) => ctl,
        Err(e) => config_rejected(&e),
    };
    match found.saved {
        Some(saved) => info!(
            "parameters: the saved set, record {=u32}, id {=u16:#06x}",
            saved.seq,
            ctl.config_id()
        ),
        None => info!("parameters: the built-in set"),
    }
    (store, ctl)
}

/// Stops the board on a configuration the core refuses. Fields logged one by one: defmt
/// formats the f64 on the host, so no float formatting code goes into flash.
fn config_rejected(e: &firmware::config::ConfigError) -> ! {
    defmt::panic!(
        "configuration rejected: {=str} = {=f64}: {=str}",
        e.field,
        e.value,
        e.expected
    )
}

/// Moves the queued frames into the mailboxes, oldest first, as each mailbox frees. A frame
/// that has no mailbox `max_age_us` after its step is stale: it is dropped, and so are the
/// frames in the mailboxes, which are older still (a bus outage: unplugged, bus-off). So when
/// the bus is back the drives get the loop's current commands, not the ones it made before.
#[embassy_executor::task]
async fn transmit(mut tx: CanTx<'static>, max_age_us: u64) {
    loop {
        let (queued, frame) = TX_QUEUE.receive().await;
        let deadline = embassy_time::Instant::from_micros(queued.as_micros() + max_age_us);
        let free = select(tx.flush_any(), Timer::at(deadline)).await;
        if matches!(free, Either::Second(())) || embassy_time::Instant::now() > deadline {
            let mut stale = 1;
            for mailbox in [Mailbox::Mailbox0, Mailbox::Mailbox1, Mailbox::Mailbox2] {
                stale += u32::from(tx.abort(mailbox));
            }
            TX_STALE.fetch_add(stale, Ordering::Relaxed);
            continue;
        }
        // A mailbox is free (and nothing else writes them): this cannot fail.
        let _ = tx.try_write(&frame);
    }
}

/// Hands every frame still in RX FIFO 0 to the core, in arrival order, checking the overrun
/// flag before each read (a read clears it).
fn drain_fifo(rx: &mut CanRx<'_>, ctl: &mut Controller, counters: &mut Counters) {
    loop {
        counters.check_fifo_overrun();
        match rx.try_read() {
            Ok(envelope) => {
                let (frame, ts) = envelope.parts();
                ctl.on_frame(instant_of(ts), &frame);
                counters.rx();
            }
            Err(TryReadError::BusError(_)) => counters.bus_error(),
            Err(TryReadError::Empty) => break,
        }
    }
}

/// Logs each change of the core's state or fault with the step that made it (`step` counts
/// from 0): STATUS shows it only at its next frame, up to 100 ms later, and boardsim reads
/// these lines to compare the image's state changes with the in-process core's, step for step.
fn log_state_change(ctl: &Controller, last: &mut (RobotState, Fault), step: u64) {
    let shown = (ctl.state(), ctl.fault());
    if shown != *last {
        info!(
            "step {=u64}: state {=u8} fault {=u8}",
            step,
            shown.0.raw(),
            shown.1.raw()
        );
        *last = shown;
    }
}

/// Logs the loop's counters and the core's state (once per second).
fn report(ctl: &Controller, c: &Counters) {
    let s = ctl.snapshot();
    info!(
        // State and fault as their protocol codes (dbc/, STATUS frame); the legend costs no
        // flash, defmt keeps format strings on the host.
        "steps {} state {=u8} (0 disabled 1 enabled 2 fault 3 e-stop) fault {=u8} (0 none 1 motor stale 2 motor missing 3 drive error 4 watchdog 5 config 6 encoder stuck) motors {=u8:04b} | rx {} rejected {} overruns {} bus errors {} | tx {} dropped {} stale {}",
        s.steps,
        s.state as u8,
        s.fault as u8,
        s.motors_online,
        c.rx_frames,
        s.rx_errors.total(),
        c.rx_overruns,
        c.bus_errors,
        c.tx_queued,
        c.tx_dropped,
        TX_STALE.load(Ordering::Relaxed),
    );
}
