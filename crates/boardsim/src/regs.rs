//! Register files: peripherals the firmware only configures (PWR, GPIO, SYSCFG, DMA, DBGMCU)
//! read back what was written, from their RM0090 reset values; RCC's ready flags follow their
//! enables at once (each of embassy's clock busy-waits then ends on its first read), and it
//! computes the clock tree the firmware programmed.

/// A peripheral's registers as words that read back what was written, from reset values.
#[derive(Debug, Clone)]
pub struct RegFile {
    /// The peripheral's name (RM0090), for reports.
    pub name: &'static str,
    words: Vec<u32>,
    /// Offsets of the registers RM0090 documents; any other offset is "unknown".
    known: &'static [u32],
}

impl RegFile {
    /// Registers `known` (offsets) of a block of `size` bytes, zero but for `resets`.
    #[must_use]
    pub fn new(
        name: &'static str,
        size: u32,
        known: &'static [u32],
        resets: &[(u32, u32)],
    ) -> Self {
        let mut words = vec![0; size as usize / 4];
        for &(off, value) in resets {
            words[off as usize / 4] = value;
        }
        Self { name, words, known }
    }

    /// Whether `off` (byte offset) is in a documented register.
    #[must_use]
    pub fn knows(&self, off: u32) -> bool {
        self.known.contains(&(off & !3))
    }

    /// The word at `off`.
    #[must_use]
    pub fn word(&self, off: u32) -> u32 {
        self.words.get(off as usize / 4).copied().unwrap_or(0)
    }

    /// Sets the word at `off`.
    pub fn set_word(&mut self, off: u32, value: u32) {
        if let Some(w) = self.words.get_mut(off as usize / 4) {
            *w = value;
        }
    }

    /// A read of `size` bytes at `off`.
    #[must_use]
    pub fn read(&self, off: u32, size: usize) -> u32 {
        sub_word(self.word(off), off, size)
    }

    /// A write of `size` bytes at `off`: the bytes written change, the others keep.
    pub fn write(&mut self, off: u32, size: usize, value: u32) {
        let merged = merge(self.word(off), off, size, value);
        self.set_word(off, merged);
    }
}

/// The `size` bytes at byte `off & 3` of `word`.
#[must_use]
pub const fn sub_word(word: u32, off: u32, size: usize) -> u32 {
    let shifted = word >> ((off & 3) * 8);
    if size >= 4 {
        shifted
    } else {
        shifted & ((1 << (size * 8)) - 1)
    }
}

/// `word` with the `size` bytes at byte `off & 3` replaced by `value`.
#[must_use]
pub const fn merge(word: u32, off: u32, size: usize, value: u32) -> u32 {
    if size >= 4 {
        return value;
    }
    let shift = (off & 3) * 8;
    let mask = ((1u32 << (size * 8)) - 1) << shift;
    (word & !mask) | ((value << shift) & mask)
}

/// RCC register offsets (RM0090 §7.3).
pub mod rcc {
    /// Clock control.
    pub const CR: u32 = 0x00;
    /// PLL configuration.
    pub const PLLCFGR: u32 = 0x04;
    /// Clock configuration.
    pub const CFGR: u32 = 0x08;
    /// APB1 peripheral clock enable.
    pub const APB1ENR: u32 = 0x40;
    /// Backup domain control.
    pub const BDCR: u32 = 0x70;
    /// Control and status.
    pub const CSR: u32 = 0x74;
    /// Dedicated clocks configuration: on the STM32F42x/43x only (RM0090 §7.3.24); on the
    /// F405/F407 a reserved word that reads 0 and ignores writes. embassy-stm32's F4 clock
    /// set-up writes it on every F4.
    pub const DCKCFGR: u32 = 0x8C;
    /// Every documented register (and DCKCFGR).
    pub const KNOWN: &[u32] = &[
        0x00, 0x04, 0x08, 0x0C, 0x10, 0x14, 0x18, 0x20, 0x24, 0x30, 0x34, 0x38, 0x40, 0x44, 0x50,
        0x54, 0x58, 0x60, 0x64, 0x70, 0x74, 0x80, 0x84, DCKCFGR,
    ];
}

