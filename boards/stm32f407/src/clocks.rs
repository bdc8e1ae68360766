//! Clock tree of the RoboMaster development board type C: a 12 MHz crystal (HSE) to a
//! 168 MHz system clock, the STM32F407's maximum.
//!
//! | clock | source | frequency |
//! |---|---|---|
//! | HSE | crystal | 12 MHz |
//! | PLL input | HSE / M (6) | 2 MHz |
//! | VCO | x N (168) | 336 MHz |
//! | SYSCLK, HCLK | VCO / P (2) | 168 MHz |
//! | PLL48CK (USB, SDIO) | VCO / Q (7) | 48 MHz |
//! | APB1 (CAN1, CAN2, TIM2) | HCLK / 4 | 42 MHz (timers x2: 84 MHz) |
//! | APB2 | HCLK / 2 | 84 MHz (timers x2: 168 MHz) |
//!
//! The same tree as DJI's CubeMX examples for the board (PLLM 6, PLLN 168, PLLP 2, PLLQ 7,
//! APB1 /4, APB2 /2). The HAL sets the flash wait states (5 at 168 MHz, 3.3 V).

use embassy_stm32::rcc::{
    AHBPrescaler, APBPrescaler, Hse, HseMode, Pll, PllMul, PllPDiv, PllPreDiv, PllQDiv, PllSource,
    Sysclk,
};
use embassy_stm32::time::Hertz;

/// The HAL configuration with the board's clock tree.
pub fn config() -> embassy_stm32::Config {
    let mut config = embassy_stm32::Config::default();
    let rcc = &mut config.rcc;
    rcc.hse = Some(Hse {
        freq: Hertz::mhz(12),
        mode: HseMode::Oscillator,
    });
    rcc.pll_src = PllSource::HSE;
    rcc.pll = Some(Pll {
        prediv: PllPreDiv::DIV6,
        mul: PllMul::MUL168,
        divp: Some(PllPDiv::DIV2),
        divq: Some(PllQDiv::DIV7),
        divr: None,
    });
    rcc.sys = Sysclk::PLL1_P;
    rcc.ahb_pre = AHBPrescaler::DIV1;
    rcc.apb1_pre = APBPrescaler::DIV4;
    rcc.apb2_pre = APBPrescaler::DIV2;
    config
}
