"""The firmware runner and the simulated drives as real processes on a real vcan0.

`mecanum-runner --iface vcan0` (the control core) and `hostsim plant --iface vcan0` (four
simulated C620/M3508 drives on a 20 kg chassis, or four ODrive axes) run in real time; the
test is the host, sending the robot protocol with python-can and cantools (DBC files of this
repository), and candump records the bus. Each module-scoped session below runs one script of
commands; the tests then check what crossed the bus, with the tolerances stated at each.

Here: the stops (watchdog, status polls, e-stop, a repeated frame), malformed and non-finite
frames, the runner's own log of those sessions, the link lost and back, and the frame rate.
Driving and its records (odometry, the plant's log, replays): tests/test_vcan_motion.py.

The binaries are $MECANUM_RUNNER and $HOSTSIM (scripts/test.sh passes release builds: the
micro-VM of the vcan lane emulates its CPU in software, some 20 times slower than the host).
"""

from __future__ import annotations

import collections
import json
import math
import re
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence

import canopen
import pytest
from mecanum_drive import params as robot_params
from vcan_robot import (
    DJI_CMD_1_4, FAULT_NONE, FAULT_WATCHDOG, HOST_STALLS, MODE_ENABLE, MODE_RESET, ODOM_VELOCITY,
    SLOW_CPU, STATE_DISABLED, STATE_ENABLED, STATE_ESTOP, STATUS, STATUS_COUNTERS, STATUS_REQ,
    TWIST_CMD, Robot, dji_currents, mean, run_cangen,
)
# The lane's budgets; the odometry's tolerances against the command.
from vcan_robot import COMMAND_TIMEOUT_S, CONTROL_PERIOD_S, MIN_STEP_RATIO, STOP_BUDGET_S, TIMING_SLACK_S, timing_note
from vcan_robot import VEL_TOL, WZ_TOL

pytestmark = pytest.mark.vcan

# --- stops: watchdog, status polls, e-stop ---------------------------------------------------

HOLD_S = 1.0  # driving before each stop


@pytest.fixture(scope="module")
def stops(robot_factory) -> Robot:
    """Three stops in one run: the host falls silent; the host only polls STATUS; e-stop."""
    with robot_factory("stops", runner_log=True) as robot:
        # 1. Silence: the watchdog stops the robot and latches (DISABLED, fault WATCHDOG).
        robot.mode(MODE_ENABLE, mark="enable1")
        robot.twist(0.5, 0.0, 0.0)
        robot.start_stream()
        time.sleep(HOLD_S)
        robot.stop_stream(mark="silence")
        time.sleep(0.4)
        # 2. STATUS_REQ every 5 ms after the last twist: not a motion command.
        robot.mode(MODE_ENABLE, mark="enable2")
        robot.start_stream()
        time.sleep(HOLD_S)
        robot.stop_stream(mark="polls")
        end = time.monotonic() + 0.4
        while time.monotonic() < end:
            robot.send("STATUS_REQ")
            time.sleep(0.005)
        robot.marks["polls_end"] = time.time()
        # 3. E-stop while twists keep coming; then twists and an enable: still stopped.
        robot.mode(MODE_ENABLE, mark="enable3")
        robot.start_stream()
        time.sleep(HOLD_S)
        robot.estop(mark="estop")
        time.sleep(0.3)
        robot.mode(MODE_ENABLE, mark="enable_in_estop")
        time.sleep(0.3)
        robot.stop_stream()
        # Reset clears the latch (to Disabled); enable and twist drive again.
        robot.mode(MODE_RESET, mark="reset")
        time.sleep(0.1)
        robot.mode(MODE_ENABLE, mark="enable4")
        robot.start_stream()
        time.sleep(0.2)
        # 4. Parameters set while it drives: gains.kp by the package's command line, gains.kv
        # by python-canopen with the robot's EDS (docs/protocol.md, "Parameters").
        robot.marks["params"] = time.time()
        robot.param_cli = subprocess.run(
            [sys.executable, "-m", "mecanum_drive", "--channel", robot.iface, "param", "set", "gains.kp", "1.5"],
            capture_output=True, text=True, timeout=120, check=False)
        network = canopen.Network()
        network.connect(interface="socketcan", channel=robot.iface)
        try:
            node = network.add_node(127, str(robot_params.eds_path()))
            node.sdo["gains"]["gains.kv"].raw = 0.05
            robot.param_kv = node.sdo["gains"]["gains.kv"].raw
        finally:
            network.disconnect()
        time.sleep(0.3)
        robot.stop_stream(mark="end")
        time.sleep(0.3)
    return robot


def _last_before(robot: Robot, ident: int, t: float) -> float:
    frames = robot.of(ident, t1=t)
    assert frames, f"no frame {ident:#x} before {t}"
    return frames[-1].t