/// The reset and clock control: a register file whose ready flags follow their enables.
#[derive(Debug, Clone)]
pub struct Rcc {
    /// The registers.
    pub regs: RegFile,
    /// The HSE crystal's frequency (a board property: 12 MHz on the type C board).
    pub hse_hz: u32,
}

/// Internal RC oscillator, Hz.
pub const HSI_HZ: u32 = 16_000_000;

/// The clock tree as the RCC registers program it, Hz.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Clocks {
    /// System clock (the CPU's).
    pub sysclk: u32,
    /// AHB clock.
    pub hclk: u32,
    /// APB1 peripheral clock (CAN1, CAN2).
    pub pclk1: u32,
    /// APB2 peripheral clock.
    pub pclk2: u32,
    /// APB1 timers' clock (TIM2..TIM7, TIM12..14): PCLK1, doubled when APB1 is divided.
    pub tim_apb1: u32,
}

impl Rcc {
    /// The RCC after reset, with an HSE crystal of `hse_hz`.
    #[must_use]
    pub fn new(hse_hz: u32) -> Self {
        let regs = RegFile::new(
            "RCC",
            0x400,
            rcc::KNOWN,
            &[
                (rcc::CR, 0x0000_0083),
                (rcc::PLLCFGR, 0x2400_3010),
                (0x30, 0x0010_0000),
                (0x50, 0x7E67_91FF),
                (0x54, 0x0000_00F1),
                (0x58, 0x0000_0001),
                (0x60, 0x36FE_C9FF),
                (0x64, 0x0007_5F33),
                (rcc::CSR, 0x0E00_0000),
                (0x84, 0x2000_3000),
            ],
        );
        Self { regs, hse_hz }
    }

    /// A read.
    #[must_use]
    pub fn read(&self, off: u32, size: usize) -> u32 {
        self.regs.read(off, size)
    }

    /// A write; the ready flags (CR: HSIRDY, HSERDY, PLLRDY, PLLI2SRDY; BDCR: LSERDY; CSR:
    /// LSIRDY) and CFGR.SWS follow at once.
    pub fn write(&mut self, off: u32, size: usize, value: u32) {
        if off & !3 == rcc::DCKCFGR {
            return;
        }
        self.regs.write(off, size, value);
        let follow = |word: u32, pairs: &[(u32, u32)]| {
            pairs.iter().fold(word, |w, &(on, rdy)| {
                (w & !(1 << rdy)) | (((w >> on) & 1) << rdy)
            })
        };
        match off & !3 {
            rcc::CR => {
                let w = follow(
                    self.regs.word(rcc::CR),
                    &[(0, 1), (16, 17), (24, 25), (26, 27)],
                );
                self.regs.set_word(rcc::CR, w);
            }
            rcc::CFGR => {
                let w = self.regs.word(rcc::CFGR);
                self.regs.set_word(rcc::CFGR, (w & !0xC) | ((w & 3) << 2));
            }
            rcc::BDCR => {
                let w = follow(self.regs.word(rcc::BDCR), &[(0, 1)]);
                self.regs.set_word(rcc::BDCR, w);
            }
            rcc::CSR => {
                let mut w = follow(self.regs.word(rcc::CSR), &[(0, 1)]);
                if w & 1 << 24 != 0 {
                    // RMVF: clears the reset flags (bits 25..31); it reads 0.
                    w &= 0x00FF_FFFF & !(1 << 24);
                }
                self.regs.set_word(rcc::CSR, w);
            }
            _ => {}
        }
    }

