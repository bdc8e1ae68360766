#!/usr/bin/env bash
# The project's performance figures in one run, printed as a Markdown table and written as
# the "current figures" at the top of docs/benchmarks.md (with the machine, the date and the
# commit; not with --quick):
#   kinematics full step (f32, f64) and the control step on the host with the DJI, ODrive
#   and CiA 402 examples (criterion medians),
#   the parts of one lockstep period (a frame's length on the wire, a chassis step, a
#   simulated ms of the C620 plant) and the built-in square in process (criterion),
#   instructions per control step on the emulated Cortex-M4 (QEMU, scripts/xtarget.sh; the
#   DJI, ODrive and CiA 402 examples),
#   flash and static RAM of the STM32F407 board build (the default DJI configuration, and
#   config/cia402.toml),
#   simulator real-time factor of the 60 s square with and without MCAP logging, the cost
#   of logging (with / without, interleaved runs) and the log's size,
#   the sweep's throughput, 200 runs of the 60 s square on 1 and on 2 threads,
#   MCAP write throughput against the Python mcap writer on the same frames (ratio),
#   what --log costs the runner's loop per step and the log's size per hour (in process,
#   crates/runner/benches/recorder.rs),
#   frames/s the firmware runner takes on vcan0 without loss (the vcan lane's rate test;
#   natively where the kernel has vcan, else in the micro-VM, which the table says), and
#   the runner's jitter and step time on vcan0 with and without --log, on a quiet bus and
#   under an 8,000 frames/s flood (scripts/runner_log_bench.py).
#
# usage: scripts/bench.sh [--quick] [--no-vcan]
#   --quick     shorter criterion runs, one simulator run each, 200,000 MCAP frames
#   --no-vcan   skip the vcan0 measurement (it boots a VM where the kernel has no vcan)
# Needs what scripts/test.sh installs (the Python .venv, the thumbv7em target, QEMU).
set -euo pipefail
cd "$(dirname "$0")/.."
# Build outputs are read from ./target and the boards' own target/ directories.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET

quick=0 vcan=1
for arg in "$@"; do
    case $arg in
    --quick) quick=1 ;;
    --no-vcan) vcan=0 ;;
    -h | --help) sed -n '2,27p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "bench.sh: unknown argument $arg (see --help)" >&2; exit 2 ;;
    esac
done
if [ "$quick" = 1 ]; then
    crit=(--warm-up-time 1 --measurement-time 2) sim_runs=1 mcap_frames=200000
else
    crit=(--warm-up-time 2 --measurement-time 5) sim_runs=21 mcap_frames=1000000
fi
PY=.venv/bin/python
[ -x "$PY" ] || { echo "bench.sh: no .venv (run scripts/test.sh once, or python3 -m venv .venv && .venv/bin/pip install -r tests/requirements.txt)" >&2; exit 2; }

log() { printf '==> %s\n' "$*" >&2; }
rows=()
row() { rows+=("| $1 | $2 | $3 |"); }
# Median of a criterion benchmark, ns, from its estimates file.
median_ns() {
    "$PY" -c 'import json, sys; print("%.1f" % json.load(open(sys.argv[1]))["median"]["point_estimate"])' \
        "target/criterion/$1/new/estimates.json"
}

log "kinematics (criterion)"
cargo bench --locked -q -p kinematics --bench kinematics -- "${crit[@]}" full_step >&2
f32_ns=$(median_ns f32/full_step) f64_ns=$(median_ns f64/full_step)
row "kinematics full step (inverse, desaturate, forward, odometry), f32" "$f32_ns ns" "criterion median"
row "kinematics full step, f64" "$f64_ns ns" "criterion median"

log "control step (criterion)"
cargo bench --locked -q -p firmware --bench control -- "${crit[@]}" >&2
step_ns=$(median_ns control_step_4_wheels_dji)
row "control step, 4 x C620, enabled and driving (host)" "$step_ns ns" "criterion median"
row "control step, 4 x ODrive, enabled and driving (host)" "$(median_ns control_step_4_wheels_odrive) ns" "criterion median"
row "control step, 2 x dual-axis CiA 402 (250 Hz SYNC), enabled and driving (host)" "$(median_ns control_step_4_wheels_cia402) ns" "criterion median"

log "the lockstep period's parts (criterion): the floor of one run's speed"
cargo bench --locked -q -p hostsim --bench lockstep -- "${crit[@]}" >&2
row "one frame's stuffed length on the wire (frame_bits; about 5.3 a simulated ms)" "$(median_ns frame_bits) ns" "criterion median"
row "one implicit chassis step (at least 2 a simulated ms)" "$(median_ns chassis_step) ns" "criterion median"
row "one simulated ms of the C620 plant (2 chassis steps, 8 drive steps, 4 feedback frames)" "$(median_ns dji_plant_period) ns" "criterion median"
# Simulated over wall time: the built-in square's length as the simulator reports it.
cargo build --release --locked -q -p hostsim --bin hostsim
square_out=$(mktemp -d)
square_s=$(target/release/hostsim run square --no-log --no-plot --json --out "$square_out" |
    "$PY" -c 'import json, sys; print(json.load(sys.stdin)["duration_s"])')
