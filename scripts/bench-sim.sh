#!/usr/bin/env bash
# Real-time factor of the simulator: the 60 s square (scenarios/square_60s.toml) at 1 kHz with
# four C620 drives, with and without MCAP logging. Best of N runs (default 3), since other
# load on the machine only ever slows a run down. Prints a table for docs/benchmarks.md.
#
# usage: scripts/bench-sim.sh [RUNS]
set -euo pipefail
cd "$(dirname "$0")/.."
# Build outputs are read from ./target and the boards' own target/ directories.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET
runs=${1:-3}
cargo build --release --locked -p hostsim --bin hostsim >&2
bin=target/release/hostsim
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

best() { # best wall time (s) of $runs runs of: hostsim run ... --json
    local best=""
    for _ in $(seq "$runs"); do
        local wall
        wall=$("$bin" run scenarios/square_60s.toml --out "$out" --no-plot --json "$@" |
            python3 -c 'import json,sys; print(json.load(sys.stdin)["wall_s"])')
        best=$(python3 -c "print(min(float('$wall'), float('${best:-inf}')))")
    done
    echo "$best"
}

with_log=$(best)
without_log=$(best --no-log)
size=$(stat -c %s "$out/square-60s.mcap")
python3 - "$with_log" "$without_log" "$size" "$runs" <<'PY'
import sys
w, wo, size, runs = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
print(f"60 s square, 1 kHz, 4 x C620; best of {runs} runs")
print(f"| logging | wall time | real-time factor |")
print(f"|---|---|---|")
print(f"| MCAP (zstd), {size/1e6:.1f} MB | {w:.3f} s | {60/w:,.0f}x |")
print(f"| none | {wo:.3f} s | {60/wo:,.0f}x |")
PY