    /// The clock tree the registers select (RM0090 §6.2: PLL = source / M × N / P; AHB, APB1,
    /// APB2 prescalers; timers on a divided APB run at twice its clock).
    #[must_use]
    pub fn clocks(&self) -> Clocks {
        let cfgr = self.regs.word(rcc::CFGR);
        let pll = self.regs.word(rcc::PLLCFGR);
        let pll_in = if pll >> 22 & 1 == 1 {
            self.hse_hz
        } else {
            HSI_HZ
        };
        let m = (pll & 0x3F).max(1);
        let n = (pll >> 6) & 0x1FF;
        let p = 2 * (((pll >> 16) & 3) + 1);
        let pll_p = (u64::from(pll_in) / u64::from(m) * u64::from(n) / u64::from(p)) as u32;
        let sysclk = match (cfgr >> 2) & 3 {
            1 => self.hse_hz,
            2 => pll_p,
            _ => HSI_HZ,
        };
        let hpre = (cfgr >> 4) & 0xF;
        let hclk = if hpre < 8 {
            sysclk
        } else {
            sysclk >> [1, 2, 3, 4, 6, 7, 8, 9][hpre as usize - 8]
        };
        let apb = |bits: u32| if bits < 4 { 1 } else { 1 << (bits - 3) };
        let ppre1 = apb((cfgr >> 10) & 7);
        let ppre2 = apb((cfgr >> 13) & 7);
        let pclk1 = hclk / ppre1;
        Clocks {
            sysclk,
            hclk,
            pclk1,
            pclk2: hclk / ppre2,
            tim_apb1: if ppre1 == 1 { pclk1 } else { 2 * pclk1 },
        }
    }
}

/// A documented-register list for the blocks kept as plain register files.
mod known {
    pub const PWR: &[u32] = &[0x00, 0x04];
    pub const GPIO: &[u32] = &[0x00, 0x04, 0x08, 0x0C, 0x10, 0x14, 0x18, 0x1C, 0x20, 0x24];
    pub const SYSCFG: &[u32] = &[0x00, 0x04, 0x08, 0x0C, 0x10, 0x14, 0x20];
    pub const DBGMCU: &[u32] = &[0x00, 0x04, 0x08, 0x0C];
    /// LISR, HISR, LIFCR, HIFCR, then 8 streams of CR, NDTR, PAR, M0AR, M1AR, FCR.
    pub const DMA: &[u32] = &[
        0x00, 0x04, 0x08, 0x0C, //
        0x10, 0x14, 0x18, 0x1C, 0x20, 0x24, 0x28, 0x2C, 0x30, 0x34, 0x38, 0x3C, //
        0x40, 0x44, 0x48, 0x4C, 0x50, 0x54, 0x58, 0x5C, 0x60, 0x64, 0x68, 0x6C, //
        0x70, 0x74, 0x78, 0x7C, 0x80, 0x84, 0x88, 0x8C, 0x90, 0x94, 0x98, 0x9C, //
        0xA0, 0xA4, 0xA8, 0xAC, 0xB0, 0xB4, 0xB8, 0xBC, 0xC0, 0xC4, 0xC8, 0xCC,
    ];
}

/// Base addresses (RM0090 §2.3, Table 1).
pub mod base {
    /// TIM2 (APB1).
    pub const TIM2: u32 = 0x4000_0000;
    /// Independent watchdog (APB1).
    pub const IWDG: u32 = 0x4000_3000;
    /// bxCAN CAN1 (APB1).
    pub const CAN1: u32 = 0x4000_6400;
    /// Power control (APB1).
    pub const PWR: u32 = 0x4000_7000;
    /// System configuration controller (APB2).
    pub const SYSCFG: u32 = 0x4001_3800;
    /// GPIO port A; ports B..I follow every 0x400 (AHB1).
    pub const GPIOA: u32 = 0x4002_0000;
    /// RCC (AHB1).
    pub const RCC: u32 = 0x4002_3800;
    /// Flash interface (AHB1).
    pub const FLASH: u32 = 0x4002_3C00;
    /// DMA1 (AHB1).
    pub const DMA1: u32 = 0x4002_6000;
    /// DMA2 (AHB1).
    pub const DMA2: u32 = 0x4002_6400;
    /// Debug MCU configuration (PPB).
    pub const DBGMCU: u32 = 0xE004_2000;
}