def _zero_from(robot: Robot, t0: float, t1: float) -> float:
    """`Robot.zero_currents_from`, the motors driven in the half of HOLD_S before t0."""
    return robot.zero_currents_from(t0, t1, driven_s=HOLD_S / 2)


def _next_mode(robot: Robot, t: float, request: int | None = None) -> float:
    """Time of the first MODE_CMD after t (with this request, if given), as candump saw it."""
    for f in robot.of(0x302, t):
        if request is None or f.data == bytes([request]):
            return f.t
    raise AssertionError(f"no MODE_CMD {request} after {t}")


def _statuses(robot: Robot, t0: float, t1: float) -> list[tuple[float, dict]]:
    """The STATUS frames of [t0, t1], at least as many as its steps that run send (10 Hz,
    MIN_STEP_RATIO), and one: a check over them then looked at some."""
    statuses = robot.decoded(STATUS, t0, t1)
    assert len(statuses) >= max(1, int(MIN_STEP_RATIO * 10 * (t1 - t0))), (t1 - t0, statuses)
    return statuses


def test_silence_stops_within_the_timeout_plus_two_periods(stops: Robot) -> None:
    last = _last_before(stops, TWIST_CMD, stops.marks["silence"] + 0.01)
    enable2 = _next_mode(stops, last)
    zero = _zero_from(stops, last, enable2)
    latency = zero - last
    print(f"silence: zero currents {latency * 1e3:.1f} ms after the last TWIST_CMD "
          f"(budget {STOP_BUDGET_S * 1e3:.0f} ms{timing_note()})")
    assert COMMAND_TIMEOUT_S - 0.002 <= latency <= STOP_BUDGET_S + TIMING_SLACK_S
    status = stops.status_in(zero, enable2)
    assert (status["state"], status["fault"]) == (STATE_DISABLED, FAULT_WATCHDOG), status


def test_status_polls_do_not_keep_motion_alive(stops: Robot) -> None:
    last = _last_before(stops, TWIST_CMD, stops.marks["polls"] + 0.01)
    polls = stops.of(STATUS_REQ, last, stops.marks["polls_end"] + 0.01)
    assert len(polls) >= 20, f"only {len(polls)} STATUS_REQ sent"
    zero = _zero_from(stops, last, _next_mode(stops, last))
    latency = zero - last
    print(f"polls: {len(polls)} STATUS_REQ; zero currents {latency * 1e3:.1f} ms after the last "
          f"TWIST_CMD (budget {STOP_BUDGET_S * 1e3:.0f} ms{timing_note()})")
    assert COMMAND_TIMEOUT_S - 0.002 <= latency <= STOP_BUDGET_S + TIMING_SLACK_S
    # Each poll is answered: STATUS frames at the poll rate, not just the 10 Hz ones.
    answers = stops.of(STATUS, last, stops.marks["polls_end"] + 0.05)
    assert len(answers) >= 0.8 * len(polls), (len(answers), len(polls))


def test_estop_stops_at_once_and_latches(stops: Robot) -> None:
    estop = stops.of(0x300, stops.marks["estop"] - 1.0)[0].t
    reset = _next_mode(stops, estop, MODE_RESET)
    zero = _zero_from(stops, estop, reset)
    latency = zero - estop
    print(f"e-stop: zero currents {latency * 1e3:.1f} ms after ESTOP (budget "
          f"{2 * CONTROL_PERIOD_S * 1e3:.0f} ms{timing_note()})")
    assert latency <= 2 * CONTROL_PERIOD_S + TIMING_SLACK_S
    # Latched: twists kept coming and an enable was sent, and the currents stayed zero.
    twists = stops.of(TWIST_CMD, zero, reset)
    assert len(twists) >= 10, len(twists)
    assert stops.of(0x302, zero, reset), "the enable in e-stop was not sent"
    for t, status in _statuses(stops, zero + 0.01, reset):
        assert status["state"] == STATE_ESTOP, (t, status)
    # Reset, enable and twist: it drives again.
    enable = _next_mode(stops, reset, MODE_ENABLE)
    driven = [c for c in stops.of(DJI_CMD_1_4, enable) if dji_currents(c) != (0,) * 4]
    assert len(driven) > 100, "no motion after reset and enable"
    assert stops.status_in(enable + 0.2, stops.marks["end"])["state"] == STATE_ENABLED


# --- a sender stuck on one TWIST_CMD frame -------------------------------------------------

REPEAT_S = 1.0  # how long the one frame is repeated
TWIST_PERIOD_S = 0.02  # the stream's rate, 50 Hz