rm -rf "$square_out"
row "built-in square (${square_s} s) in process, no log" "$("$PY" -c "import sys; print(f'{float(sys.argv[1]) * 1e9 / float(sys.argv[2]):,.0f}x')" "$square_s" "$(median_ns run/square)")" "real-time factor"

log "instructions per control step on the emulated Cortex-M4"
xt=$(scripts/xtarget.sh 2>&1 | tee /dev/stderr)
while IFS= read -r line; do
    setup=$(sed -n 's/.*Cortex-M4, \([^,]*\),.*/\1/p' <<<"$line")
    row "instructions per control step, Cortex-M4 (QEMU), $setup" "$(sed -n 's/.*: mean \([0-9]*\), min \([0-9]*\), max \([0-9]*\)/\1 (min \2, max \3)/p' <<<"$line")" "instructions"
done < <(grep '^instructions per control step' <<<"$xt")

log "STM32F407 board: flash and static RAM (the default configuration and config/cia402.toml)"
# The CiA 402 image first, kept under its own name as scripts/test.sh keeps the ODrive one;
# then the default, which stays at the path a user flashes. Only the board crate rebuilds.
release=boards/stm32f407/target/thumbv7em-none-eabihf/release
(cd boards/stm32f407 && MECANUM_CONFIG=../../config/cia402.toml cargo build --release --locked -q)
cp "$release/board-stm32f407" "$release/board-stm32f407-cia402"
(cd boards/stm32f407 && cargo build --release --locked -q)
board_rows() { # elf, "flash" row, "RAM" row
    local size
    size=$(python3 boards/stm32f407/size.py "$1")
    row "$2" "$(sed -n 's/^flash: \([0-9]*\) bytes.*/\1/p' <<<"$size") B" "bytes"
    row "$3" "$(sed -n 's/^RAM: *\([0-9]*\) bytes.*/\1/p' <<<"$size") B" "bytes"
}
board_rows "$release/board-stm32f407" "board flash (STM32F407, release, LTO)" "board static RAM"
board_rows "$release/board-stm32f407-cia402" "board flash, config/cia402.toml" \
    "board static RAM, config/cia402.toml"

log "simulator real-time factor (60 s square, best of $sim_runs, interleaved)"
sim=$(scripts/bench-sim.sh "$sim_runs" | tee /dev/stderr)
row "simulator, 60 s square at 1 kHz, 4 x C620, MCAP logging" "$(grep '^| MCAP' <<<"$sim" | awk -F'|' '{gsub(/ /,"",$4); print $4}')" "real-time factor"
row "simulator, same, no logging" "$(grep '^| none' <<<"$sim" | awk -F'|' '{gsub(/ /,"",$4); print $4}')" "real-time factor"
row "simulator, cost of MCAP logging (wall time with / without, interleaved; median of the pairs)" "$(grep '^| cost of logging (with / without), median' <<<"$sim" | awk -F'|' '{gsub(/ /,"",$3); print $3}')" "ratio"
row "simulator, cost of MCAP logging (best with / best without)" "$(grep '^| cost of logging, best' <<<"$sim" | awk -F'|' '{gsub(/ /,"",$3); print $3}')" "ratio"
row "60 s square's MCAP log (ROS 2 messages, every frame once, zstd)" "$(sed -n 's/^| MCAP (ROS 2 messages, zstd), \([0-9.]*\) MB.*/\1/p' <<<"$sim") MB" "MB"

log "sweep throughput: 200 runs of the 60 s square without logs, 1 thread against 2"
cargo build --release --locked -q -p hostsim --bin hostsim
sweep_dir=$(mktemp -d)
sweep_s() {
    local t0 t1
    t0=$(date +%s.%N)
    target/release/hostsim sweep scenarios/square_60s.toml --seeds 1..200 --jobs "$1" \
        --no-plot --worst 0 --out "$sweep_dir/j$1" >/dev/null 2>&1
    t1=$(date +%s.%N)
    "$PY" -c "print(f'{$t1 - $t0:.2f}')"
}
one=$(sweep_s 1) two=$(sweep_s 2)
cmp -s "$sweep_dir/j1/sweep.csv" "$sweep_dir/j2/sweep.csv" || { echo "bench.sh: the sweep's tables differ between 1 and 2 threads" >&2; exit 1; }
rm -rf "$sweep_dir"
row "sweep, 200 runs of the 60 s square, 1 thread" "$one s" "wall time"
row "sweep, same, 2 threads (the same table)" "$two s" "wall time"
row "sweep speed-up, 2 threads / 1" "$("$PY" -c "print(f'{$one / $two:.2f}x')")" "ratio"

