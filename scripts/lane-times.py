#!/usr/bin/env python3
"""Where the vcan lane's time went: a Markdown table from target/vcan-lane/timeline.tsv.

scripts/vcan-vm.py writes the timeline: each progress line of the guest (tests/lane.py prints
`lane: start` and `lane: end` per test, scripts/vcan-guest.sh its own) with the host's wall
seconds since the VM started. This prints the VM's start-up, then per test module its tests,
guest seconds (the guest's clock: executed instructions, plus the jumps to the next timer
while every guest process waits, on the host's file reads among them) and wall seconds, and
their shares of the lane; where the lines carry them, the seconds the guest's CPU ran tasks
and how often it went idle (both cost wall time under emulation) and the CPU seconds of
pytest and of the programs it ran;
`--tests` lists every test as well.

    scripts/lane-times.py [TIMELINE] [--tests]
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import re
import sys

END = re.compile(r"lane: end \[(\d+)/(\d+)\] (\S+(?: \(\w+\))?) (\S+) in ([\d.]+) s \(guest ([\d.]+) s\)"
                 r"(?: cpu ([\d.]+) s, (\d+) idles: pytest ([\d.]+) s, children ([\d.]+) s)?")
START = re.compile(r"lane: start \[(\d+)/(\d+)\] (\S+) \(guest ([\d.]+) s\)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("timeline", nargs="?", type=pathlib.Path, default=pathlib.Path("target/vcan-lane/timeline.tsv"))
    ap.add_argument("--tests", action="store_true", help="a row for every test, not only per module")
    args = ap.parse_args()
    try:
        text = args.timeline.read_text()
    except OSError as err:
        print(f"lane-times: {args.timeline}: {err}", file=sys.stderr)
        return 2
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        wall_s, _, message = line.partition("\t")
        try:
            rows.append((float(wall_s), message))
        except ValueError:
            print(f"lane-times: {args.timeline}:{number}: not `SECONDS<TAB>LINE`: {line[:80]!r}", file=sys.stderr)
            return 2
    if not rows:
        print(f"lane-times: {args.timeline}: empty", file=sys.stderr)
        return 2
    ready = next((w for w, m in rows if m.startswith("vcan-guest:") and "running the command" in m), None)
    starts: dict[str, float] = {}
    tests = []  # (nodeid, outcome, guest s, wall s, (busy s, idles, pytest s, children s) or None)
    for wall, message in rows:
        if m := START.search(message):
            starts[m.group(3)] = wall
        elif m := END.search(message):
            nodeid = m.group(4)
            cpu = tuple(float(v) for v in m.group(7, 8, 9, 10)) if m.group(7) else None
            tests.append((nodeid, m.group(3), float(m.group(5)), wall - starts.get(nodeid, wall), cpu))
    end = rows[-1][0]
    first = min(starts.values(), default=end)
    total_guest = sum(t[2] for t in tests)
    total_wall = sum(t[3] for t in tests)
    print(f"VM start to vcan0 up: {ready if ready is not None else float('nan'):.1f} s wall; "
          f"to the first test: {first:.1f} s (Python and pytest start-up, collection); "
          f"last line: {end:.1f} s")
    print(f"{len(tests)} tests: {total_guest:.1f} s of guest time, {total_wall:.1f} s of wall time\n")
    with_cpu = all(t[4] is not None for t in tests)

    def cpu_cells(items: list) -> str:
        if not with_cpu:
            return ""
        busy, idles, own, children = (sum(t[4][i] for t in items) for i in range(4))
        return f" {busy:.1f} | {idles:.0f} | {own:.1f} | {children:.1f} |"

    cpu_head, cpu_rule = ((" cpu s | idles | pytest s | children s |", "---:|---:|---:|---:|") if with_cpu
                          else ("", ""))
    print(f"| module | tests | guest s | share | wall s | share |{cpu_head}")
    print(f"|---|---:|---:|---:|---:|---:|{cpu_rule}")
    modules: dict[str, list] = collections.defaultdict(list)
    for t in tests:
        modules[t[0].split("::")[0]].append(t)
    for module, items in sorted(modules.items(), key=lambda kv: -sum(t[3] for t in kv[1])):
        guest, wall = sum(t[2] for t in items), sum(t[3] for t in items)
        print(f"| `{module}` | {len(items)} | {guest:.1f} | {guest / total_guest:.0%} | {wall:.1f} | "
              f"{wall / max(end, 1e-9):.0%} |{cpu_cells(items)}")
    if args.tests:
        print(f"\n| test | outcome | guest s | wall s |{cpu_head}")
        print(f"|---|---|---:|---:|{cpu_rule}")
        for t in tests:
            print(f"| `{t[0]}` | {t[1]} | {t[2]:.1f} | {t[3]:.1f} |{cpu_cells([t])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
