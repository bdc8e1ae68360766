#!/usr/bin/env bash
# Cross-target determinism: the firmware core and a fixed scenario (boards/qemu-m4/scenario:
# scripted host commands and plant, 3,000 steps at 1 kHz, DJI, ODrive and CiA 402
# configurations, and DJI with tracking pods) run on an emulated Cortex-M4 (QEMU
# mps2-an386, thumbv7em-none-eabihf, semihosting) and on the host; their reports (outbound frame count, FNV-1a 64 hash,
# checkpoints every 100 steps, every 100th frame, final pose bits) must be byte-identical.
# Then counts the instructions per control step on the emulated Cortex-M4 from QEMU's
# execution trace.
#
# Installs qemu-system-arm with apt-get when it is missing and the script runs as root.
# RUSTC_WORKSPACE_WRAPPER, when set, applies to the board's crates in every build: scripts/test.sh
# sets Clippy's (scripts/clippy-rustc.sh), so the three builds are also the lint check.
#
# usage: scripts/xtarget.sh [--no-icount]
#   --no-icount   skip the instruction count (the determinism check only)
# Exit status: 0 when bit-identical; 1 on a difference (the first one is printed); 2 on a
# setup or build error.
set -euo pipefail
cd "$(dirname "$0")/.."
# Build outputs are read from ./target and the boards' own target/ directories.
unset CARGO_TARGET_DIR CARGO_BUILD_TARGET

icount=1
case "${1:-}" in
    "") ;;
    --no-icount) icount=0 ;;
    -h | --help) sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "usage: $0 [--no-icount] (see --help)" >&2; exit 2 ;;
esac

THUMB=thumbv7em-none-eabihf
BOARD=boards/qemu-m4
HOST=$(rustc -vV | sed -n 's/^host: //p')
QEMU=(qemu-system-arm -cpu cortex-m4 -machine mps2-an386 -nographic
      -semihosting-config enable=on,target=native)
# A hung guest must not hang CI: the full scenario takes well under a second under QEMU.
QEMU_TIMEOUT=${QEMU_TIMEOUT:-120}

stage() { printf '\n==> %s\n' "$*" >&2; }
die() { echo "xtarget: $*" >&2; exit 2; }

if ! command -v qemu-system-arm >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        stage "installing qemu-system-arm (apt-get)"
        apt-get update -qq >&2
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
            qemu-system-arm >&2
    else
        die "qemu-system-arm not found (Debian/Ubuntu: apt-get install qemu-system-arm)"
    fi
fi
qemu_version=$(qemu-system-arm --version | sed -n '1s/^QEMU emulator version //p')
rustup target add "$THUMB" >/dev/null 2>&1 || true

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# Both binaries come from one workspace (boards/qemu-m4, one Cargo.lock, one release
# profile). The board's .cargo/config.toml makes thumbv7em the default target there; the host
# binary gets an explicit --target. Feature variants of the M4 binary use their own target
# directories so that switching between them does not rebuild the default one.
build_m4() { # [target dir] [features]
    local dir=${1:-target} features=${2:-}
    (cd "$BOARD" && CARGO_TARGET_DIR=$dir cargo build --release --locked \
        ${features:+--features "$features"} >&2) || return 1
    echo "$BOARD/$dir/$THUMB/release/board-qemu-m4"
}
build_host() {
    (cd "$BOARD" && cargo build --release --locked -p xtarget-scenario --target "$HOST" >&2) ||
        return 1
    echo "$BOARD/target/$HOST/release/xtarget-host"
}
run_m4() { # elf [extra qemu args...]
    local elf=$1
    shift
    timeout "$QEMU_TIMEOUT" "${QEMU[@]}" "$@" -kernel "$elf"
}

stage "build: $THUMB (board-qemu-m4) and $HOST (xtarget-host)"
m4_elf=$(build_m4) || die "M4 build failed"
host_bin=$(build_host) || die "host build failed"

stage "run: QEMU $qemu_version (mps2-an386, Cortex-M4) and the host"
run_m4 "$m4_elf" >"$work/m4.txt" || die "the M4 run failed (exit $?); output: $(tail -3 "$work/m4.txt")"
"$host_bin" >"$work/host.txt" || die "the host run failed"

total=$(grep '^total ' "$work/host.txt" || true)
[ -n "$total" ] || die "the host report has no total line"
if cmp -s "$work/m4.txt" "$work/host.txt"; then
    frames=$(sed -n 's/^total frames=\([0-9]*\) .*/\1/p' <<<"$total")
    hash=$(sed -n 's/.* hash=\([0-9a-f]*\)$/\1/p' <<<"$total")
    per_setup=$(sed -n 's/^end \([a-z0-9]*\) frames=\([0-9]*\) hash=\([0-9a-f]*\).*/\1: \2 frames, hash \3/p' \
        "$work/host.txt" | paste -sd ';' | sed 's/;/; /g')
    echo "bit-identical: $frames frames, hash $hash ($per_setup); Cortex-M4 (QEMU $qemu_version) = $HOST"
