#!/usr/bin/env bash
# The whole suite on a busy machine: scripts/test.sh while `stress-ng --cpu N` keeps N cores
# busy from before its first stage to after its last (docs/reliability.md, "A suite that does
# not flake"). Usage: scripts/test-busy.sh [--cpus N] [--runs K] [--fresh DIR] [-- TEST.SH ARGS...]
#   --cpus N     busy cores (default 1)
#   --runs K     run the suite K times in a row, stopping at the first failure (default 1)
#   --fresh DIR  each run in a fresh clone of this repository's HEAD at DIR (removed first
#                and made anew for every run: no target/, no .venv), as CI runs it (CI=true)
# Installs stress-ng (Debian) as root when missing. Prints each run's time, result and stage
# times (also in target/test-stages/busy.txt), and exits with the first failing run's status
# (0 when all passed).
set -euo pipefail
cd "$(dirname "$0")/.."

cpus=1 runs=1 fresh=
while [ $# -gt 0 ]; do
    case $1 in
    --cpus) cpus=${2:?--cpus needs a number}; shift 2 ;;
    --runs) runs=${2:?--runs needs a number}; shift 2 ;;
    --fresh) fresh=${2:?--fresh needs a directory}; shift 2 ;;
    -h | --help) sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    --) shift; break ;;
    *) echo "test-busy.sh: unknown argument '$1' (--help)" >&2; exit 2 ;;
    esac
done
case "$cpus$runs" in *[!0-9]*) echo "test-busy.sh: --cpus and --runs take whole numbers" >&2; exit 2 ;; esac
if [ -n "$fresh" ]; then
    case $fresh in /*) ;; *) fresh=$PWD/$fresh ;; esac
    case $fresh/ in "$PWD"/*) echo "test-busy.sh: --fresh $fresh is inside this repository" >&2; exit 2 ;; esac
    # It is removed before each run: only a directory that is not there or an earlier clone.
    if [ -e "$fresh" ] && [ ! -e "$fresh/.git" -o ! -e "$fresh/scripts/test-busy.sh" ]; then
        echo "test-busy.sh: --fresh $fresh exists and is not a clone of this repository; not removing it" >&2
        exit 2
    fi
fi

if ! command -v stress-ng >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends stress-ng
    else
        echo "test-busy.sh: stress-ng not found (Debian: apt-get install stress-ng)" >&2
        exit 2
    fi
fi

stress_pid=
stop_stress() {
    if [ -n "$stress_pid" ]; then
        kill -TERM "$stress_pid" 2>/dev/null || true
        wait "$stress_pid" 2>/dev/null || true
        stress_pid=
    fi
}
trap stop_stress EXIT
trap 'stop_stress; exit 130' INT TERM HUP

mkdir -p target/test-stages
results=()
rc=0
for ((i = 1; i <= runs; i++)); do
    stress-ng --cpu "$cpus" --quiet &
    stress_pid=$!
    start=$(date +%s)
    run_rc=0
    if [ -n "$fresh" ]; then
        rm -rf "$fresh"
        git clone -q "$PWD" "$fresh"
        commit=$(git -C "$fresh" rev-parse --short HEAD)  # HEAD here may move during the run
        (cd "$fresh" && CI=true ./scripts/test.sh "$@") || run_rc=$?
        times=$fresh/target/test-stages/times.txt
    else
        ./scripts/test.sh "$@" || run_rc=$?
        times=target/test-stages/times.txt
    fi
    took=$(($(date +%s) - start))
    stop_stress
    # A failed run may have no stage times: its line is printed all the same.
    stages=$(grep -E '^ +[0-9]+ s' "$times" 2>/dev/null | awk '{printf "%s%s %s", sep, $3, $1; sep=", "}') ||
        stages="no stage times in $times"
    results+=("run $i of $runs${fresh:+ (fresh clone of $commit)}, $cpus core(s) busy: exit $run_rc after $took s; $stages")
    printf '\n==> test-busy: %s\n' "${results[-1]}"
    if [ "$run_rc" != 0 ]; then
        rc=$run_rc
        break
    fi
done
printf '\n==> test-busy: %s\n' "${results[@]}" | tee target/test-stages/busy.txt
exit "$rc"