@pytest.fixture(scope="module")
def repeated(robot_factory) -> Robot:
    """Driving at 0.5 m/s for HOLD_S; then the host stops making new TWIST_CMD frames and its
    last one goes out again, unchanged (the same seq), at 50 Hz for REPEAT_S, as a stuck host,
    USB adapter or gateway would send it (python-can, the stream's own thread and cadence, so
    the first repeat comes 20 ms after the last new frame); then nothing."""
    with robot_factory("repeated") as robot:
        robot.mode(MODE_ENABLE)
        robot.twist(0.5, 0.0, 0.0)
        robot.start_stream(TWIST_PERIOD_S)
        time.sleep(HOLD_S)
        robot.repeat_last_twist(mark="stuck")
        time.sleep(REPEAT_S)
        robot.stop_stream(mark="end")
        # STATUS and STATUS_COUNTERS (10 Hz; fewer where steps are lost) after the last repeat.
        time.sleep(1.5 if HOST_STALLS else 0.4)
    return robot


def test_a_repeated_twist_frame_stops_the_robot_and_is_counted(repeated: Robot) -> None:
    stuck = repeated.repeated_twist
    assert stuck is not None
    seq = repeated.db.decode_message(TWIST_CMD, stuck)["seq"]
    # The last new frame (the host's; the robot takes it), then the same bytes again.
    same = repeated.of(TWIST_CMD, repeated.marks["stuck"] - 0.5)
    same = [f for f in same if f.data == stuck]
    assert len(same) >= 2, "no repeat on the bus"
    last, repeats = same[0], same[1:]
    # Only repeats after the last new frame: the sender is stuck, not interleaving.
    assert not [f for f in repeated.of(TWIST_CMD, last.t) if f.data != stuck]
    gaps = [b.t - a.t for a, b in zip(same, same[1:])]
    print(f"repeated twist: seq {seq}, {len(repeats)} repeats in {repeats[-1].t - last.t:.3f} s after "
          f"the last new frame (gaps {min(gaps) * 1e3:.1f} to {max(gaps) * 1e3:.1f} ms)")
    want = REPEAT_S / TWIST_PERIOD_S
    assert (0.5 if HOST_STALLS else 0.9) * want <= len(repeats) <= want + 2, len(repeats)
    if not HOST_STALLS:
        # Often enough that a robot taking them would never see its command time out.
        assert max(gaps) < COMMAND_TIMEOUT_S / 2, max(gaps)

    # The motors stop as if the host were silent: counted from the last new frame.
    zero = _zero_from(repeated, last.t, repeated.marks["end"] + 0.3)
    latency = zero - last.t
    during = sum(1 for f in repeats if f.t < zero)
    print(f"repeated twist: zero currents {latency * 1e3:.1f} ms after the last new TWIST_CMD, "
          f"{during} repeats before (budget {STOP_BUDGET_S * 1e3:.0f} ms{timing_note()})")
    assert COMMAND_TIMEOUT_S - 0.002 <= latency <= STOP_BUDGET_S + TIMING_SLACK_S
    assert during >= (1 if HOST_STALLS else 3), "the stop came before the repeats could have kept it going"
    status = repeated.status_in(zero, math.inf)
    assert (status["state"], status["fault"]) == (STATE_DISABLED, FAULT_WATCHDOG), status

    # Every repeat counted, those after the stop too; none is a rejected frame.
    controller = repeated.runner_stats["controller"]
    print(f"repeated twist: the runner counted {controller['repeated_seq']} repeats of "
          f"{len(repeats)} on the bus; rejected {controller['rx_errors']}")
    assert controller["repeated_seq"] == len(repeats), controller
    assert sum(controller["rx_errors"].values()) == 0, controller

    # On the bus: a STATUS_COUNTERS after every STATUS, its count never ahead of the repeats
    # candump saw before it and, but for those still on their way to the runner, not behind.
    _statuses(repeated, repeated.marks["stuck"], repeated.marks["end"])
    statuses = repeated.of(STATUS)
    counters = repeated.decoded(STATUS_COUNTERS)
    assert len(counters) == len(statuses), (len(counters), len(statuses))
    for (t, c), s in zip(counters, statuses):
        assert 0.0 <= t - s.t <= 0.002 + TIMING_SLACK_S, (t, s.t)
        on_bus = sum(1 for f in repeats if f.t <= t)
        arrived = sum(1 for f in repeats if f.t < t - 0.002 - TIMING_SLACK_S)
        assert arrived <= c["repeated_seq"] <= on_bus, (t, c, arrived, on_bus)
        assert (c["wrong_dlc"], c["out_of_range"], c["non_finite"]) == (0, 0, 0), c
    t, c = counters[-1]
    assert t > repeats[-1].t + 0.002 + TIMING_SLACK_S, "no STATUS_COUNTERS after the last repeat"
    assert c["repeated_seq"] == len(repeats), c


# --- malformed frames ------------------------------------------------------------------------

