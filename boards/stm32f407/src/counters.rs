//! What the loop counts: frames in and out, and what it had to drop.

use embassy_stm32::pac;

/// Counters of the control loop (wrapping is not a concern: `u32` frames at 1 Mbit/s last
/// more than five days; `steps` is `u64`).
#[derive(Debug, Default, Clone, Copy)]
pub struct Counters {
    /// Control steps run.
    pub steps: u64,
    /// Frames taken from RX FIFO 0 and handed to the core.
    pub rx_frames: u32,
    /// FIFO 0 overruns: a frame arrived while the 3-deep FIFO was full and was lost. Each
    /// count is at least one lost frame (the hardware keeps one flag, not a count).
    pub rx_overruns: u32,
    /// Bus errors the controller reported (stuff, form, ACK, bit, CRC).
    pub bus_errors: u32,
    /// Outbox frames put in the TX queue.
    pub tx_queued: u32,
    /// Outbox frames dropped because the TX queue was full (nothing acknowledges them, or the
    /// bus is saturated).
    pub tx_dropped: u32,
}

impl Counters {
    /// Counts one outbox frame, queued or dropped.
    pub fn tx(&mut self, queued: bool) {
        if queued {
            self.tx_queued = self.tx_queued.wrapping_add(1);
        } else {
            self.tx_dropped = self.tx_dropped.wrapping_add(1);
        }
    }

    /// Counts one received frame.
    pub fn rx(&mut self) {
        self.rx_frames = self.rx_frames.wrapping_add(1);
    }

    /// Counts one bus error.
    pub fn bus_error(&mut self) {
        self.bus_errors = self.bus_errors.wrapping_add(1);
    }

    /// Reads and clears CAN1's FIFO 0 overrun flag (`CAN_RF0R.FOVR0`, write 1 to clear); the
    /// HAL does not expose it. Writing 0 to the other bits of RF0R changes nothing (RFOM0 and
    /// FULL0 act on a 1 only), so this cannot release a frame the driver has not read.
    pub fn check_fifo_overrun(&mut self) {
        let rf0r = pac::CAN1.rfr(0);
        if rf0r.read().fovr() {
            rf0r.write(|w| w.set_fovr(true));
            self.rx_overruns = self.rx_overruns.wrapping_add(1);
        }
    }
}