else
    echo "DIFFERENCE between the Cortex-M4 (QEMU) and the host ($HOST) reports:"
    diff --label Cortex-M4 --label host -U0 "$work/m4.txt" "$work/host.txt" | sed -n '1,12p' ||
        true
    stage "locating the first differing frame (every frame printed on both sides)"
    m4_all=$(build_m4 target/every-frame every-frame) || die "M4 build (every-frame) failed"
    run_m4 "$m4_all" >"$work/m4-all.txt" || true
    "$host_bin" --every 1 >"$work/host-all.txt" || true
    first=$({ cmp "$work/m4-all.txt" "$work/host-all.txt" 2>&1 || true; } |
        sed -n 's/.* line \([0-9]*\)$/\1/p')
    if [ -n "$first" ]; then
        echo "first difference, report line $first (f <setup> <frame index> <t_us> <frame>):"
        echo "  Cortex-M4: $(sed -n "${first}p" "$work/m4-all.txt")"
        echo "  host:      $(sed -n "${first}p" "$work/host-all.txt")"
    fi
    exit 1
fi

if [ "$icount" = 1 ]; then
    stage "instructions per control step on the emulated Cortex-M4 (QEMU trace, steps 100..200)"
    icount_elf=$(build_m4 target/icount icount) || die "M4 build (icount) failed"
    # One trace line per executed instruction (-singlestep: one instruction per translation
    # block; nochain: every block execution is logged). The lines are counted as they stream
    # by, from each xtarget_mark_<setup>_begin to the next xtarget_mark_<setup>_end: the
    # control core's on_frame calls and step of one control period.
    # QEMU 8.1 renamed -singlestep (removed in 9.0) to a TCG accelerator property.
    case $qemu_version in
    [0-7].* | 8.0*) one_insn=(-singlestep) ;;
    *) one_insn=(-accel tcg,one-insn-per-tb=on) ;;
    esac
    { run_m4 "$icount_elf" "${one_insn[@]}" -d exec,nochain -D /dev/stdout | awk -v guest="$work/icount.txt" '
        /^Trace/ {
            if (index($0, "xtarget_mark_")) {
                tag = $NF; sub(/.*xtarget_mark_/, "", tag); sub(/17h[0-9a-f]+E$/, "", tag)
                setup = tag; sub(/_(begin|end)$/, "", setup)
                if (tag ~ /_begin$/) { inside = 1; c = 0 }
                else if (inside) {
                    inside = 0; n[setup]++; sum[setup] += c; windows++
                    if (c > hi[setup]) hi[setup] = c
                    if (!(setup in lo) || c < lo[setup]) lo[setup] = c
                }
                next
            }
            if (inside) c++
            next
        }
        { print > guest }   # the guest'"'"'s own lines
        END {
            if (windows == 0) { print "xtarget: no markers in the trace" > "/dev/stderr"; exit 2 }
            for (k in n)
                printf "instructions per control step (Cortex-M4, %s, %d steps): mean %.0f, min %d, max %d\n",
                    k, n[k], sum[k] / n[k], lo[k], hi[k]
        }' | sort; } || die "the instruction-count run failed (exit $?; QEMU_TIMEOUT is ${QEMU_TIMEOUT} s)"
    [ -s "$work/icount.txt" ] || die "the instruction-count run printed no report"
    # The instrumented build must compute the same frames as the host up to its last step
    # (every setup: no report line would otherwise pass unchecked).
    checked=$(grep -c '^icount [a-z0-9]* steps=' "$work/icount.txt" || true)
    [ "$checked" = 4 ] || { echo "icount build: $checked report lines, expected 4 (dji, odrive, cia402, pods)"; exit 1; }
    while read -r _ setup range frames hash; do
        want=$(sed -n "s/^ck $setup step=${range#steps=*..} \(frames=[0-9]* hash=[0-9a-f]*\)$/\1/p" \
            "$work/host.txt")
        if [ "$frames $hash" != "$want" ]; then
            echo "icount build of $setup differs from the host at ${range#steps=*..}: $frames $hash vs $want"
            exit 1
        fi
    done < <(grep '^icount [a-z0-9]* steps=' "$work/icount.txt")
    echo "(instrumented build: frames and hash at step $(sed -n 's/.*steps=[0-9]*\.\.\([0-9]*\) .*/\1/p' "$work/icount.txt" | head -1) equal the host's)"
fi
