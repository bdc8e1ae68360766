#!/usr/bin/env bash
# Real-time factor of the simulator: the 60 s square (scenarios/square_60s.toml) at 1 kHz with
# four C620 drives, with and without MCAP logging, the runs interleaved (with, without, with,
# ...) so that both see the same machine. Best of N runs each (default 21), since other load
# on the machine only ever slows a run down. Prints a table for docs/benchmarks.md: wall
# times, real-time factors, the log's size, and the cost of logging: the median of the N
# pairs' ratios (with / its own without), which a noisy host moves less than the ratio of
# the best times, printed beside it.
#
# usage: scripts/bench-sim.sh [RUNS]
set -euo pipefail
cd "$(dirname "$0")/.."
# Build outputs are read from ./target and the boards' own target/ directories.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET
runs=${1:-21}
cargo build --release --locked -p hostsim --bin hostsim >&2
bin=target/release/hostsim
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

wall() { # wall time (s) of: hostsim run ... --json
    "$bin" run scenarios/square_60s.toml --out "$out" --no-plot --json "$@" |
        python3 -c 'import json,sys; print(json.load(sys.stdin)["wall_s"])'
}

with_log=() without_log=()
for _ in $(seq "$runs"); do
    with_log+=("$(wall)")
    without_log+=("$(wall --no-log)")
done
size=$(stat -c %s "$out/square-60s.mcap")
python3 - "${with_log[*]}" "${without_log[*]}" "$size" "$runs" <<'PY'
import statistics
import sys
ws, wos = ([float(x) for x in a.split()] for a in sys.argv[1:3])
w, wo = min(ws), min(wos)
pairs = statistics.median(a / b for a, b in zip(ws, wos))
size, runs = int(sys.argv[3]), sys.argv[4]
print(f"60 s square, 1 kHz, 4 x C620; best of {runs} runs")
print(f"| logging | wall time | real-time factor |")
print(f"|---|---|---|")
print(f"| MCAP (ROS 2 messages, zstd), {size/1e6:.2f} MB | {w:.3f} s | {60/w:,.0f}x |")
print(f"| none | {wo:.3f} s | {60/wo:,.0f}x |")
print(f"| cost of logging (with / without), median of the pairs | {pairs:.2f}x | |")
print(f"| cost of logging, best with / best without | {w/wo:.2f}x | |")
PY