FLOOD_S = 2.0
# The flood, in frames per second per kind (can-utils cangen, one process per kind): five
# kinds at 1,000/s natively, about the most a 1 Mbit/s bus carries on top of the drives'
# 4,000 feedback frames/s. The emulated machine cannot keep up with that: 200/s per kind.
FLOOD_RATE = 200 if HOST_STALLS else 1000
# (kind the runner counts it as, cangen arguments, predicate recognising it in candump)
MALFORMED = [
    ("wrong_dlc", ["-I", "301", "-L", "4", "-D", "r"], lambda f: f.id == TWIST_CMD and len(f.data) == 4 and not f.remote),
    ("out_of_range", ["-I", "302", "-L", "1", "-D", "09"], lambda f: f.id == 0x302 and f.data == b"\x09"),
    ("unknown_id", ["-I", "123", "-L", "8", "-D", "r"], lambda f: f.id == 0x123 and not f.extended),
    ("extended_id", ["-e", "-I", "1ABCDEF0", "-L", "8", "-D", "r"], lambda f: f.extended),
    ("remote", ["-I", "301", "-R", "-L", "8"], lambda f: f.remote),
]


def _drive_through(robot: Robot, twist: tuple[float, float, float], name: str, cangen: str,
                   arg_sets: Iterable[Sequence[str]], after_s: float) -> None:
    """Enables and streams `twist`; after 1 s runs `cangen` with each of `arg_sets`
    (`run_cangen`) between the marks `name` and `{name}_end`; drives on for `after_s`, then
    stops (mark "end")."""
    robot.mode(MODE_ENABLE)
    robot.twist(*twist)
    robot.start_stream()
    time.sleep(1.0)
    robot.marks[name] = time.time()
    run_cangen(cangen, robot.iface, arg_sets)
    robot.marks[f"{name}_end"] = time.time()
    time.sleep(after_s)
    robot.stop_stream(mark="end")
    time.sleep(0.2)


@pytest.fixture(scope="module")
def malformed(robot_factory, can_utils) -> Robot:
    """Driving at 0.4 m/s while a flood of malformed frames arrives for FLOOD_S seconds."""
    cangen = can_utils("cangen")
    count = str(int(FLOOD_RATE * FLOOD_S))
    gap_ms = f"{1000.0 / FLOOD_RATE:g}"
    with robot_factory("malformed", runner_log=True) as robot:
        # -p 10: on a full queue (ENOBUFS) wait and retry, so every frame goes out.
        _drive_through(robot, (0.4, 0.0, 0.0), "flood", cangen,
                       (["-g", gap_ms, "-n", count, "-p", "10", *args] for _, args, _ in MALFORMED), 1.0)
    return robot


def test_malformed_frames_are_counted_exactly(malformed: Robot) -> None:
    counted = malformed.runner_stats["controller"]["rx_errors"]
    flood = [f for f in malformed.frames if f.t >= malformed.marks["flood"] - 0.01]
    on_bus = {kind: sum(1 for f in flood if match(f)) for kind, _, match in MALFORMED}
    t0, t1 = malformed.marks["flood"], malformed.marks["flood_end"]
    total = sum(on_bus.values())
    print(f"flood: {total} malformed frames in {t1 - t0:.2f} s ({total / (t1 - t0):.0f}/s); on the "
          f"bus by kind {on_bus}; the runner counted {counted}")
    # Every frame cangen was asked for went out (candump saw it) ...
    for kind, n in on_bus.items():
        assert n == int(FLOOD_RATE * FLOOD_S), (kind, n)
    # ... and the runner counted each one, by kind.
    for kind, n in on_bus.items():
        assert counted[kind] == n, (kind, counted[kind], n)
    assert counted["non_finite"] == 0
    # STATUS carries the counts (unknown_ids; rx_errors: the other rejected frames).
    last = malformed.decoded(STATUS)[-1][1]
    assert last["unknown_ids"] == min(on_bus["unknown_id"], 0xFFFF), last
    assert last["rx_errors"] == min(total - on_bus["unknown_id"], 0xFFFF), last


