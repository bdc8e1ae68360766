//! `boardsim`: the STM32F407 board image, exactly as `cargo build --release` in
//! `boards/stm32f407` makes it for flashing, run under the Unicorn CPU emulator with the
//! project's own peripheral models, as the firmware node on the simulated robot's CAN bus.
//!
//! - [`elf`]: the image's load segments, symbols and hint instructions;
//! - [`board`]: the Cortex-M4 in virtual time (instructions at 168 MHz), the memory map,
//!   exception entry and return, sleep; [`nvic`] (NVIC, SCB, SysTick), [`regs`] (RCC and
//!   the register files), [`tim`] (TIM2), [`bxcan`] (CAN1), [`iwdg`] (the watchdog),
//!   [`flash`] (the flash interface: program, erase);
//! - [`rtt`]: the board's defmt log over RTT;
//! - [`lockstep`]: the board on hostsim's bit-timed bus; [`run`]: a scenario with it.
//!
//! GPL-2.0-or-later because it links Unicorn (GPL-2.0); a test tool, nothing the project
//! ships depends on it (see the crate's README).

pub mod board;
pub mod bxcan;
pub mod elf;
pub mod flash;
pub mod iwdg;
pub mod lockstep;
pub mod nvic;
pub mod powercut;
pub mod regs;
pub mod rtt;
pub mod run;
pub mod tim;

pub use board::{Board, BoardError, CPU_HZ};
pub use elf::Image;
pub use lockstep::Lockstep;
