#!/usr/bin/env python3
"""Figures of `mecanum-runner --live` (docs/live.md): the runner's step lateness and step time
(p50, p99, max, as it measures them on its own clock, `--stats-json`) without a client, with a
client that reads every channel (with `/can/*` thinned as for a viewer, and with every CAN
frame), and with one that stops reading; and what each client got.

    scripts/vcan.sh -- .venv/bin/python scripts/bench-live-runner.py [--seconds 20]

Needs a SocketCAN interface (scripts/vcan.sh brings vcan0 up, in its micro-VM where the kernel
has no vcan) and release builds of `hostsim` and `mecanum-runner` ($HOSTSIM, $MECANUM_RUNNER,
else target/release). Each session is the plant and the runner on the interface
(tests/vcan_robot.py), the runner with `--log` and `--live 127.0.0.1:0`, driven for `--seconds`
with twist commands at 50 Hz; `--live-can-hz 0` forwards every CAN frame (the most a client
can ask of the runner), the default 100 per CAN id a second. The reading client is a process
of its own (tests/foxglove_client.py).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import pathlib
import platform
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from foxglove_client import FoxgloveClient, StalledClient  # noqa: E402
from test_vcan_live import live_url  # noqa: E402
from vcan_robot import MODE_ENABLE, Robot, binary, write_config  # noqa: E402


def reader(url: str, ready: mp.Event, out: mp.Queue) -> None:  # type: ignore[type-arg]
    c = FoxgloveClient(url)
    c.start()
    c.subscribe()
    ready.set()
    out.put(len(c.read_until_closed(timeout=600)))
    c.close()


def session(work: pathlib.Path, config: pathlib.Path, kind: str, can_hz: int, seconds: float) -> dict:
    robot = Robot(runner=binary("MECANUM_RUNNER", ROOT / "target" / "release" / "mecanum-runner"),
                  hostsim=binary("HOSTSIM", ROOT / "target" / "release" / "hostsim"),
                  candump="candump", iface="vcan0", config=config, workdir=work, runner_log=True,
                  runner_args=["--live", "127.0.0.1:0", "--live-can-hz", str(can_hz)])
    proc = stalled = None
    out: mp.Queue = mp.Queue()  # type: ignore[type-arg]
    with robot:
        url = live_url(robot, "runner")
        if kind == "reading":
            ready = mp.Event()
            proc = mp.Process(target=reader, args=(url, ready, out))
            proc.start()
            ready.wait(60)
        elif kind == "stalled":
            stalled = StalledClient(url)
        robot.mode(MODE_ENABLE)
        robot.twist(0.3, 0.1, 0.5)
        robot.start_stream()
        time.sleep(seconds)
        robot.stop_stream()
    if proc is not None:
        proc.join(60)
    if stalled is not None:
        stalled.close()
    return robot.runner_stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="driving time of each session (default 20)")
    args = ap.parse_args()
    print(f"machine: {platform.machine()}, {platform.platform()}; {time.strftime('%Y-%m-%d %H:%M')}")
    with tempfile.TemporaryDirectory() as tmp:
        config = write_config(pathlib.Path(tmp) / "dji.toml", ROOT / "config" / "dji_m3508.toml")
        print("| client | CAN frames | steps | overruns | lateness p50 / p99 / max "
              "| step time p50 / p99 / max | sent | dropped |")
        print("|---|---|---|---|---|---|---|---|")
        for kind, can_hz in (("none", 0), ("reading", 100), ("reading", 0), ("stalled", 0)):
            work = pathlib.Path(tmp) / f"{kind}-{can_hz}"
            work.mkdir()
            s = session(work, config, kind, can_hz, args.seconds)
            j, t, live = s["jitter"], s["step_time"], s["live"]
            frames = "all" if can_hz == 0 else f"{can_hz}/s per id"
            print(f"| {kind} | {frames} | {s['steps']:,} | {s['overruns']} "
                  f"| {j['p50_us']} / {j['p99_us']} / {j['max_us']} µs "
                  f"| {t['p50_us']} / {t['p99_us']} / {t['max_us']} µs "
                  f"| {live['sent']:,} | {live['dropped']:,} |", flush=True)


if __name__ == "__main__":
    main()