def test_malformed_flood_is_ignored_and_the_rate_kept(malformed: Robot) -> None:
    t0, t1 = malformed.marks["flood"], malformed.marks["flood_end"]
    for t, status in _statuses(malformed, t0, t1 + 0.5):
        assert (status["state"], status["fault"]) == (STATE_ENABLED, FAULT_NONE), (t, status)
    # The control rate: one motor command per 1 ms period, during the flood as before it.
    during = len(malformed.of(DJI_CMD_1_4, t0, t1)) / (t1 - t0)
    before = len(malformed.of(DJI_CMD_1_4, t0 - 0.8, t0)) / 0.8
    stats = malformed.runner_stats
    print(f"motor commands: {before:.0f}/s before the flood, {during:.0f}/s during it; runner "
          f"{stats['overruns']} overruns in {stats['steps']} steps, jitter {stats['jitter']}")
    # Kept: natively the full 1 kHz through the flood. The emulated machine runs the loop
    # below 1 kHz with or without a flood, and every process that receives the flood's frames
    # (runner, plant, candump) takes from the same two emulated CPUs: there the loop must keep
    # at least 60 % of its rate before the flood.
    assert during >= (0.6 if HOST_STALLS else 0.8) * before, (before, during)
    if not HOST_STALLS:
        assert during >= 980, during
    # Still driving at the commanded speed.
    vx = mean(v["vx"] for _, v in malformed.decoded(ODOM_VELOCITY, t0, t1))
    assert abs(vx - 0.4) <= VEL_TOL, vx


# --- ODrive: the other motor protocol, and non-finite values ---------------------------------

NON_FINITE = 200


