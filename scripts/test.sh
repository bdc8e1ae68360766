#!/usr/bin/env bash
# The project's whole test suite: what CI runs and what a user runs (README, "Two commands").
# `scripts/test.sh --help` lists the stages and the options.
set -euo pipefail
cd "$(dirname "$0")/.."
# The stages find build outputs under ./target and each board's own target/: a target
# directory or build target set in the environment would move them.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET

THUMB=thumbv7em-none-eabihf
# no_std crates that must build for the MCU target.
NO_STD_CRATES=(kinematics firmware)
BOARD=boards/stm32f407
# The workspace's `ci` builds compile its crates with Clippy's lints (scripts/clippy-rustc.sh):
# one build is both the lint check and what the tests run. Every `--profile ci` command below
# sets it, as Cargo rebuilds a crate whose wrapper changed. The boards' crates are linted the
# same way, in a build of their own; the images a user flashes are built without it.
LINT_WRAPPER=$PWD/scripts/clippy-rustc.sh
QEMU_BOARD=boards/qemu-m4
LOGS=target/test-stages

# name|what (the order they run in; `vcan` starts right after `prepare`, in the background)
STAGES=(
    "prepare|the Rust target and components (rustup), cmake and libclang for boardsim (apt-get, as root), the Python virtual environment .venv (pip), and the binaries the Python stages run: hostsim, mecanum-runner and mecanum-codec (the ci profile, which every Rust stage below shares)"
    "vcan|the tests marked vcan on a real vcan0: natively where the kernel has vcan, else in a QEMU micro-VM (scripts/vcan.sh); runs in the background beside the stages below"
    "fmt|cargo fmt --check"
    "stm32f407|$BOARD: clippy, the release images for the DJI, the ODrive and the CiA 402 example (boardsim's tests run the first two), their flash and RAM budgets"
    "clippy|every target of the workspace (lib, bins, tests, benchmarks, examples; all features) built with Clippy's lints, -D warnings: the build the tests run (scripts/clippy-rustc.sh)"
    "rust-tests|cargo test: unit, integration, property and doc tests; boardsim runs the $BOARD image"
    "python|the Python tests that need no CAN bus (cantools, mcap, rosbags, the package), a worker per core (pytest-xdist); in the background beside the stages below"
    "rustdoc|cargo doc, -D warnings, default and all features"
    "no-std|the no_std crates (${NO_STD_CRATES[*]}, firmware with serde) for $THUMB"
    "qemu-m4|$QEMU_BOARD: fmt, clippy; the core on an emulated Cortex-M4 bit-identical to the host (scripts/xtarget.sh)"
)

