//! What the tests share: where the board image is.

use std::path::PathBuf;

/// The board ELF: `BOARDSIM_ELF`, else the release build of `boards/stm32f407` (which
/// `scripts/test.sh` makes before the Rust tests).
pub fn elf() -> PathBuf {
    let path = std::env::var_os("BOARDSIM_ELF").map_or_else(
        || {
            PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                .join("../../boards/stm32f407/target/thumbv7em-none-eabihf/release/board-stm32f407")
        },
        PathBuf::from,
    );
    assert!(
        path.exists(),
        "{}: no board image; build it with `cd boards/stm32f407 && cargo build --release` \
         (scripts/test.sh does) or set BOARDSIM_ELF",
        path.display()
    );
    path
}