@pytest.fixture(scope="module")
def odrive(robot_factory, configs, can_utils) -> Robot:
    cangen = can_utils("cangen")
    # Get_Encoder_Estimates (command 0x09) of node 0 with a NaN position and of node 1 with an
    # infinite velocity, every 4 ms between the drives' real ones (cangen: the twist stream
    # keeps the Python interpreter to itself).
    nan_pos = struct.pack("<ff", math.nan, 0.0).hex().upper()
    inf_vel = struct.pack("<ff", 0.0, math.inf).hex().upper()
    with robot_factory("odrive", config=configs["odrive"]) as robot:
        _drive_through(robot, (0.3, 0.0, 0.4), "nan", cangen, (
            ["-I", f"{ident:03X}", "-L", "8", "-D", data, "-g", "4", "-n", str(NON_FINITE // 2), "-p", "10"]
            for ident, data in ((0 << 5 | 0x09, nan_pos), (1 << 5 | 0x09, inf_vel))
        ), 0.8)
    return robot


def test_odrive_non_finite_estimates_are_counted_and_ignored(odrive: Robot) -> None:
    counted = odrive.runner_stats["controller"]["rx_errors"]
    print(f"ODrive: {NON_FINITE} non-finite estimates sent; runner counted {counted}")
    assert counted["non_finite"] == NON_FINITE, counted
    assert sum(counted.values()) == NON_FINITE, counted
    t0, t1 = odrive.marks["nan"], odrive.marks["end"]
    for t, status in _statuses(odrive, t0, t1):
        assert (status["state"], status["fault"]) == (STATE_ENABLED, FAULT_NONE), (t, status)
    vel = odrive.decoded(ODOM_VELOCITY, t0, t1)
    got = (mean(v["vx"] for _, v in vel), mean(v["wz"] for _, v in vel))
    print(f"ODrive odometry during the injection: vx {got[0]:.4f} m/s, wz {got[1]:.4f} rad/s")
    assert abs(got[0] - 0.3) <= VEL_TOL and abs(got[1] - 0.4) <= WZ_TOL, got
    # The ODrive side of the protocol: velocity setpoints (Set_Input_Vel, node << 5 | 0x0D) at
    # 200 Hz to every node, the two whose estimates were non-finite included, sent by the
    # steps that run (MIN_STEP_RATIO; one CI run in the emulated machine made 28 %).
    for node in range(4):
        setpoints = odrive.of(node << 5 | 0x0D, t0, t1)
        assert len(setpoints) >= MIN_STEP_RATIO * 200 * (t1 - t0), (node, len(setpoints))


# --- the runner's own MCAP log (`mecanum-runner --log`) ------------------------------------


@pytest.mark.parametrize("session", ["stops", "malformed", "link_gap"])
def test_runner_log_replays_bit_identical_and_reads_with_rosbags(request, session, plant_bin) -> None:
    """The runner's log of a session (stops: driving, the watchdog's stop, status polls, an
    e-stop and its reset; malformed: driving through a flood of malformed frames; link_gap:
    the interface down for 2 s mid-drive):
    `hostsim replay` runs a fresh core at the logged step times on the logged inbound frames
    and gets every outbound frame bit for bit (exit 0); rosbags reads every message, and the
    counts are the runner's own."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    robot: Robot = request.getfixturevalue(session)
    assert robot.runner_mcap is not None and robot.runner_mcap.is_file()
    stats = robot.runner_stats
    proc = subprocess.run(
        [str(plant_bin), "replay", str(robot.runner_mcap), "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads(proc.stdout)
    print(f"{session}: hostsim replay of the runner's log: {report['steps']} steps, {report['fed']} "
          f"frames fed, {report['compared']} compared, {report['verdict']}; log {stats['log']}")
    assert report["identical"] and report["complete"], report
    # Every step, plus the shutdown; every frame the runner took; every frame its core sent.
    assert report["steps"] == stats["steps"] + 1
    assert report["fed"] == stats["frames_received"]
    sent = (stats["frames_sent"] + stats["send_errors"] + stats["link"]["frames_not_sent"]
            + stats["shutdown"]["frames"])
    assert report["compared"] == sent
    assert stats["log"]["dropped"] == 0, stats["log"]

    topics = collections.Counter()
    texts = []
    with AnyReader([robot.runner_mcap], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for connection, _, raw in reader.messages():
            topics[connection.topic] += 1
            message = reader.deserialize(raw, connection.msgtype)
            if connection.topic == "/rosout":
                texts.append(message.msg)
            elif connection.topic == "/firmware/steps":
                assert message.kind in (0, 1)
    assert topics["/can/rx"] == stats["frames_received"]
    assert topics["/can/tx"] == sent
    assert topics["/firmware/steps"] == stats["steps"] + 1
    assert topics["/odom"] == topics["/joint_states"] == topics["/diagnostics"] > stats["steps"] // 10
    assert sum(topics.values()) == stats["log"]["messages"]
    print(f"{session}: rosbags read {dict(topics)}; /rosout {texts}")
    assert "state ENABLED, fault NONE" in texts
    if session == "stops":
        assert "state DISABLED, fault WATCHDOG" in texts
        assert any(t.startswith("state ESTOP") for t in texts)
    elif session == "malformed":
        assert stats["controller"]["rx_errors"]["wrong_dlc"] > 0
    else:
        assert sum(t.startswith("CAN link lost") for t in texts) == 1, texts
        assert sum(t.startswith("CAN link back after") for t in texts) == 1, texts


def test_parameters_set_while_driving_are_answered_within_two_periods_and_logged(stops) -> None:
    """The stops session's fourth drive: `mecanum-drive param set gains.kp 1.5` and
    python-canopen's write of gains.kv to the runner's parameter service (node 127) while it
    drives. Each request is answered within two control periods (candump's kernel
    timestamps), the robot stays enabled, the heartbeat carries the new configuration id, and
    the runner's log says each change on /rosout."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    cli = stops.param_cli
    assert cli.returncode == 0 and cli.stdout.strip() == "gains.kp = 1.5", cli.stdout + cli.stderr
    assert stops.param_kv == pytest.approx(0.05)
    t0, t1 = stops.marks["params"], stops.marks["end"]
    requests, answers = stops.of(0x67F, t0=t0, t1=t1), stops.of(0x5FF, t0=t0, t1=t1)
    # Set and read back, each: kp by the command line, kv by python-canopen.
    assert len(requests) == len(answers) == 4, (requests, answers)
    for request, answer in zip(requests, answers):
        assert answer.data[1:4] == request.data[1:4], (request, answer)
        assert answer.data[0] != 0x80, f"refused: {answer}"
        assert answer.t - request.t <= 2 * CONTROL_PERIOD_S, (answer.t - request.t, request, answer)
    assert stops.status_in(t0, t1)["state"] == STATE_ENABLED
    ids = {f.data[6] | f.data[7] << 8 for f in stops.of(0x31F, t0=t1)}
    assert len(ids) == 1, ids
    with AnyReader([stops.runner_mcap], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        texts = [reader.deserialize(raw, c.msgtype).msg for c, _, raw in reader.messages()
                 if c.topic == "/rosout"]
    kp = [t for t in texts if t.startswith("gains.kp ")]
    kv = [t for t in texts if t.startswith("gains.kv ")]
    assert len(kp) == len(kv) == 1, texts
    assert kp[0].startswith("gains.kp 1.2 -> 1.5, config 0x") and kv[0].endswith(f"0x{ids.pop():04x}"), (kp, kv)


# --- the link: the interface goes down mid-drive and comes back ------------------------------

LINK_DOWN_S = 2.0
# The runner tries to reopen the interface 10 ms after the loss, doubling to every 200 ms: it
# is back at most that long after the link (plus a step, and the emulation's slack).
LINK_RETRY_MAX_S = 0.2


def _ip_link(iface: str, state: str) -> None:
    from conftest import vcan_unavailable

    proc = subprocess.run(["ip", "link", "set", state, "dev", iface], capture_output=True, text=True)
    if proc.returncode != 0:
        vcan_unavailable(f"cannot set {iface} {state} (needs CAP_NET_ADMIN)",
                         f"ip link set {state} dev {iface}: {proc.stderr.strip()}")


class _LinkSwitch:
    """One `ip -batch -` process that sets the interface down and up when told: both changes
    come from one running process, so the link is down for the time between the two calls
    (a process start for each would add its own start-up, hundreds of milliseconds on a slow
    machine, to the time the link was down)."""

    def __init__(self, iface: str) -> None:
        _ip_link(iface, "up")  # fails or skips here, not mid-session, without CAP_NET_ADMIN
        self.iface = iface
        self.proc = subprocess.Popen(["ip", "-batch", "-"], stdin=subprocess.PIPE, text=True)

    def set(self, state: str) -> float:
        """Sets the link `state` ("down" or "up"); returns the wall time just after."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"link set {state} dev {self.iface}\n")
        self.proc.stdin.flush()
        return time.time()

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        assert self.proc.wait(timeout=30) == 0, f"ip -batch exited with {self.proc.returncode}"


@pytest.fixture(scope="module")
def link_gap(robot_factory) -> Robot:
    """Driving forward, the interface is set down for LINK_DOWN_S and up again, while the host
    goes on streaming twists (it does not know: its sends fail meanwhile). The runner must
    survive, say so, and keep the robot stopped until a reset and a new enable, which then
    drive it again."""
    with robot_factory("link", runner_log=True) as robot:
        robot.mode(MODE_ENABLE, mark="enable")
        robot.twist(0.3, 0.0, 0.0)
        robot.start_stream(tolerate_send_errors=True)
        switch = _LinkSwitch(robot.iface)
        time.sleep(1.0)
        robot.marks["down"] = switch.set("down")
        time.sleep(LINK_DOWN_S)
        robot.marks["up"] = switch.set("up")
        switch.close()
        # Twists keep coming: not an enable.
        time.sleep(1.0)
        robot.mode(MODE_RESET, mark="reset")
        time.sleep(0.1)
        robot.mode(MODE_ENABLE, mark="enable2")
        time.sleep(1.0)
        robot.stop_stream(mark="end")
        time.sleep(0.3)
    return robot


def test_the_runner_survives_the_link_going_down_and_keeps_the_robot_stopped(link_gap: Robot) -> None:
    robot = link_gap
    stats = robot.runner_stats
    link = stats["link"]
    down_s = link["down_us"] / 1e6
    out = robot.outputs["runner"]
    print(f"link gap: runner link report {link}; send errors {stats['send_errors_by_kind']}, receive "
          f"errors {stats['rx_errors_by_kind']}; host sends that failed: {robot.stream_send_errors}")
    print("\n".join(line for line in out.splitlines() if "link" in line))
    # One loss, one recovery, and the gap as long as the link was down (the runner notices the
    # loss at its next step and the recovery at its next reopen attempt).
    assert (link["losses"], link["recoveries"], link["down_at_stop"]) == (1, 1, False), link
    link_down_s = robot.marks["up"] - robot.marks["down"]
    print(f"link gap: down {link_down_s:.3f} s as the test set it, {down_s:.3f} s as the runner saw it")
    assert link_down_s - 0.1 <= down_s <= link_down_s + LINK_RETRY_MAX_S + 0.1 + 10 * TIMING_SLACK_S, down_s
    assert link["reopen_attempts"] >= 2 and link["frames_not_sent"] > 0, link
    kinds = stats["send_errors_by_kind"]["link_down"] + stats["rx_errors_by_kind"]["link_down"]
    assert kinds >= 1, (stats["send_errors_by_kind"], stats["rx_errors_by_kind"])
    assert robot.stream_send_errors > 0, "the host's sends did not fail: was the link down?"
    # It said so as it happened: the loss, then the recovery with the core's (not driving) state.
    lost = re.search(r"link LOST at [\d.]+ s \((.*)\)", out)
    back = re.search(r"link back at [\d.]+ s after ([\d.]+) s down \(\d+ reopen attempts\); the core is (\w+)", out)
    assert lost and back, out
    assert "Network is down" in lost.group(1)
    assert abs(float(back.group(1)) - down_s) < 0.002, (back.group(1), down_s)
    assert back.group(2) != "ENABLED", back.group(0)
    # The core kept stepping through the gap: its steps over the run are those of the elapsed
    # time, the gap included.
    assert stats["steps"] >= MIN_STEP_RATIO * stats["elapsed_us"] / 1e3, stats["steps"]

    # Driving before: currents commanded.
    before = robot.of(DJI_CMD_1_4, robot.marks["enable"] + 0.5, robot.marks["down"])
    assert any(dji_currents(c) != (0, 0, 0, 0) for c in before)
    # After the link is back, with twists still streaming: zero currents, never Enabled.
    up, reset = robot.marks["up"], robot.marks["reset"]
    settled = up + LINK_RETRY_MAX_S + 0.1 + 10 * TIMING_SLACK_S
    after = robot.of(DJI_CMD_1_4, settled, reset)
    assert after, "no motor commands after the link came back"
    assert all(dji_currents(c) == (0, 0, 0, 0) for c in after), [dji_currents(c) for c in after[:5]]
    statuses = _statuses(robot, settled, reset)
    assert all(s["state"] != STATE_ENABLED for _, s in statuses), statuses[:3]
    # A reset and an enable drive it again.
    enable2 = _next_mode(robot, robot.marks["enable2"] - 0.05, MODE_ENABLE)
    assert robot.status_in(enable2 + 0.3, robot.marks["end"])["state"] == STATE_ENABLED
    again = robot.of(DJI_CMD_1_4, enable2 + 0.3, robot.marks["end"])
    assert any(dji_currents(c) != (0, 0, 0, 0) for c in again)
    # The link is in the plant's statistics too (it survived: its sends failed meanwhile).
    assert robot.plant_stats["send_errors"] > 0, robot.plant_stats


def test_exit_on_link_loss_stops_with_status_3(runner_bin, vcan, config, tmp_path) -> None:
    """`--exit-on-link-loss`: the runner stops at the loss with status 3 and a message."""
    stats = tmp_path / "runner.json"
    proc = subprocess.Popen(
        [str(runner_bin), "--iface", vcan, "--config", str(config), "--exit-on-link-loss",
         "--stats-json", str(stats)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        time.sleep(1.0)
        assert proc.poll() is None, proc.communicate()[0]
        _ip_link(vcan, "down")
        try:
            out, _ = proc.communicate(timeout=30)
        finally:
            _ip_link(vcan, "up")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    print(out)
    assert proc.returncode == 3, out
    assert "CAN link lost" in out and "--exit-on-link-loss" in out, out
    report = json.loads(stats.read_text())
    assert report["stop"] == "link_lost" and report["link"]["losses"] == 1, report


# --- rate: the runner under a sustained stream of frames -----------------------------------

RATE_S = 30.0
RATE_TARGET = 8000  # frames/s
RATE_BURST = 40 if HOST_STALLS else 10


def test_rate_8000_frames_per_second_for_30_s_without_loss(
    runner_bin, config, can_utils, vcan, tmp_path
) -> None:
    """cangen sends frames of an id nobody uses (0x123) at >= 8,000/s for 30 s; the runner,
    alone on the bus, must receive and count every one (its unknown-id counter equals
    cangen's count) and keep its 1 kHz loop. Jitter figures go to docs/benchmarks.md."""
    stats_path = tmp_path / "runner.json"
    runner = subprocess.Popen(
        [str(runner_bin), "--iface", vcan, "--config", str(config), "--stats-json", str(stats_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # The runner prints this line once its socket is bound: frames sent before would be lost.
        ready = runner.stderr.readline()
        assert "stop with Ctrl-C" in ready, ready + runner.communicate(timeout=10)[1]
        # BURST frames every 1 ms: 10,000/s nominal natively. The emulated machine's sleeps
        # overshoot by about a millisecond, so there the bursts are bigger. (The rate is
        # measured either way.)
        # Chunks of a known size until 30 s have passed, so that the total is known exactly
        # (for the loss check) however fast the machine is.
        chunk = 40_000  # few cangen starts, which are slow on the emulated machine
        count = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < RATE_S:
            run_cangen(
                can_utils("cangen"),
                vcan,
                [["-I", "123", "-L", "8", "-D", "i", "-g", "1", "-c", str(RATE_BURST), "-n", str(chunk), "-p", "100"]],
                timeout=RATE_S * 10,
            )
            count += chunk
        elapsed = time.monotonic() - t0
        time.sleep(0.5)
    finally:
        runner.send_signal(signal.SIGINT)
        try:
            _, err = runner.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            runner.kill()  # not left on vcan0 for the tests that follow
            _, err = runner.communicate()
    assert runner.returncode == 0, err
    stats = json.loads(stats_path.read_text())
    rate = count / elapsed
    jitter = stats["jitter"]
    print(f"rate: {count} frames in {elapsed:.2f} s = {rate:.0f} frames/s; runner received "
          f"{stats['frames_received']}, counted {stats['controller']['rx_errors']['unknown_id']} "
          f"unknown; {stats['steps']} steps, {stats['overruns']} overruns; jitter p50 "
          f"{jitter['p50_us']} µs p99 {jitter['p99_us']} µs max {jitter['max_us']} µs"
          f"{' (emulated machine)' if SLOW_CPU else ''}")
    assert stats["frames_received"] == count, "the runner lost frames"
    assert stats["controller"]["rx_errors"]["unknown_id"] == count
    assert stats["rx_errors"] == 0
    assert rate >= RATE_TARGET, f"only {rate:.0f} frames/s offered"
    # ... and it kept its 1 kHz loop while it did (the stalled-loop bound).
    assert stats["steps"] >= MIN_STEP_RATIO * stats["elapsed_us"] * 1e-3, stats
