#!/usr/bin/env bash
# Fuzz the frame decoders, the control core, the configuration and scenario loaders, the candump
# parser, the MCAP reading path and hostsim's command line with cargo-fuzz (libFuzzer, nightly
# toolchain). See docs/reliability.md.
#
# usage: scripts/fuzz.sh [--runs N] [SECONDS_PER_TARGET] [TARGET...]
#
#   SECONDS_PER_TARGET  wall-time budget of each target (-max_total_time); default 60, or no
#                       time limit when --runs is given
#   --runs N            stop each target after N executions (-runs=N), e.g. --runs 10000000
#   TARGET...           default: every target in fuzz/fuzz_targets/
#
# Environment: SANITIZER (default none: the crates forbid unsafe code; `address` for ASan),
# FUZZ_ARGS (extra libFuzzer flags). Each target runs as one libFuzzer process, on one core
# (no -jobs/-workers: with them libFuzzer forks a child that writes fuzz-N.log files).
#
# Corpora live in fuzz/corpus/<target>/ (git-ignored); seeds are regenerated on every run
# (a real hostsim MCAP log and truncations of it, the example configurations, candump lines
# of the codec's golden frames, a hostsim argument vector per subcommand; hostsim_args gets a
# dictionary of its options too). Crash inputs land in fuzz/artifacts/<target>/; libFuzzer
# logs in fuzz/target/fuzz-logs/. Exits non-zero if any target crashed, panicked, timed out
# or ran out of memory.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
fuzz="$root/fuzz"
cd "$root"
# Build outputs are read from ./target and fuzz/target.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET

runs=""
seconds=""
targets=()
while (($#)); do
    case "$1" in
    --runs)
        runs="${2:?--runs needs a number}"
        shift 2
        ;;
    --runs=*)
        runs="${1#--runs=}"
        shift
        ;;
    -h | --help)
        sed -n '2,22p' "$0" | sed 's/^# \{0,1\}//'
        exit 0
        ;;
    *)
        if [[ -z "$seconds" && ${#targets[@]} -eq 0 && "$1" =~ ^[0-9]+$ ]]; then
            seconds="$1"
        else
            targets+=("$1")
        fi
        shift
        ;;
    esac
done
if [[ -z "$runs" && -z "$seconds" ]]; then
    seconds=60
fi
if ((${#targets[@]} == 0)); then
    for f in "$fuzz"/fuzz_targets/*.rs; do
        targets+=("$(basename "$f" .rs)")
    done
fi
for t in "${targets[@]}"; do
    [[ -f "$fuzz/fuzz_targets/$t.rs" ]] || {
        echo "fuzz.sh: no target '$t' in fuzz/fuzz_targets/" >&2
        exit 2
    }
done

if ! cargo +nightly --version >/dev/null 2>&1; then
    echo "fuzz.sh: needs the nightly toolchain (rustup toolchain install nightly)" >&2
    exit 2
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "fuzz.sh: installing cargo-fuzz from crates.io" >&2
    cargo install cargo-fuzz --locked
fi

sanitizer="${SANITIZER:-none}"
logs="$fuzz/target/fuzz-logs"
mkdir -p "$logs"

# --- seeds ------------------------------------------------------------------------------------

seed_dir() { mkdir -p "$fuzz/corpus/$1" && echo "$fuzz/corpus/$1"; }

wants() {
    local t
    for t in "${targets[@]}"; do [[ "$t" == "$1" ]] && return 0; done
    return 1
}

if wants scenario_toml; then
    d=$(seed_dir scenario_toml)
    for f in "$root"/scenarios/*.toml "$root"/tests/bad_input/files/*.toml; do cp "$f" "$d/seed-$(basename "$f")"; done
    printf 'name = "s"\nduration_s = 0.02\n[[actions]]\nat_s = 0.005\nenable = true\n[[actions]]\nat_s = 0.01\ntwist = [0.5, 0.1, 0.2]\n' >"$d/seed-short.toml"
fi
if wants sweep_args; then
    d=$(seed_dir sweep_args)
    printf '1..200\0gains.kp=0.8,1.0,1.2' >"$d/seed-grid"
    printf '1,5,9\0plant.mass_kg=18..24\0gains.ki=20,30' >"$d/seed-draw"
    printf '0..18446744073709551615\0pods.scale=0.99..1.01' >"$d/seed-huge"
fi
if wants hostsim_args; then
    d=$(seed_dir hostsim_args)
    # Argument vectors after `hostsim`, NUL-separated, as a user types them; paths are the
    # repository's (the target runs in it).
    seed() { local name=$1; shift; printf '%s\0' "$@" | head -c -1 >"$d/seed-$name"; }
    seed run run
    seed run-file run scenarios/faults.toml --config config/odrive.toml --seed 3 \
        --set gains.kp=1.2 --set plant.mass_kg=22 --no-plot --json --progress-lines
    seed run-live run circle --live 127.0.0.1:0 --rate 0.5 --live-can-hz 100 \
        --live-max-clients 4 --live-max-subscriptions 16 --out out/fuzz
    seed sweep sweep square --seeds 1..200 --set gains.kp=0.8,1.0,1.2 \
        --set plant.mass_kg=18..24 --jobs 2 --worst 3 --log-worst 1 --no-plot --out out/sweep
    seed sweep-file sweep scenarios/square_60s.toml --config config/dji_m3508.toml --seeds 1,5,9
    seed sweep-huge sweep spin --seeds 0..=999999 --set gains.ki=20,30
    seed check check --config config/odrive.toml --flip FL --swap FR,RL --speed -3 \
        --duration-ms 500 --json
    seed plant plant --iface vcan0 --config config/dji_m3508_pods3.toml --pods --imu \
        --imu-bias-deg-s 0.2 --duration 2.5 --spin-us 200 --log out/plant.mcap --live 8765 \
        --lifted --stats-json out/stats.json -q
    seed replay replay out/square.mcap --json
    seed replay-candump replay tests/bad_input/files/garbage.candump --config config/odrive.toml \
        --position-tolerance 0.02 --heading-tolerance 0.05
    seed replay-play replay out/square.mcap --iface vcan0 --speed 2 --only all
    seed summary summary out/square.mcap
    seed calibrate calibrate out/calibration.mcap --reference /tracker/pose --window 0.2 \
        --write cal.toml --json
    seed plot plot out/calibration.mcap recal/calibration.mcap --out cmp.png
    seed kin kin
    seed help help sweep
    seed version --version
fi
if wants config_toml; then
    d=$(seed_dir config_toml)
    for f in "$root"/config/*.toml; do cp "$f" "$d/seed-$(basename "$f")"; done
fi

if wants candump_parse; then
    d=$(seed_dir candump_parse)
    # Every golden frame of the codecs, as a candump -L log 1 ms apart...
    cargo run -q --release -p mecanum-codec -- golden |
        sed -n 's/.*"candump":"\([^"]*\)".*/\1/p' |
        awk '{ printf "(1700000000.%06d) vcan0 %s\n", NR * 1000, $0 }' >"$d/seed-golden.log"
    # ...and the notations the parser knows (remote, dots, direction, extended, FD, XL).
    cat >"$d/seed-notations.log" <<'EOF'
(1700000000.000000) vcan0 302#01 R
(1700000000.000100) can0 301#F4.01.06.FF.E8.03.07.00 T
(1700000000.000200) vcan0 023#R
(1700000000.000300) vcan0 023#R8

(1700000000.000400) vcan0 12345678#DEADBEEF
(1700000000.000500) vcan0 123##1DEADBEEF
(1700000000.000600) vcan0 123###DEADBEEF
(1700000000.000700) vcan0 201#1FFF03E8FC180019_9
EOF
fi

if wants mcap_read; then
    d=$(seed_dir mcap_read)
    tmp=$(mktemp -d)
    trap 'rm -rf "$tmp"' EXIT
    cat >"$tmp/short.toml" <<'EOF'
name = "fuzz-seed"
duration_s = 0.2
seed = 1
command_hz = 50.0

[[actions]]
at_s = 0.02
enable = true

[[actions]]
at_s = 0.05
twist = [0.3, 0.1, 0.2]
EOF
    cargo build -q --release -p hostsim
    hostsim="$root/target/release/hostsim"
    "$hostsim" run circle --out "$tmp/circle" --no-plot >/dev/null
    "$hostsim" run "$tmp/short.toml" --out "$tmp/dji" --no-plot >/dev/null
    "$hostsim" run "$tmp/short.toml" --config "$root/config/odrive.toml" --out "$tmp/odrive" \
        --no-plot >/dev/null
    cp "$tmp/dji/fuzz-seed.mcap" "$d/seed-short-dji.mcap"
    cp "$tmp/odrive/fuzz-seed.mcap" "$d/seed-short-odrive.mcap"
    # The full circle log is megabytes (too slow per execution): its first bytes, cut
    # mid-record as a killed run leaves them.
    for n in 4096 16384 65536; do
        head -c "$n" "$tmp/circle/circle.mcap" >"$d/seed-circle-$n.mcap"
    done
    head -c 20000 "$tmp/dji/fuzz-seed.mcap" >"$d/seed-short-dji-cut.mcap"
fi

# --- build and run ----------------------------------------------------------------------------

cd "$fuzz"
echo "fuzz.sh: building ${#targets[@]} target(s) (sanitizer $sanitizer)" >&2
all=$(find fuzz_targets -name '*.rs' | wc -l)
if ((${#targets[@]} == all)); then
    build=("")
else
    build=("${targets[@]}")
fi
for t in "${build[@]}"; do
    # `cargo fuzz build` builds one target, or every target when given none.
    # shellcheck disable=SC2086
    if ! cargo +nightly fuzz build -s "$sanitizer" $t >"$logs/build.log" 2>&1; then
        cat "$logs/build.log" >&2
        exit 2
    fi
done

max_len_for() {
    case "$1" in
    mcap_read) echo 131072 ;;
    config_toml | candump_parse | scenario_toml) echo 8192 ;;
    *) echo 4096 ;;
    esac
}

# Dictionaries: hostsim's options and names (fuzz/hostsim_args.dict, kept up to date from its
# clap definition by a unit test), with the repository's configuration and scenario files.
dict_for() {
    case "$1" in
    hostsim_args)
        local dict="$fuzz/target/hostsim_args.dict"
        {
            cat "$fuzz/hostsim_args.dict"
            for f in "$root"/config/*.toml "$root"/scenarios/*.toml; do
                printf '"%s"\n' "${f#"$root"/}"
            done
        } >"$dict"
        echo "$dict"
        ;;
    esac
}

failed=0
rows=()
for t in "${targets[@]}"; do
    corpus=$(seed_dir "$t")
    artifacts="$fuzz/artifacts/$t"
    mkdir -p "$artifacts"
    before=$(find "$artifacts" -type f | wc -l)
    args=(-print_final_stats=1 -timeout=10 -max_len="$(max_len_for "$t")"
        -artifact_prefix="$artifacts/")
    dict=$(dict_for "$t")
    [[ -n "$dict" ]] && args+=(-dict="$dict")
    [[ -n "$seconds" ]] && args+=(-max_total_time="$seconds")
    [[ -n "$runs" ]] && args+=(-runs="$runs")
    # shellcheck disable=SC2206
    args+=(${FUZZ_ARGS:-})
    echo "fuzz.sh: $t ${args[*]}" >&2
    start=$(date +%s)
    status=0
    cargo +nightly fuzz run -s "$sanitizer" "$t" "$corpus" -- "${args[@]}" \
        >"$logs/$t.log" 2>&1 || status=$?
    wall=$(($(date +%s) - start))
    after=$(find "$artifacts" -type f | wc -l)
    crashes=$((after - before))
    if ((status != 0 || crashes > 0)); then
        failed=1
        grep -E "panicked|ERROR: libFuzzer|SUMMARY|Test unit written" "$logs/$t.log" >&2 || true
    fi
    final_stat() { sed -n "s/^stat::$1: *//p" "$logs/$t.log" | tail -1; }
    execs=$(final_stat number_of_executed_units)
    rate=$(final_stat average_exec_per_sec)
    done_line=$(grep -E "^#[0-9]+[[:space:]]+DONE" "$logs/$t.log" | tail -1 || true)
    cov=$(sed -n 's/.*cov: \([0-9]*\).*/\1/p' <<<"$done_line")
    ft=$(sed -n 's/.*ft: \([0-9]*\).*/\1/p' <<<"$done_line")
    files=$(find "$corpus" -type f | wc -l)
    rows+=("$(printf '%-18s %13s %10s %6s %7s %8s %7s %6s %s' "$t" "${execs:--}" "${rate:--}" \
        "${cov:--}" "${ft:--}" "$files" "$crashes" "${wall}s" "exit $status")")
done

printf '\n%-18s %13s %10s %6s %7s %8s %7s %6s %s\n' target executions exec/s cov ft corpus \
    crashes wall status
printf '%s\n' "${rows[@]}"
echo "nightly: $(cargo +nightly --version); sanitizer: $sanitizer; logs: fuzz/target/fuzz-logs/"
if ((failed)); then
    echo "fuzz.sh: FAILED: crash inputs are in fuzz/artifacts/<target>/" >&2
    exit 1
fi