log "MCAP write throughput: Rust (McapLog) against the Python mcap writer, $mcap_frames frames"
cargo build --release --locked -q -p hostsim --example mcap_throughput
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rust=$(target/release/examples/mcap_throughput "$mcap_frames" "$work/rust.mcap")
python=$("$PY" scripts/mcap_throughput.py "$mcap_frames" "$work/python.mcap")
read -r rust_fps python_fps ratio < <("$PY" -c '
import json, sys
r, p = json.loads(sys.argv[1])["frames_per_s"], json.loads(sys.argv[2])["frames_per_s"]
print(f"{r:,.0f} {p:,.0f} {r / p:.1f}")' "$rust" "$python")
row "MCAP frames written per second, Rust McapLog" "$rust_fps" "frames/s"
row "MCAP frames written per second, Python mcap writer" "$python_fps" "frames/s"
row "MCAP write throughput, Rust / Python" "${ratio}x" "ratio"

if [ "$vcan" = 1 ]; then
    log "vcan0: frames/s the runner takes without loss (the vcan lane's rate test)"
    cargo build --release --locked -q -p mecanum-runner
    # The test prints its `rate:` line before it checks for loss: the figure counts only when
    # the lane passed (pipefail: the status is vcan.sh's, not tee's).
    lane_rc=0
    out=$(MECANUM_RUNNER="$PWD/target/release/mecanum-runner" scripts/vcan.sh -- \
        "$PY" -m pytest tests/test_vcan_runner.py -q -s -p no:cacheprovider -k test_rate_ 2>&1 | tee /dev/stderr) ||
        lane_rc=$?
    where=native
    grep -q 'vcan.sh: vm:' <<<"$out" && where="micro-VM, software-emulated CPU"
    line=$(grep '^rate: ' <<<"$out" | tail -1 || true)
    if [ -n "$line" ] && [ "$lane_rc" != 0 ]; then
        row "vcan0 frames/s into the runner" "FAILED (the rate test exited $lane_rc; its output is above)" ""
    elif [ -n "$line" ]; then
        row "vcan0 frames/s into the runner, 30 s, no loss ($where)" "$(sed -n 's/.* = \([0-9]*\) frames\/s.*/\1/p' <<<"$line")" "frames/s"
        row "runner loop jitter during it ($where)" "$(sed -n 's/.*jitter \(p50 .*\)/\1/p' <<<"$line")" "µs"
    else
        row "vcan0 frames/s into the runner" "not measured: $(grep -m1 -E 'SKIP|FAIL|failed|Error' <<<"$out" || echo 'no figure printed')" ""
    fi
fi

log "what --log costs the runner's loop (per step, in process)"
rec=$(cargo bench --locked -q -p mecanum-runner --bench recorder 2>/dev/null | tee /dev/stderr)
row "runner loop thread per step, no log (paced 1 kHz, in process)" "$(sed -n 's/.*no log: *//p' <<<"$rec")" "µs"
row "runner loop thread per step, --log" "$(sed -n 's/.*--log: *//p' <<<"$rec")" "µs"
row "logging cost per step (loop thread)" "$(sed -n 's/.*logging cost per step: //p' <<<"$rec")" "µs"
row "runner log size, DJI x 4 at 1 kHz (in process)" "$(sed -n 's/.*= \([0-9]*\) MB per hour.*/\1/p' <<<"$rec")" "MB/h"

if [ "$vcan" = 1 ]; then
    log "vcan0: the runner's jitter and step time with and without --log, quiet and flooded"
    cargo build --release --locked -q -p hostsim --bin hostsim
    lane_rc=0
    out=$(HOSTSIM="$PWD/target/release/hostsim" MECANUM_RUNNER="$PWD/target/release/mecanum-runner" \
        scripts/vcan.sh -- "$PY" scripts/runner_log_bench.py 2>&1 | tee /dev/stderr) || lane_rc=$?
    if [ "$lane_rc" = 0 ]; then
        while IFS= read -r line; do rows+=("$line"); done < <(grep '^| runner at 1 kHz' <<<"$out")
    else
        row "runner jitter with and without --log on vcan0" "FAILED (exit $lane_rc; the output is above)" ""
    fi
fi

table=$(
    printf '%s, %s, %s cores (%s), Linux %s, %s, commit %s%s.\n\n' "$(date -u +%Y-%m-%d)" \
        "$(sed -n 's/^model name\s*: //p' /proc/cpuinfo | head -1)" "$(nproc)" \
        "$(grep -q hypervisor /proc/cpuinfo && echo VM || echo bare metal)" "$(uname -r)" \
        "$(rustc --version)" "$(git rev-parse --short HEAD)" "$(git diff --quiet HEAD || echo ' with changes')"
    echo "| figure | value | unit |"
    echo "|---|---|---|"
    printf '%s\n' "${rows[@]}"
)
printf '\n%s\n' "$table"
# The current figures at the top of docs/benchmarks.md are this table; the dated sections
# below them are the history (--quick figures are not written there).
if [ "$quick" = 0 ]; then
    "$PY" - docs/benchmarks.md "$table" <<'PY'
import sys
path, table = sys.argv[1], sys.argv[2]
begin, end = "<!-- current-figures:begin -->\n", "<!-- current-figures:end -->"
doc = open(path).read()
b, e = doc.index(begin) + len(begin), doc.index(end)
open(path, "w").write(doc[:b] + table + "\n" + doc[e:])
PY
    log "wrote the current figures into docs/benchmarks.md"
fi
