#!/usr/bin/env python3
"""Where tracking pods hold 1 % of the distance, and where not: `hostsim sweep` over drawn pod
errors, on the square, a straight leg and a circle, for three pods and for two and the gyro.

Each line of the table is one `hostsim sweep` command (printed with `--print`), the pod
errors drawn as crates/hostsim/tests/pod_odometry.rs draws them: the block's misalignment
uniform in ±0.5°, each pod's own in ±0.1°, contact points ±2 mm, and the scale as the source
needs it (two pods and the gyro: each pod's own ±1 %; three pods: one common to the pods
±1 % and each pod's own ±0.1 %, as the test holds them). The same draws with what the pods'
calibration leaves (docs/simulator.md, "Calibration", "Tracking pods": each radius within
0.02 %, each direction within 0.01°, each lever within 0.03 mm) make the "calibrated" lines. A run holds when its
largest position error is at most 1 % of the distance it drove and its heading at the end
within 1°. docs/simulator.md, "Tracking pods", has the table.

usage: scripts/pod-sweeps.py [--runs N] [--hostsim PATH] [--out DIR] [--print]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shlex
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCENARIOS = ["square_60s_pods", "straight_pods", "circle_pods"]
SOURCES = {
    # name: (configuration, pods, common scale ±, own scale ±)
    "pods3": ("config/dji_m3508_pods3.toml", 3, 0.01, 0.001),
    "pods2_gyro": ("config/dji_m3508_pods2_gyro.toml", 2, 0.0, 0.01),
}
#: What the pods' calibration leaves (each pod's: no common part): scale, direction (°),
#: contact point (m; the lever's standard error).
CALIBRATED = (0.0, 0.0002, 0.01, 0.00003)


def draws(pods: int, common: float, own: float, block_deg: float, own_deg: float, offset: float) -> list[str]:
    """The --set arguments of one sweep's pod errors: each a uniform draw in ±half (a
    constant 0 for none)."""
    def draw(key: str, half: float) -> str:
        return f"{key}={-half}..{half}" if half else f"{key}=0"

    sets = [draw("pods.misalignment_deg", block_deg), draw("pods.radius_error", common)]
    for i in range(pods):
        sets += [draw(f"pods.pod[{i}].radius_error", own), draw(f"pods.pod[{i}].misalignment_deg", own_deg),
                 draw(f"pods.pod[{i}].offset_x", offset), draw(f"pods.pod[{i}].offset_y", offset)]
    return sets


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=200, help="seeds per sweep (1..N), default 200")
    ap.add_argument("--hostsim", default=os.environ.get("HOSTSIM", str(ROOT / "target" / "release" / "hostsim")))
    ap.add_argument("--out", help="keep each sweep's table in DIR/<scenario>-<source>[-calibrated]")
    ap.add_argument("--print", action="store_true", help="print the commands, run nothing")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error(f"--runs {args.runs}: at least 1")
    out = pathlib.Path(args.out) if args.out else pathlib.Path(tempfile.mkdtemp(prefix="pod-sweeps-"))
    print("| scenario | odometry | pod errors | runs held | drift / distance p50, max | heading at the end, max |")
    print("|---|---|---|---:|---|---|")
    for scenario in SCENARIOS:
        for source, (config, pods, common, own) in SOURCES.items():
            for label, (c, o, deg, offset) in (("as drawn", (common, own, 0.1, 0.002)), ("calibrated", CALIBRATED)):
                block = 0.5 if label == "as drawn" else 0.01
                name = f"{scenario}-{source}" + ("-calibrated" if label == "calibrated" else "")
                cmd = [args.hostsim, "sweep", f"scenarios/{scenario}.toml", "--config", config,
                       "--seeds", f"1..{args.runs}", "--out", str(out / name), "--no-plot"]
                for s in draws(pods, c, o, block, deg, offset):
                    cmd += ["--set", s]
                if args.print:
                    print(shlex.join(cmd))
                    continue
                proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
                if proc.returncode != 0:
                    sys.stderr.write(f"{shlex.join(cmd)}\n{proc.stderr}")
                    return proc.returncode
                rows = [json.loads(line) for line in (out / name / "sweep.jsonl").read_text().splitlines()]
                ratio = sorted(100 * r["drift_max_m"] / r["distance_m"] for r in rows)
                heading = max(abs(r["heading_error_deg"]) for r in rows)
                held = sum(1 for r in rows
                           if r["drift_max_m"] <= 0.01 * r["distance_m"] and abs(r["heading_error_deg"]) <= 1.0)
                print(f"| {scenario} | {source} | {label} | {held} of {len(rows)} | "
                      f"{ratio[len(ratio) // 2]:.2f} %, {ratio[-1]:.2f} % | {heading:.2f}° |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
