//! Exceptions as the board does them (Unicorn has no NVIC): entry (the 8- or 26-word frame,
//! 8-byte alignment, EXC_RETURN, IPSR, the vector), return (unstacking), and the choice of
//! which pending exception preempts, from the SCS model.

use unicorn_engine::RegisterARM;

use super::hw::Sleep;
use super::{Board, BoardError, uc_err};
use crate::nvic::exc;

/// Cycles of an exception entry (Cortex-M4 TRM §3.3: 12-cycle latency).
const ENTRY_CYCLES: u64 = 12;
/// Cycles of an exception return.
const RETURN_CYCLES: u64 = 10;

impl Board {
    pub(super) fn reg(&self, r: RegisterARM) -> u32 {
        self.uc.reg_read(r).unwrap_or(0) as u32
    }

    fn set_reg(&mut self, r: RegisterARM, v: u32) -> Result<(), BoardError> {
        self.uc
            .reg_write(r, u64::from(v))
            .map_err(|e| uc_err(e, self.pc))
    }

    fn read_words(&self, addr: u32, n: usize) -> Result<Vec<u32>, BoardError> {
        let mut bytes = vec![0u8; 4 * n];
        self.uc
            .mem_read(u64::from(addr), &mut bytes)
            .map_err(|_| BoardError::Unmapped {
                access: "read",
                addr,
                pc: self.pc,
            })?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn write_words(&mut self, addr: u32, words: &[u32]) -> Result<(), BoardError> {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        self.uc
            .mem_write(u64::from(addr), &bytes)
            .map_err(|_| BoardError::Unmapped {
                access: "write",
                addr,
                pc: self.pc,
            })
    }

    const STACKED: [RegisterARM; 6] = [
        RegisterARM::R0,
        RegisterARM::R1,
        RegisterARM::R2,
        RegisterARM::R3,
        RegisterARM::R12,
        RegisterARM::LR,
    ];

    /// Exception entry (ARMv7-M B1.5.6): pushes the frame on the main stack, sets LR to
    /// EXC_RETURN, IPSR, clears the IT bits and CONTROL.FPCA, and branches to the vector.
    fn enter(&mut self, n: u16) -> Result<(), BoardError> {
        let control = self.reg(RegisterARM::CONTROL);
        let handler = self.reg(RegisterARM::IPSR) & 0x1FF != 0;
        if !handler && control & 2 != 0 {
            return Err(BoardError::ProcessStack { pc: self.pc });
        }
        let fp = control & 4 != 0;
        let xpsr = self.reg(RegisterARM::XPSR);
        let sp = self.reg(RegisterARM::MSP);
        let size = if fp { 0x68 } else { 0x20 };
        let realign = (sp - size) & 4 != 0;
        let frame_sp = (sp - size) & !7;
        let mut frame: Vec<u32> = Self::STACKED.iter().map(|&r| self.reg(r)).collect();
        frame.push(self.pc & !1);
        frame.push((xpsr & !(1 << 9)) | u32::from(realign) << 9 | 1 << 24);
        if fp {
            for i in 0..16 {
                frame.push(self.reg(s_reg(i)));
            }
            frame.push(self.reg(RegisterARM::FPSCR));
            frame.push(0);
        }
        self.write_words(frame_sp, &frame)?;
        self.set_reg(RegisterARM::MSP, frame_sp)?;
        let exc_return = match (handler, fp) {
            (true, false) => 0xFFFF_FFF1,
            (false, false) => 0xFFFF_FFF9,
            (true, true) => 0xFFFF_FFE1,
            (false, true) => 0xFFFF_FFE9,
        };
        self.set_reg(RegisterARM::LR, exc_return)?;
        self.set_reg(RegisterARM::CONTROL, control & !4)?;
        // IPSR = n; EPSR: T, no IT state; the flags are kept.
        self.set_reg(
            RegisterARM::XPSR_NZCVQG,
            (xpsr & 0xF80F_0000) | 1 << 24 | u32::from(n),
        )?;
        let vtor = self.uc.get_data().scs.vtor();
        let vector = self.read_words(vtor + 4 * u32::from(n), 1)?[0];
        self.pc = vector | 1;
        let hw = self.uc.get_data_mut();
        hw.scs.activate(n);
        hw.event = true;
        hw.sleep = Sleep::Awake;
        hw.now += ENTRY_CYCLES;
        hw.stats.exceptions += 1;
        Ok(())
    }

    /// Exception return to `value` (EXC_RETURN): unstacks the frame (8 or 26 words, the
    /// alignment word), restores xPSR (IPSR, IT, flags) and CONTROL.FPCA.
    pub(super) fn exception_return(&mut self, value: u32) -> Result<(), BoardError> {
        let pc = self.reg(RegisterARM::PC);
        let value = value | 1;
        let ok = matches!(value, 0xFFFF_FFF1 | 0xFFFF_FFF9 | 0xFFFF_FFE1 | 0xFFFF_FFE9);
        if !ok || self.uc.get_data().scs.active_stack().is_empty() {
            return Err(BoardError::BadExceptionReturn { value, pc });
        }
        let fp = value & 0x10 == 0;
        let sp = self.reg(RegisterARM::MSP);
        let words = self.read_words(sp, if fp { 26 } else { 8 })?;
        for (&r, &w) in Self::STACKED.iter().zip(&words) {
            self.set_reg(r, w)?;
        }
        if fp {
            for i in 0..16 {
                self.set_reg(s_reg(i), words[8 + i])?;
            }
            self.set_reg(RegisterARM::FPSCR, words[24])?;
        }
        let xpsr = words[7];
        let mut new_sp = sp + if fp { 0x68 } else { 0x20 };
        if xpsr & 1 << 9 != 0 {
            new_sp += 4;
        }
        self.set_reg(RegisterARM::MSP, new_sp)?;
        self.set_reg(RegisterARM::XPSR_NZCVQG, xpsr & !(1 << 9))?;
        let control = self.reg(RegisterARM::CONTROL);
        self.set_reg(
            RegisterARM::CONTROL,
            if fp { control | 4 } else { control & !4 },
        )?;
        self.pc = words[6] | 1;
        let hw = self.uc.get_data_mut();
        hw.scs.deactivate();
        hw.event = true;
        hw.now += RETURN_CYCLES;
        hw.stats.returns += 1;
        Ok(())
    }

    /// Takes every exception that preempts now (nesting: a higher one can follow at once).
    pub(super) fn take_exceptions(&mut self) -> Result<(), BoardError> {
        loop {
            // Nothing pending (most slices): no register reads.
            if self.uc.get_data().scs.highest_pending().is_none() {
                return Ok(());
            }
            let primask = self.reg(RegisterARM::PRIMASK) & 1 != 0;
            let basepri = self.reg(RegisterARM::BASEPRI) as u8;
            let faultmask = self.reg(RegisterARM::FAULTMASK) & 1 != 0;
            let hw = self.uc.get_data();
            let Some(n) = hw.scs.next(primask, basepri, faultmask) else {
                return Ok(());
            };
            if n == exc::HARD_FAULT || n == exc::SVCALL {
                return Err(BoardError::Emulation {
                    error: format!("exception {n} is not modelled"),
                    pc: self.pc,
                });
            }
            self.enter(n)?;
        }
    }
}

/// S0..S15.
fn s_reg(i: usize) -> RegisterARM {
    const S: [RegisterARM; 16] = [
        RegisterARM::S0,
        RegisterARM::S1,
        RegisterARM::S2,
        RegisterARM::S3,
        RegisterARM::S4,
        RegisterARM::S5,
        RegisterARM::S6,
        RegisterARM::S7,
        RegisterARM::S8,
        RegisterARM::S9,
        RegisterARM::S10,
        RegisterARM::S11,
        RegisterARM::S12,
        RegisterARM::S13,
        RegisterARM::S14,
        RegisterARM::S15,
    ];
    S[i]
}
