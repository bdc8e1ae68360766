#!/usr/bin/env python3
"""Figures of `hostsim run --live` (docs/live.md): messages per second delivered to one and to
three clients, and the simulator's pacing error over the 60 s square.

    .venv/bin/python scripts/bench-live.py [--hostsim target/release/hostsim] [--quick]

Each client is a process of its own (tests/foxglove_client.py) that subscribes to every
channel and reads until the server closes. Two loads:

- `viewer`: the 60 s square at real time with the default thinning (`/can/*` at 100 frames a
  second per CAN id): what Foxglove gets from a live run.
- `flood`: the same run at 20x real time with every CAN frame (`--live-can-hz 0`): what the
  server can push, and what clients that cannot keep up lose (counted).

Then the pacing error (how far behind the wall clock the simulation's steps were) of the
60 s square at real time, without a client and with one. `--quick` runs the built-in 9 s
square instead of the 60 s one. Binds 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import pathlib
import platform
import re
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from foxglove_client import FoxgloveClient  # noqa: E402

LIVE_LINE = re.compile(r"^live: (ws://\S+) \((\S+)\)")


def client(url: str, ready: mp.Event, out: mp.Queue) -> None:  # type: ignore[type-arg]
    c = FoxgloveClient(url)
    c.start()
    c.subscribe()
    ready.set()
    received = c.read_until_closed(timeout=600)
    c.close()
    times = [t for _, _, t in received]
    out.put({"messages": len(received), "first": times[0] if times else 0.0, "last": times[-1] if times else 0.0})


def live_run(hostsim: str, scenario: str, clients: int, *args: str) -> dict:
    with tempfile.TemporaryDirectory() as out:
        proc = subprocess.Popen([hostsim, "run", scenario, "--live", "127.0.0.1:0", "--out", out, "--no-plot",
                                 "--json", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stderr is not None
        url = ""
        for line in proc.stderr:
            m = LIVE_LINE.match(line)
            if m:
                url = m.group(1)
                break
        assert url, "no live: line"
        queue: mp.Queue = mp.Queue()  # type: ignore[type-arg]
        procs = []
        for _ in range(clients):
            ready = mp.Event()
            p = mp.Process(target=client, args=(url, ready, queue))
            p.start()
            procs.append(p)
        stdout, stderr = proc.communicate(timeout=900)
        assert proc.returncode == 0, stderr
        got = [queue.get(timeout=60) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        summary = json.loads(stdout)
        summary["received"] = got
        return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hostsim", default=str(ROOT / "target" / "release" / "hostsim"))
    parser.add_argument("--quick", action="store_true", help="the built-in 9 s square, not the 60 s one")
    a = parser.parse_args()
    scenario = "square" if a.quick else str(ROOT / "scenarios" / "square_60s.toml")
    print(f"# {platform.node()}: {platform.processor() or platform.machine()}, "
          f"{mp.cpu_count()} cores, {time.strftime('%Y-%m-%d')}")
    print("load    clients  per client: received msg/s  (sent by the server, dropped)  "
          "server total msg/s  pacing p99")
    for load, args in [("viewer", ["--rate", "1"]), ("flood", ["--rate", "20", "--live-can-hz", "0"])]:
        for n in (1, 3):
            s = live_run(a.hostsim, scenario, n, *args)
            live = s["live"]
            rates = []
            for r in s["received"]:
                span = max(r["last"] - r["first"], 1e-9)
                rates.append(r["messages"] / span)
            per = ", ".join(f"{r:,.0f}" for r in rates)
            sent = sum(c["sent"] for c in live["clients"])
            print(f"{load:7} {n:7}  {per:>28}  ({sent:,} sent, {live['dropped']:,} dropped)  "
                  f"{sent / s['wall_s']:>18,.0f}  {live['late_p99_s'] * 1e3:.2f} ms")
    print("pacing over the run at real time (lateness of the steps against the wall clock):")
    for n in (0, 1):
        s = live_run(a.hostsim, scenario, n, "--rate", "1")
        live = s["live"]
        print(f"  {n} client(s): {live['paced_steps']} steps in {s['wall_s']:.3f} s for "
              f"{s['duration_s']:.2f} s simulated; late by {live['late_mean_s'] * 1e3:.3f} ms on average, "
              f"{live['late_p99_s'] * 1e3:.3f} ms p99, {live['late_max_s'] * 1e3:.3f} ms at most")


if __name__ == "__main__":
    main()
