"""`hostsim calibrate` from the outside: the built-in `calibration` run, its fit as JSON, the
written configuration, and the log read by `rosbags` and `mcap` without this project's code.

The fit is checked against figures read from the log with rosbags alone: the steady strafe's
and the steady spin's ground-truth speed over the odometry's.
"""

from __future__ import annotations

import json
import math
import pathlib
import subprocess
import tomllib

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore


def hostsim(binary: pathlib.Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary), *args], capture_output=True, text=True, timeout=120, check=False)


@pytest.fixture(scope="module")
def calibrated(hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, dict]:
    out = tmp_path_factory.mktemp("calibration")
    run = hostsim(hostsim_bin, "run", "calibration", "--out", str(out), "--no-plot", "--json")
    assert run.returncode == 0, run.stderr
    fit = hostsim(
        hostsim_bin, "calibrate", str(out / "calibration.mcap"), "--json", "--write", str(out / "cal.toml")
    )
    assert fit.returncode == 0, fit.stderr
    return out, json.loads(fit.stdout)


def test_the_fit_is_finite_and_tight(calibrated) -> None:
    _, fit = calibrated
    axes = {a["axis"]: a for a in fit["axes"]}
    for name, axis in axes.items():
        print(f"{name}: correction {axis['correction']:.5f} ± {axis['stderr']:.1e}, residual {axis['residual_rms']:.2e}")
        assert math.isfinite(axis["correction"]) and 0 < axis["stderr"] < 1e-3, axis
    for key in ("wheel_radius", "lx_plus_ly", "lateral_effectiveness"):
        value, stderr = fit[key]["value"], fit[key]["stderr"]
        print(f"{key}: {value:.6f} ± {stderr:.1e}")
        assert math.isfinite(value) and 0 < stderr < 1e-3 * value, fit[key]
    # The simulated robot: no forward slip, a strafe at 75 % (roller drag 1/7), a spin at 99.2 %.
    assert axes["forward"]["correction"] == pytest.approx(1.0, abs=2e-3)
    assert axes["lateral"]["correction"] == pytest.approx(0.75, abs=2e-3)
    assert axes["yaw"]["correction"] == pytest.approx(0.992, abs=1e-3)
    assert fit["moving_windows"] >= 100 and fit["complete"] is True


def test_the_written_configuration_holds_the_fit(calibrated) -> None:
    out, fit = calibrated
    config = tomllib.loads((out / "cal.toml").read_text())
    geometry = config["geometry"]
    for key in ("lx", "ly", "wheel_radius", "lateral_effectiveness"):
        assert geometry[key] == pytest.approx(fit["fitted"][key], rel=1e-6), key
        assert f"\n{key} = " in fit["geometry_lines"]
    # 1.0 is the default, left out of the file.
    assert geometry.get("forward_effectiveness", 1.0) == geometry.get("yaw_effectiveness", 1.0) == 1.0
    assert geometry["lx"] / geometry["ly"] == pytest.approx(0.20 / 0.18, rel=1e-4)
    assert config["drive"]["protocol"] == "dji"


def _steady_ratio(reader: AnyReader, field: str, t0: float, t1: float) -> float:
    """Mean ground-truth speed over the odometry's, from the logged twists between t0 and t1."""
    speeds: dict[str, list[float]] = {"/odom": [], "/ground_truth/odom": []}
    connections = [c for c in reader.connections if c.topic in speeds]
    for connection, t_ns, raw in reader.messages(connections=connections):
        if t0 <= t_ns * 1e-9 <= t1:
            msg = reader.deserialize(raw, connection.msgtype)
            twist = msg.twist.twist
            value = twist.linear.y if field == "vy" else twist.angular.z
            speeds[connection.topic].append(value)
    odom, truth = (sum(speeds[t]) / len(speeds[t]) for t in ("/odom", "/ground_truth/odom"))
    return truth / odom


def test_the_log_reads_without_this_project_and_agrees_with_the_fit(calibrated) -> None:
    out, fit = calibrated
    log = out / "calibration.mcap"
    with open(log, "rb") as f:
        reader = make_reader(f)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        summary = reader.get_summary()
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
    drive = metadata["mecanum_drive"]
    assert drive["scenario"] == "calibration"
    assert "roller_drag" in drive["plant"] and "[geometry]" in drive["config"]
    assert counts["/joint_states"] == fit["odometry_samples"]
    assert counts["/ground_truth/odom"] == fit["reference_samples"]
    with AnyReader([log], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        # The strafe left runs from 6.1 s to 8.1 s, the first spin from 11.1 s to 15.3 s.
        lateral = _steady_ratio(reader, "vy", 6.8, 7.8)
        yaw = _steady_ratio(reader, "wz", 12.0, 15.0)
    axes = {a["axis"]: a for a in fit["axes"]}
    print(f"steady ratios read with rosbags: lateral {lateral:.5f}, yaw {yaw:.5f}")
    assert lateral == pytest.approx(axes["lateral"]["correction"], abs=1e-3)
    assert yaw == pytest.approx(axes["yaw"]["correction"], abs=1e-3)


def test_a_log_without_forward_travel_or_rotation_is_refused(hostsim_bin, tmp_path) -> None:
    run = hostsim(hostsim_bin, "run", "strafe", "--out", str(tmp_path), "--no-plot")
    assert run.returncode == 0, run.stderr
    fit = hostsim(hostsim_bin, "calibrate", str(tmp_path / "strafe.mcap"), "--json")
    print(fit.stderr)
    assert fit.returncode == 2 and fit.stdout == ""
    assert "no forward travel in this log" in fit.stderr and "cannot fit wheel_radius" in fit.stderr
    assert "no rotation in this log" in fit.stderr and "no strafe" not in fit.stderr
