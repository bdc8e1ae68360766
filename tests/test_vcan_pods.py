"""Tracking pods on vcan0: `hostsim plant --pods` (and `--imu`) with `mecanum-runner`
configured for pod odometry.

The plant's pod node sends POD_COUNTS from the chassis's true travel, the pods as
config/dji_m3508_pods3.toml and config/dji_m3508_pods2_gyro.toml place them; the runner takes
its odometry from them. Checked on what crossed the bus (candump's kernel stamps) and the
plant's ground truth: the pod frames' rate, ODOM_SLIP's odometry source, and the final pose
against the truth.
"""

from __future__ import annotations

import math
import subprocess
import time

import cantools
import pytest
from vcan_robot import MODE_ENABLE, ODOM_POSITION, ODOM_VELOCITY, ROBOT_DBC, ROOT, VM_TIMING, Robot, write_config

pytestmark = pytest.mark.vcan

POD_COUNTS, ODOM_SLIP = 0x306, 0x315
POD_HZ = 200  # hostsim's pod node, PodsParams::default()
DB = cantools.database.load_file(str(ROBOT_DBC), strict=True)
#: ODOM_SLIP.source by value: WHEELS, PODS2_GYRO, PODS3, WHEELS_PODS_SILENT.
SOURCES = {v: str(k) for v, k in DB.get_message_by_frame_id(ODOM_SLIP).get_signal_by_name("source").choices.items()}

# A figure eight of sorts: forward with a turn, a strafe, a turn in place, each DRIVE_S.
DRIVE = [(0.4, 0.0, 0.6), (0.0, 0.3, 0.0), (0.0, 0.0, -1.0)]
DRIVE_S = 1.5


def drive(robot: Robot) -> None:
    robot.mode(MODE_ENABLE)
    robot.start_stream()
    for vx, vy, wz in DRIVE:
        robot.twist(vx, vy, wz)
        time.sleep(DRIVE_S)
    robot.twist(0.0, 0.0, 0.0)
    time.sleep(0.5)
    robot.stop_stream()
    time.sleep(0.3)


@pytest.fixture(scope="module", params=["pods3", "pods2_gyro"])
def session(request, robot_factory, tmp_path_factory) -> tuple[str, Robot]:
    mode = request.param
    config = write_config(tmp_path_factory.mktemp("config") / f"{mode}.toml",
                          ROOT / "config" / f"dji_m3508_{mode}.toml", **VM_TIMING)
    plant_args = ["--pods"] + (["--imu"] if mode == "pods2_gyro" else [])
    with robot_factory(f"pods-{mode}", config=config, plant_args=plant_args) as robot:
        drive(robot)
    return mode, robot


def test_the_runner_takes_its_odometry_from_the_plants_pods(session: tuple[str, Robot]) -> None:
    mode, robot = session
    pods = robot.of(POD_COUNTS)
    span = pods[-1].t - pods[0].t
    rate = (len(pods) - 1) / span
    print(f"\n{mode}: {len(pods)} POD_COUNTS frames at {rate:.1f} Hz")
    assert abs(rate - POD_HZ) < 0.02 * POD_HZ, rate
    # The runner starts on the wheels (WHEELS_PODS_SILENT) and hands over to the pods at
    # their second frame; from then on every ODOM_SLIP names the configured source: the pods
    # never fell silent.
    slips = [(t, SOURCES[s["source"]]) for t, s in robot.decoded(ODOM_SLIP)]
    assert slips, "no ODOM_SLIP"
    first = next(i for i, (_, source) in enumerate(slips) if source == mode.upper())
    print(f"{mode}: the pods took over {(slips[first][0] - slips[0][0]) * 1e3:.1f} ms after the first ODOM_SLIP")
    assert {source for _, source in slips[:first]} <= {"WHEELS_PODS_SILENT"}, slips[:first]
    assert {source for _, source in slips[first:]} == {mode.upper()}
    assert len(slips) - first > 400, f"{len(slips) - first} frames from the pods"


def test_the_pod_odometry_ends_where_the_robot_is(session: tuple[str, Robot]) -> None:
    mode, robot = session
    pose = robot.decoded(ODOM_POSITION)[-1][1]
    heading = robot.decoded(ODOM_VELOCITY)[-1][1]["heading"]
    truth = robot.plant_stats["truth"]
    positions = [(p["x"], p["y"]) for _, p in robot.decoded(ODOM_POSITION)]
    path = sum(math.dist(a, b) for a, b in zip(positions, positions[1:]))
    error = math.hypot(pose["x"] - truth["x"], pose["y"] - truth["y"])
    dheading = math.remainder(heading - truth["heading"], math.tau)
    print(f"{mode}: odometry ({pose['x']:+.4f}, {pose['y']:+.4f}, {heading:+.4f}) truth "
          f"({truth['x']:+.4f}, {truth['y']:+.4f}, {truth['heading']:+.4f}): {error * 1e3:.1f} mm "
          f"over a {path:.2f} m path, heading {math.degrees(dheading):+.2f}°")
    assert path > 0.8, path
    # The pods are the true ones, counted at 2000 a turn on 24 mm: the pose is off by the
    # counts' quantization and the steps between two frames, a millimetre (measured 0.0 mm
    # with three pods, 0.6 mm with two and the gyro). The bound is 1 % of the path.
    assert error < 0.01 * path, error
    assert abs(dheading) < math.radians(0.5), math.degrees(dheading)


def test_pods_without_configured_pods_are_refused(plant_bin, vcan) -> None:
    proc = subprocess.run([str(plant_bin), "plant", "--iface", vcan, "--config", str(ROOT / "config" / "dji_m3508.toml"),
                           "--pods"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "--pods" in proc.stderr and "[[odometry.pods]]" in proc.stderr, proc.stderr
