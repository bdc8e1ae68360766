//! The firmware control core and the fixed scenario of `xtarget_scenario` on an emulated
//! Cortex-M4 (QEMU `mps2-an386`): prints the scenario's report through semihosting and exits
//! with the result, so that `scripts/xtarget.sh` can compare it with the host's report.
//!
//! With feature `icount` it runs a short window instead (see [`icount`]): the control core's
//! work in steps 100..200 of each setup sits between calls to marker functions whose names
//! QEMU's execution trace shows, so the trace's lines between them count the instructions.

#![no_std]
#![no_main]

use core::fmt::{self, Write};
use core::panic::PanicInfo;

use cortex_m_rt::entry;
use cortex_m_semihosting::debug::{self, EXIT_FAILURE, EXIT_SUCCESS};
use cortex_m_semihosting::hio::{self, HostStream};

/// Buffers a line and writes it with one semihosting call (each call traps into QEMU).
struct LineWriter {
    host: HostStream,
    buf: [u8; 160],
    len: usize,
}

impl LineWriter {
    fn new(host: HostStream) -> Self {
        Self {
            host,
            buf: [0; 160],
            len: 0,
        }
    }

    fn flush(&mut self) -> fmt::Result {
        let line = self.buf.get(..self.len).ok_or(fmt::Error)?;
        self.host.write_all(line).map_err(|()| fmt::Error)?;
        self.len = 0;
        Ok(())
    }
}

impl Write for LineWriter {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        for &b in s.as_bytes() {
            if self.len == self.buf.len() {
                self.flush()?;
            }
            if let Some(slot) = self.buf.get_mut(self.len) {
                *slot = b;
                self.len += 1;
            }
            if b == b'\n' {
                self.flush()?;
            }
        }
        Ok(())
    }
}

#[entry]
fn main() -> ! {
    let Ok(host) = hio::hstdout() else {
        exit(false)
    };
    let mut out = LineWriter::new(host);
    let ok = if cfg!(feature = "icount") {
        icount::run(&mut out).is_ok()
    } else {
        let opts = xtarget_scenario::Options {
            frame_every: if cfg!(feature = "every-frame") {
                1
            } else {
                100
            },
            ..xtarget_scenario::Options::default()
        };
        xtarget_scenario::run_all(&opts, &mut out, &mut xtarget_scenario::NoProbe).is_ok()
    };
    exit(ok && out.flush().is_ok())
}

/// Ends the emulation with the exit status (`EXIT_SUCCESS` or `EXIT_FAILURE` on the host).
fn exit(ok: bool) -> ! {
    debug::exit(if ok { EXIT_SUCCESS } else { EXIT_FAILURE });
    // Not reached under QEMU; a debugger that ignores the request leaves the core asleep.
    loop {
        cortex_m::asm::wfi();
    }
}

/// The instruction-count window.
///
/// Each setup runs its first [`END`](icount::END) steps with the report switched off; in
/// steps [`BEGIN`](icount::BEGIN)..`END` (enabled, translating and rotating, 10 odometry
/// frames and one status/heartbeat pair among them; CiA 402: 25 SYNC cycles, each SYNC with
/// four RPDOs out and four TPDOs in the step after) the control core's work of each step (its
/// `on_frame` calls and its `step`) runs between `xtarget_mark_<setup>_begin` and
/// `xtarget_mark_<setup>_end`. Counting the trace lines (one per instruction with
/// `-singlestep -d exec,nochain`) from each `begin` to the next `end` gives the instructions
/// per control step, plus the few instructions of the marker calls themselves.
mod icount {
    use core::fmt::{self, Write};
    use core::sync::atomic::{AtomicU32, Ordering};

    use xtarget_scenario::{Options, Probe, Setup};

    /// First measured step.
    pub const BEGIN: u32 = 100;
    /// End of the run (exclusive).
    pub const END: u32 = 200;

    /// Written by the markers so that the calls are not optimised away; the values differ so
    /// that the eight functions are not merged into one.
    static MARK: AtomicU32 = AtomicU32::new(0);

    #[inline(never)]
    fn xtarget_mark_dji_begin() {
        MARK.store(1, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_dji_end() {
        MARK.store(2, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_odrive_begin() {
        MARK.store(3, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_odrive_end() {
        MARK.store(4, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_cia402_begin() {
        MARK.store(5, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_cia402_end() {
        MARK.store(6, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_pods_begin() {
        MARK.store(7, Ordering::Relaxed);
    }
    #[inline(never)]
    fn xtarget_mark_pods_end() {
        MARK.store(8, Ordering::Relaxed);
    }

    struct Markers;

    impl Probe for Markers {
        fn core_begin(&mut self, setup: Setup, step: u32) {
            if step >= BEGIN {
                match setup {
                    Setup::Dji => xtarget_mark_dji_begin(),
                    Setup::Odrive => xtarget_mark_odrive_begin(),
                    Setup::Cia402 => xtarget_mark_cia402_begin(),
                    Setup::Pods => xtarget_mark_pods_begin(),
                }
            }
        }
        fn core_end(&mut self, setup: Setup, step: u32) {
            if step >= BEGIN {
                match setup {
                    Setup::Dji => xtarget_mark_dji_end(),
                    Setup::Odrive => xtarget_mark_odrive_end(),
                    Setup::Cia402 => xtarget_mark_cia402_end(),
                    Setup::Pods => xtarget_mark_pods_end(),
                }
            }
        }
    }

    /// A report sink that drops everything.
    struct Discard;

    impl Write for Discard {
        fn write_str(&mut self, _: &str) -> fmt::Result {
            Ok(())
        }
    }

    pub fn run(out: &mut impl Write) -> fmt::Result {
        let opts = Options {
            steps: END,
            frame_every: 0,
            checkpoints: false,
        };
        for setup in Setup::ALL {
            let d = xtarget_scenario::run(setup, &opts, &mut Discard, &mut Markers)?;
            writeln!(
                out,
                "icount {} steps={BEGIN}..{END} frames={} hash={:016x}",
                setup.name(),
                d.frames,
                d.hash
            )?;
        }
        // Reading the marker value keeps the markers' stores (and so their calls) alive.
        writeln!(out, "icount last marker {}", MARK.load(Ordering::Relaxed))
    }
}

#[panic_handler]
fn panic(info: &PanicInfo) -> ! {
    if let Ok(mut host) = hio::hstderr() {
        let _ = writeln!(host, "panic: {info}");
    }
    exit(false)
}
