#!/usr/bin/env bash
# The project's whole test suite: what CI runs and what a user runs (README, "Two commands").
# Each stage is a separate check that fails on its own; the script stops at the first failure
# and names it. It installs what it needs: the thumbv7em target (rustup) and a Python virtual
# environment for the Python tests (pip), into .venv beside this repository.
set -euo pipefail
cd "$(dirname "$0")/.."
# The stages find build outputs under ./target and each board's own target/: a target
# directory or build target set in the environment would move them.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET

THUMB=thumbv7em-none-eabihf
# no_std crates that must build for the MCU target.
NO_STD_CRATES=(kinematics firmware)

STAGE=
stage() {
    STAGE=$*
    printf '\n==> %s\n' "$*"
}
trap 'printf "\n==> FAILED (exit %s): %s\n" "$?" "$STAGE" >&2' ERR

stage "toolchain: $(rustc --version); installing target $THUMB"
rustup component add rustfmt clippy >/dev/null
rustup target add "$THUMB"

stage "fmt"
cargo fmt --all -- --check

stage "clippy (all targets, -D warnings)"
cargo clippy --workspace --all-targets --all-features --locked -- -D warnings

stage "tests"
cargo test --workspace --all-features --locked

stage "rustdoc (-D warnings)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --all-features --locked

for crate in "${NO_STD_CRATES[@]}"; do
    stage "no_std build: $crate for $THUMB"
    cargo build -p "$crate" --target "$THUMB" --locked
done
# The firmware's `serde` feature is no_std too (with `alloc`): a configuration can be
# deserialized on an MCU that has an allocator.
stage "no_std build: firmware --features serde for $THUMB"
cargo build -p firmware --features serde --target "$THUMB" --locked

# The board crate is its own package (not a workspace member, its own Cargo.lock): its
# commands run from its directory so that its .cargo/config.toml (target, linker script) applies.
BOARD=boards/stm32f407
stage "board $BOARD: fmt"
cargo fmt --check --manifest-path "$BOARD/Cargo.toml"
stage "board $BOARD: clippy (-D warnings)"
(cd "$BOARD" && cargo clippy --release --locked -- -D warnings)
stage "board $BOARD: release build for $THUMB"
(cd "$BOARD" && cargo build --release --locked)
stage "board $BOARD: flash and RAM (budgets 256 KiB flash, 32 KiB static RAM)"
python3 "$BOARD/size.py" "$BOARD/target/$THUMB/release/board-stm32f407" \
    --max-flash 262144 --max-ram 32768

# The emulated Cortex-M4 (QEMU mps2-an386) board: its own workspace, like the STM32F407 one.
# The firmware core and a fixed scenario run there and on the host; the outbound frame streams
# must be bit-identical (scripts/xtarget.sh installs qemu-system-arm when root and missing).
QEMU_BOARD=boards/qemu-m4
stage "board $QEMU_BOARD: fmt"
cargo fmt --check --all --manifest-path "$QEMU_BOARD/Cargo.toml"
stage "board $QEMU_BOARD: clippy (-D warnings; M4, M4 icount, host)"
(cd "$QEMU_BOARD" && cargo clippy --release --locked -- -D warnings &&
    cargo clippy --release --locked --features icount -- -D warnings &&
    cargo clippy --release --locked -p xtarget-scenario \
        --target "$(rustc -vV | sed -n 's/^host: //p')" -- -D warnings)
stage "cross-target determinism: Cortex-M4 (QEMU) against the host, instructions per step"
scripts/xtarget.sh

stage "benchmarks compile"
cargo bench -p kinematics -p firmware --no-run --locked

if [ -d tests ] && compgen -G "tests/test_*.py" >/dev/null; then
    stage "python tests"
    # A venv left broken (python3 without ensurepip makes one with no pip) is made anew;
    # as root, Debian's python3-venv is installed first when ensurepip is missing.
    if ! .venv/bin/python -m pip --version >/dev/null 2>&1; then
        if ! python3 -c 'import ensurepip' 2>/dev/null && [ "$(id -u)" = 0 ] &&
            command -v apt-get >/dev/null; then
            apt-get update -qq
            DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv
        fi
        rm -rf .venv
        python3 -m venv .venv
    fi
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -r tests/requirements.txt
    # The package's ros2 extra, for the ROS 2 bridge's tests: ROS 2 Jazzy's Python client and
    # message packages, as wheels from PyPI (x86-64 Linux; some 150 MB in .venv). Without
    # --force-reinstall pip leaves what is installed alone: only the first run downloads them.
    .venv/bin/python -m pip install --quiet --disable-pip-version-check './python[ros2]'
    # The project's own Python package (python/), as a user installs it: its wheel carries the
    # robot DBC from dbc/. Reinstalled every run, so the tests see this checkout's code.
    .venv/bin/python -m pip install --quiet --disable-pip-version-check --force-reinstall --no-deps ./python
    cargo build -p firmware --features std --bin mecanum-codec --locked
    .venv/bin/python -m pytest tests -q -m "not vcan"

    # Tests on a real SocketCAN interface: natively where the kernel has vcan, else in a QEMU
    # micro-VM (scripts/vcan.sh says how). With CI=true a lane that cannot run fails.
    # The runner and the plant run in real time there: release builds (the micro-VM emulates
    # its CPU, some 20x slower than the host). -s: the tests print their measured figures.
    stage "vcan lane: tests marked vcan on a real vcan0 (native, else a micro-VM)"
    cargo build --release --locked -p hostsim --bin hostsim -p mecanum-runner --bin mecanum-runner
    HOSTSIM="$PWD/target/release/hostsim" MECANUM_RUNNER="$PWD/target/release/mecanum-runner" \
        MECANUM_CODEC="$PWD/target/debug/mecanum-codec" \
        VCAN_VM_TIMEOUT=${VCAN_VM_TIMEOUT:-900} \
        scripts/vcan.sh -- .venv/bin/python -m pytest tests -m vcan -q -s -p no:cacheprovider
fi

stage "all checks passed"