usage() {
    cat <<EOF
Usage: scripts/test.sh [--only STAGE[,STAGE...]] [--list] [-h | --help]

Runs the project's tests, stage by stage; stops at the first stage that fails and names it.
At the end it prints each stage's wall time (also in $LOGS/times.txt).

Stages, in order:
EOF
    local entry
    for entry in "${STAGES[@]}"; do
        printf '  %-12s %s\n' "${entry%%|*}" "${entry#*|}" | fold -s -w 96 | sed '2,$s/^/               /'
    done
    cat <<EOF

The vcan lane takes one host core (the micro-VM's clock counts the guest's instructions, so a
busy host slows it down without moving its timeline) and runs while the other stages use the
rest of the machine at a lower priority (niceness 10, and 15 for the builds beside the Python
tests, whose threads keep wall-clock rates); at each stage this script says which
test the lane is at, and its output is printed when it ends (and kept in $LOGS/vcan.log;
scripts/lane-times.py tables its times). Its limits, in wall time: VCAN_VM_TIMEOUT (1530 s)
and, per test, VCAN_TEST_TIMEOUT (390 s), both grown in proportion when the emulator runs
slower than VCAN_LIMITS_PACE (3.6 wall seconds per guest second). Without vcan0 and without the
VM's packages it is skipped, or fails when CI is set (.ci/run sets it).

Options:
  --only STAGES  run only these stages (comma-separated names from the list), e.g.
                 --only vcan or --only fmt,clippy; \`prepare\` runs first when a stage needs it
  --list         print the stage names, one a line, and exit
  -h, --help     this text

Installs what it needs: the $THUMB target (rustup), Python packages into .venv (pip), and,
as root, Debian's cmake and libclang-dev (boardsim's CPU emulator), QEMU, kernel and
can-utils packages for the emulated Cortex-M4 and the vcan lane (apt-get). Environment: VCAN_* (scripts/vcan.sh --help), CI.
EOF
}

ONLY=
while [ $# -gt 0 ]; do
    case $1 in
    -h | --help) usage; exit 0 ;;
    --list) for entry in "${STAGES[@]}"; do echo "${entry%%|*}"; done; exit 0 ;;
    --only) [ $# -ge 2 ] || { echo "test.sh: --only needs stage names (--list shows them)" >&2; exit 2; }
        ONLY=$2; shift 2 ;;
    --only=*) ONLY=${1#--only=}; shift ;;
    *) echo "test.sh: unknown argument '$1' (--help)" >&2; exit 2 ;;
    esac
done

declare -A WANT=()
if [ -n "$ONLY" ]; then
    IFS=, read -r -a only_names <<<"$ONLY"
    for name in "${only_names[@]}"; do
        known=0
        for entry in "${STAGES[@]}"; do [ "${entry%%|*}" = "$name" ] && known=1; done
        if [ "$known" = 0 ]; then
            echo "test.sh: --only: no stage '$name' (stages: $(for e in "${STAGES[@]}"; do printf '%s ' "${e%%|*}"; done))" >&2
            exit 2
        fi
        WANT[$name]=1
    done
    # The Python stages run what `prepare` installs and builds; boardsim's tests (rust-tests)
    # run the board image the stm32f407 stage builds.
    if [ -n "${WANT[vcan]:-}${WANT[python]:-}" ]; then WANT[prepare]=1; fi
    if [ -n "${WANT[rust-tests]:-}" ]; then WANT[stm32f407]=1; fi
else
    for entry in "${STAGES[@]}"; do WANT[${entry%%|*}]=1; done
fi
wanted() { [ -n "${WANT[$1]:-}" ]; }

mkdir -p "$LOGS"
T0=$(date +%s)
TIMES=()
STAGE=
STAGE_T=
now() { date +%s; }
# The machine's busy and total CPU time so far, in clock ticks (the first line of /proc/stat;
# busy is all but idle and iowait): a stage's share of the machine's cores, beside its wall
# time, says whether it waited on one core or used them all. "0 0" where there is no /proc.
cpu_ticks() {
    local _cpu user nice system idle iowait rest
    if read -r _cpu user nice system idle iowait rest </proc/stat 2>/dev/null; then
        local total=$((user + nice + system + idle + iowait))
        for n in $rest; do total=$((total + n)); done
        echo "$((total - idle - iowait)) $total"
    else
        echo "0 0"
    fi
}
read -r T0_BUSY T0_TOTAL <<<"$(cpu_ticks)"
# "NN% of the CPUs" since the ticks BUSY TOTAL were read (nothing where no time was counted).
cpu_share() {
    local busy total
    read -r busy total <<<"$(cpu_ticks)"
    if [ "$((total - $2))" -gt 0 ]; then
        printf '%4d%% of the CPUs' "$((100 * (busy - $1) / (total - $2)))"
    fi
}
finish_stage() {
    if [ -n "$STAGE" ]; then
        TIMES+=("$(printf '%6d s  %-12s %s' "$(($(now) - STAGE_T))" "$STAGE" "$(cpu_share "$STAGE_BUSY" "$STAGE_TOTAL")")")
    fi
    STAGE=
}
stage() {
    finish_stage
    lane_progress
    STAGE=$1
    STAGE_T=$(now)
    read -r STAGE_BUSY STAGE_TOTAL <<<"$(cpu_ticks)"
    printf '\n==> %s: %s\n' "$1" "$2"
}
# Where the vcan lane is, while it runs in the background: its last progress line (the test,
# n of N, guest time) and the wall time since it started.
lane_progress() {
    local last
    if [ -n "${BG_PID[vcan]:-}" ] && kill -0 "${BG_PID[vcan]}" 2>/dev/null; then
        # (Under set -e and pipefail: before the guest's first line there is no file yet.)
        last=$(tail -n 1 target/vcan-lane/timeline.tsv 2>/dev/null | cut -f 2-) || last=
        printf '\n--- vcan lane, %d s in: %s\n' "$(($(now) - BG_T[vcan]))" "${last:-booting}"
    fi
}
print_times() {
    {
        printf '\nstage times (wall):\n'
        printf '  %s\n' "${TIMES[@]}"
        printf '  %6d s  %-12s %s\n' "$(($(now) - T0))" total "$(cpu_share "$T0_BUSY" "$T0_TOTAL")"
    } | tee "$LOGS/times.txt"
}

# Ends a job started in the background (PID, may be empty) and waits for it.
stop_background() {
    if [ -n "$1" ] && kill -0 "$1" 2>/dev/null; then
        kill -TERM "$1" 2>/dev/null || true
        wait "$1" 2>/dev/null || true
    fi
}
# Waits for a job started in the background (PID), prints its output (LOG), and returns its
# status: at the top level a failure there runs the ERR trap, which names the stage.
join_background() {
    local rc=0
    wait "$1" || rc=$?
    cat "$2"
    return "$rc"
}
# Stages that run in the background, beside the ones after them (the vcan lane; the python
# stage once the workspace's build is done): by name, the job, when the stage began and the
# CPU ticks then. Their output goes to $LOGS/NAME.log and is printed when they are joined.
declare -A BG_PID=() BG_T=() BG_TICKS=()
# Runs a command as the current stage's job in the background; the next stage starts at once.
start_background() {
    "$@" >"$LOGS/$STAGE.log" 2>&1 &
    BG_PID[$STAGE]=$!
    BG_T[$STAGE]=$STAGE_T
    BG_TICKS[$STAGE]="$STAGE_BUSY $STAGE_TOTAL"
    STAGE=
}
# Waits for a background stage (by name), prints its output, and takes its time.
join_stage() {
    finish_stage
    STAGE=$1
    STAGE_T=${BG_T[$1]}
    read -r STAGE_BUSY STAGE_TOTAL <<<"${BG_TICKS[$1]}"
    printf '\n==> %s: waiting for it (started %d s ago)\n' "$1" "$(($(now) - STAGE_T))"
    # The PID stays set while it is waited for: a signal meanwhile stops it (stop_stages).
    # `|| return`: a failure inside a function does not run the ERR trap (no errtrace); so
    # it is returned to the top level, where the trap names the stage and prints the times.
    join_background "${BG_PID[$1]}" "$LOGS/$1.log" || return
    unset "BG_PID[$1]"
}
stop_stages() {
    local name
    for name in "${!BG_PID[@]}"; do stop_background "${BG_PID[$name]}"; done
    BG_PID=()
}
# prepare's build, while it runs in the background.
BUILD_PID=
stop_build() {
    stop_background "$BUILD_PID"
    BUILD_PID=
}
on_error() {
    local rc=$?
    stop_build
    printf '\n==> FAILED (exit %s): %s\n' "$rc" "$STAGE" >&2
    stop_stages
    finish_stage
    print_times >&2
}
trap on_error ERR
trap 'stop_build; stop_stages; exit 130' INT TERM HUP

if wanted prepare; then
    stage prepare "toolchain $(rustc --version); target $THUMB; .venv; the binaries the Python stages run"
    rustup component add rustfmt clippy >/dev/null
    rustup target add "$THUMB"
    # boardsim links the Unicorn CPU emulator, whose C cmake builds and whose bindings bindgen
    # generates with libclang: as root, Debian's cmake and libclang-dev when missing.
    if ! { command -v cmake >/dev/null && compgen -G '/usr/lib/llvm-*/lib/libclang.so*' >/dev/null; } &&
        [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends cmake libclang-dev
    fi
    # The binaries the Python stages run, built while pip installs (one is CPU, the other the
    # network): once, in the profile every Rust stage below shares (`ci`, Cargo.toml),
    # optimised, as the vcan lane's runner and plant must be (a 1 kHz loop on an emulated
    # CPU); `cargo test` reuses these crates instead of compiling them again. For that their
    # features must be the test build's: the whole workspace is resolved (boardsim's
    # defmt-decoder adds features to serde_json and log) with the dev-dependencies (tempfile,
    # criterion and proptest add some to rustix and either), which resolver 2 brings in only
    # for a target that needs them, as the kinematics example does. Built with three packages'
    # features, nearly every crate under the binaries was compiled again: 187 s of CPU.
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER \
        cargo build --profile ci --locked --all-features --workspace --bin hostsim \
        --bin mecanum-runner --bin mecanum-codec --example drive \
        >"$LOGS/prepare-build.log" 2>&1 &
    BUILD_PID=$!
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
    # message packages, as wheels from PyPI (x86-64 Linux; some 150 MB in .venv); and its ray
    # extra, for `mecanum-drive sweep --ray`'s tests on a local cluster (some 280 MB). Without
    # --force-reinstall pip leaves what is installed alone: only the first run downloads them.
    .venv/bin/python -m pip install --quiet --disable-pip-version-check './python[ros2,ray]'
    # The project's own Python package (python/), as a user installs it: its wheel carries the
    # robot DBC from dbc/. Reinstalled every run, so the tests see this checkout's code.
    .venv/bin/python -m pip install --quiet --disable-pip-version-check --force-reinstall --no-deps ./python
    # The PID stays set while it is waited for: a signal meanwhile stops the build (stop_build).
    join_background "$BUILD_PID" "$LOGS/prepare-build.log"
    BUILD_PID=
fi
export HOSTSIM="$PWD/target/ci/hostsim" MECANUM_RUNNER="$PWD/target/ci/mecanum-runner" \
    MECANUM_CODEC="$PWD/target/ci/mecanum-codec"

if wanted vcan; then
    stage vcan "starting the vcan lane in the background (output when it ends; $LOGS/vcan.log)"
    # Tests on a real SocketCAN interface: natively where the kernel has vcan, else in a QEMU
    # micro-VM (scripts/vcan.sh says how). With CI=true a lane that cannot run fails.
    # -s: the tests print their measured figures. Its own stage time is taken when it ends.
    # The test modules compiled here, as pytest rewrites them, before the lane starts: the
    # guest finds them in tests/__pycache__ instead of compiling them on its emulated CPU.
    # The guest then collects only the modules that hold a vcan test (the same tests): their
    # imports, not every module's, on the emulated CPU (natively 2.6 s of CPU against 4.3 s).
    collected=$(.venv/bin/python -m pytest tests -m vcan -q --collect-only -p no:cacheprovider)
    mapfile -t lane_modules < <(sed -n 's/::.*//p' <<<"$collected" | sort -u)
    [ ${#lane_modules[@]} -gt 0 ] || { echo "test.sh: no vcan test collected:" >&2; echo "$collected" >&2; exit 1; }
    # The lane's limits, in wall time, from what it measured on the 2-core reference machine
    # (docs/reliability.md, "Where the suite's time goes"): 612 s alone, its longest test (the
    # ROS 2 session) 100-130 s, when they were set; two and a half times the one, three times
    # the other. Kept since the lane fell to 455 s (its longest test 83 s): on the same
    # machine's slow evenings (its emulator three times slower) the lane took 1,069-1,124 s
    # idle and 1,096 s beside stress-ng, some 400 s under the limit. The lane keeps its core on a
    # busy machine (the stages below run niced), so only a hang reaches them; then the lane
    # names the test and what the guest did. A slower emulator is not a hang: the limits were
    # set for 3.6 wall seconds per guest second (the slow evenings' tests ran 3.35-3.58), and
    # when the tests so far ran slower, both grow in proportion (VCAN_LIMITS_PACE).
    # (pytest-xdist, the python stage's, is not loaded there: its import costs the guest's CPU.)
    start_background env VCAN_VM_TIMEOUT="${VCAN_VM_TIMEOUT:-1530}" VCAN_TEST_TIMEOUT="${VCAN_TEST_TIMEOUT:-390}" \
        VCAN_LIMITS_PACE="${VCAN_LIMITS_PACE:-3.6}" \
        scripts/vcan.sh -- .venv/bin/python -m pytest "${lane_modules[@]}" -m vcan -q -s -p no:cacheprovider -rs --color=no \
        -p no:xdist -p no:xdist.looponfail
    # The lane is the critical path and keeps one core; every stage from here on runs at a
    # lower priority (niceness 10), so a busy machine stretches the build, not the lane.
    [ "$(nice)" -ge 10 ] || renice -n 10 -p $$ >/dev/null || true
fi

if wanted fmt; then
    stage fmt "cargo fmt --check (workspace and both boards)"
    cargo fmt --all -- --check
    cargo fmt --check --manifest-path "$BOARD/Cargo.toml"
    cargo fmt --check --all --manifest-path "$QEMU_BOARD/Cargo.toml"
fi

# The board crate is its own package (not a workspace member, its own Cargo.lock): its
# commands run from its directory so that its .cargo/config.toml (target, linker script) applies.
if wanted stm32f407; then
    stage stm32f407 "$BOARD: clippy (-D warnings), release builds for config/odrive.toml, config/cia402.toml and config/dji_m3508.toml (the default), flash and RAM (256 KiB, 32 KiB)"
    # Clippy's lints in a release build of the board crate (the wrapper applies to it only; its
    # dependencies build with rustc, as the images below reuse them): `cargo clippy --release`
    # type-checked every dependency a second time, 75 of the stage's 114 s of CPU. That build's
    # image differs from a user's in its symbols' hashes, so it is not kept: every image below
    # is built as a user builds it, and only the board crate rebuilds between them.
    (cd "$BOARD" && RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo build --release --locked)
    # The ODrive image first, kept under its own name for boardsim's tests; then the default,
    # which stays at the path a user flashes.
    RELEASE="$BOARD/target/$THUMB/release"
    (cd "$BOARD" && MECANUM_CONFIG=../../config/odrive.toml cargo build --release --locked)
    cp "$RELEASE/board-stm32f407" "$RELEASE/board-stm32f407-odrive"
    (cd "$BOARD" && MECANUM_CONFIG=../../config/cia402.toml cargo build --release --locked)
    cp "$RELEASE/board-stm32f407" "$RELEASE/board-stm32f407-cia402"
    (cd "$BOARD" && cargo build --release --locked)
    for elf in "$RELEASE/board-stm32f407-odrive" "$RELEASE/board-stm32f407-cia402" "$RELEASE/board-stm32f407"; do
        python3 "$BOARD/size.py" "$elf" --max-flash 262144 --max-ram 32768
    done
fi

if wanted clippy; then
    stage clippy "every target, all features, built with Clippy's lints (-D warnings)"
    # `cargo clippy --all-targets` with code generation: the same lints on the same targets,
    # and the build that rust-tests runs (what `cargo test` builds: examples as programs, not
    # as tests as with --all-targets), then the benchmarks (criterion: built, not run).
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo test --profile ci --workspace --all-features --no-run --locked
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo test --profile ci --workspace --all-features --benches --no-run --locked
fi

if wanted rust-tests; then
    stage rust-tests "cargo test --workspace --all-features (the ci profile)"
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo test --profile ci --workspace --all-features --locked
fi

# In the background from here on, beside the stages below: after the workspace's build, which
# takes the cores the lane leaves, and before the stages that use one core at a time (the
# M4's comparison, rustdoc's dependency checks); they ended with the machine half idle.
if wanted python; then
    stage python "pytest -m 'not vcan' (the binaries built in prepare), a worker per core, in the background ($LOGS/python.log)"
    # Most of these tests wait on the processes they drive: spread over the cores, a module to
    # a worker (its module fixtures built once), the stage took 63 s instead of 101 s.
    start_background .venv/bin/python -m pytest tests -q -m "not vcan" -n auto --dist loadfile
    # Its tests time threads on the wall clock (the package's 50 Hz keep-alive, say): the
    # builds from here on yield to them as they yield to the lane (niceness 15 against 10; a
    # fresh clone's run saw 63 keep-alive frames in 1.5 s instead of 75 at equal niceness).
    [ "$(nice)" -ge 15 ] || renice -n 15 -p $$ >/dev/null || true
fi

if wanted rustdoc; then
    stage rustdoc "-D warnings, default and all features"
    RUSTDOCFLAGS="-D warnings" RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER \
        cargo doc --profile ci --workspace --no-deps --locked
    RUSTDOCFLAGS="-D warnings" RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER \
        cargo doc --profile ci --workspace --no-deps --all-features --locked
fi

if wanted no-std; then
    stage no-std "${NO_STD_CRATES[*]} and firmware --features serde for $THUMB, with Clippy's lints"
    # Type-checked, not compiled: a library's use of std fails there, and the board images
    # (stm32f407, qemu-m4) compile and link both crates for this target already. Linted as
    # the MCU's build sees them (its cfg), which the host's clippy does not.
    for crate in "${NO_STD_CRATES[@]}"; do
        RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo check -p "$crate" --target "$THUMB" --locked
    done
    # The firmware's `serde` feature is no_std too (with `alloc`): a configuration can be
    # deserialized on an MCU that has an allocator.
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER cargo check -p firmware --features serde --target "$THUMB" --locked
fi

# The emulated Cortex-M4 (QEMU mps2-an386) board: its own workspace, like the STM32F407 one.
# The firmware core and a fixed scenario run there and on the host; the outbound frame streams
# must be bit-identical (scripts/xtarget.sh installs qemu-system-arm when root and missing).
if wanted qemu-m4; then
    stage qemu-m4 "$QEMU_BOARD: Cortex-M4 against the host, instructions per step; its three builds (M4, M4 icount, host) with Clippy's lints"
    # The test's builds are the lint check (as the workspace's): nothing of them is flashed.
    # Three `cargo clippy` runs type-checked what they then compile: 37 s of CPU.
    RUSTC_WORKSPACE_WRAPPER=$LINT_WRAPPER scripts/xtarget.sh
fi

# The background stages, the python stage first (it ends sooner).
for name in python vcan; do
    if [ -n "${BG_PID[$name]:-}" ]; then join_stage "$name"; fi
done

finish_stage
print_times
printf '\n==> all checks passed\n'