/// The register-file blocks, each at its base address.
#[must_use]
pub fn register_files() -> Vec<(u32, RegFile)> {
    let mut files = vec![
        (
            base::PWR,
            RegFile::new("PWR", 0x400, known::PWR, &[(0x00, 0x0000_4000)]),
        ),
        (
            base::SYSCFG,
            RegFile::new("SYSCFG", 0x400, known::SYSCFG, &[]),
        ),
        (base::DMA1, dma("DMA1")),
        (base::DMA2, dma("DMA2")),
        (
            base::DBGMCU,
            // IDCODE: STM32F40x/41x (DEV_ID 0x413), revision Z (0x1001).
            RegFile::new("DBGMCU", 0x400, known::DBGMCU, &[(0x00, 0x1001_6413)]),
        ),
    ];
    const PORTS: [&str; 9] = [
        "GPIOA", "GPIOB", "GPIOC", "GPIOD", "GPIOE", "GPIOF", "GPIOG", "GPIOH", "GPIOI",
    ];
    for (i, name) in PORTS.into_iter().enumerate() {
        let resets: &[(u32, u32)] = match i {
            0 => &[
                (0x00, 0xA800_0000),
                (0x08, 0x0C00_0000),
                (0x0C, 0x6400_0000),
            ],
            1 => &[
                (0x00, 0x0000_0280),
                (0x08, 0x0000_00C0),
                (0x0C, 0x0000_0100),
            ],
            _ => &[],
        };
        files.push((
            base::GPIOA + 0x400 * i as u32,
            RegFile::new(name, 0x400, known::GPIO, resets),
        ));
    }
    files
}

fn dma(name: &'static str) -> RegFile {
    let fcr: Vec<(u32, u32)> = (0..8).map(|s| (0x24 + 0x18 * s, 0x21)).collect();
    RegFile::new(name, 0x400, known::DMA, &fcr)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sub_word_accesses_read_and_write_their_bytes() {
        let mut f = RegFile::new("T", 0x10, &[0x0], &[(0x0, 0x1122_3344)]);
        assert_eq!(f.read(0x1, 1), 0x33);
        assert_eq!(f.read(0x2, 2), 0x1122);
        f.write(0x1, 1, 0xAB);
        assert_eq!(f.word(0), 0x1122_AB44);
        f.write(0x2, 2, 0xBEEF);
        assert_eq!(f.word(0), 0xBEEF_AB44);
        assert!(f.knows(0x3) && !f.knows(0x4));
    }

    #[test]
    fn rcc_ready_flags_follow_their_enables() {
        let mut rcc = Rcc::new(12_000_000);
        // Reset: HSION and HSIRDY (RM0090 §7.3.1, reset value 0x0000 XX83).
        assert_eq!(rcc.read(rcc::CR, 4) & 0b11, 0b11);
        rcc.write(rcc::CR, 4, 0x83 | 1 << 16 | 1 << 24);
        let cr = rcc.read(rcc::CR, 4);
        assert_eq!(cr >> 17 & 1, 1, "HSERDY");
        assert_eq!(cr >> 25 & 1, 1, "PLLRDY");
        rcc.write(rcc::CR, 4, 0x83);
        assert_eq!(rcc.read(rcc::CR, 4) >> 25 & 1, 0, "PLLRDY drops with PLLON");
        rcc.write(rcc::CFGR, 4, 2);
        assert_eq!(rcc.read(rcc::CFGR, 4) >> 2 & 3, 2, "SWS follows SW");
        assert_eq!(rcc.read(rcc::CSR, 4) >> 25, 0b111, "power-on reset flags");
        rcc.write(rcc::CSR, 4, 0x0E00_0001);
        assert_eq!(rcc.read(rcc::CSR, 4) & 2, 2, "LSIRDY");
        rcc.write(rcc::CSR, 4, 1 << 24 | 1);
        assert_eq!(rcc.read(rcc::CSR, 4), 0b11, "RMVF cleared the flags");
    }

    #[test]
    fn the_boards_clock_tree_is_168_mhz_with_apb1_at_42() {
        let mut rcc = Rcc::new(12_000_000);
        assert_eq!(rcc.clocks().sysclk, HSI_HZ);
        // PLLM 6, PLLN 168, PLLP /2 (0b00), source HSE (bit 22), PLLQ 7.
        rcc.write(rcc::PLLCFGR, 4, 6 | 168 << 6 | 1 << 22 | 7 << 24);
        // SW = PLL, HPRE /1, PPRE1 /4 (0b101), PPRE2 /2 (0b100).
        rcc.write(rcc::CFGR, 4, 2 | 0b101 << 10 | 0b100 << 13);
        let c = rcc.clocks();
        assert_eq!(
            (c.sysclk, c.hclk, c.pclk1, c.pclk2, c.tim_apb1),
            (168_000_000, 168_000_000, 42_000_000, 84_000_000, 84_000_000)
        );
    }
}
