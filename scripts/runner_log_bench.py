"""What `mecanum-runner --log` costs the real loop on a real interface (run it in the vcan
lane: `scripts/vcan.sh -- .venv/bin/python scripts/runner_log_bench.py`; bench.sh does).

Four sessions of SESSION_S seconds each, with `hostsim plant` (four C620/M3508 drives) and
`mecanum-runner` as real processes on vcan0 and a host streaming twists at 50 Hz: without and
with `--log`, on a quiet bus and under a flood of 8,000 frames/s of an unused id (cangen). It
prints, per session, the runner's own figures from `--stats-json`: the lateness of each step
start after its deadline (jitter) and the step time (wake-up to last frame sent), p50 / p99 /
max, the overruns, and with --log the log's size per hour of running and the messages dropped.
Markdown table rows on stdout; the timing figures are not asserted (see docs/benchmarks.md).
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from vcan_robot import MODE_ENABLE, Robot, binary, write_config  # noqa: E402

SESSION_S = float(os.environ.get("RUNNER_LOG_BENCH_S", "15"))
VM = os.environ.get("MECANUM_VCAN_MODE") == "vm"


def session(work: pathlib.Path, name: str, log: bool, flood: bool, config: pathlib.Path) -> dict:
    robot = Robot(
        runner=binary("MECANUM_RUNNER", ROOT / "target" / "release" / "mecanum-runner"),
        hostsim=binary("HOSTSIM", ROOT / "target" / "release" / "hostsim"),
        candump=shutil.which("candump") or "candump",
        iface="vcan0",
        config=config,
        workdir=work / name,
        runner_log=log,
    )
    (work / name).mkdir()
    cangen = None
    with robot:
        robot.mode(MODE_ENABLE)
        robot.twist(0.4, 0.1, 0.3)
        robot.start_stream()
        if flood:
            # Bursts of 8 frames every 1 ms: 8,000 frames/s nominal.
            cangen = subprocess.Popen(
                ["cangen", "vcan0", "-I", "123", "-L", "8", "-D", "i", "-g", "1", "-c", "8"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        time.sleep(SESSION_S)
        if cangen is not None:
            cangen.terminate()
            cangen.wait(timeout=30)
        robot.stop_stream()
    stats = robot.runner_stats
    stats["log_bytes"] = robot.runner_mcap.stat().st_size if robot.runner_mcap else None
    return stats


def main() -> int:
    where = "micro-VM, software-emulated CPU" if VM else "native"
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        config = write_config(
            work / "dji.toml",
            ROOT / "config" / "dji_m3508.toml",
            **({"stale_periods": 200} if VM else {}),
        )
        rows = []
        for flood in (False, True):
            for log in (False, True):
                name = f"{'flood' if flood else 'quiet'}-{'log' if log else 'nolog'}"
                s = session(work, name, log, flood, config)
                j, st = s["jitter"], s["step_time"]
                what = (f"runner at 1 kHz, {'--log' if log else 'no log'}, "
                        f"{'8,000 frames/s flood' if flood else 'quiet bus'} ({where})")
                rows.append(f"| {what}: jitter p50 / p99 / max | {j['p50_us']} / {j['p99_us']} / "
                            f"{j['max_us']} | µs |")
                rows.append(f"| {what}: step time p50 / p99 / max | {st['p50_us']} / {st['p99_us']} / "
                            f"{st['max_us']} | µs |")
                elapsed = s["elapsed_us"] / 1e6
                rows.append(f"| {what}: steps in {elapsed:.1f} s (rate), overruns, frames received | "
                            f"{s['steps']} ({s['steps'] / elapsed:.0f}/s), {s['overruns']}, "
                            f"{s['frames_received']} | |")
                if log:
                    hours = s["elapsed_us"] / 3.6e9
                    per_hour = s["log_bytes"] / hours / 1e6
                    rows.append(f"| {what}: log size per hour, dropped | {per_hour:.0f} MB/h, "
                                f"{s['log']['dropped']} of {s['log']['messages'] + s['log']['dropped']} "
                                f"dropped | MB/h |")
                print(f"{name}: {rows[-1]}", file=sys.stderr, flush=True)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
