"""The Python package `mecanum_drive` (python/) on python-can's virtual bus, against a scripted
robot (tests/scripted_robot.py): the keep-alive stream's rate and alive counter, the e-stop
ordering, what every way out sends, and every error path. The package is the installed one
(scripts/test.sh installs ./python into the virtual environment); its behaviour against the
real firmware on vcan0 is in tests/test_vcan_drive.py.
"""

from __future__ import annotations

import itertools
import json
import math
import pathlib
import statistics
import subprocess
import sys
import textwrap
import threading
import time
from typing import Any

import can
import pytest

import mecanum_drive
from mecanum_drive import NotResponding, ProtocolMismatch, Robot, RobotFault, cli, protocol
from scripted_robot import FAULTS, ScriptedRobot

ROOT = pathlib.Path(__file__).resolve().parent.parent
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    """A virtual channel of its own for each test."""
    return f"mecanum-test-{next(_channels)}"


def host_bus(channel: str) -> can.BusABC:
    return can.Bus(interface="virtual", channel=channel, receive_own_messages=False)


def test_the_package_carries_the_repositorys_dbc() -> None:
    """One source of the layout: the installed copy is the repository's file, byte for byte,
    and the package speaks the version its comment states."""
    path = protocol.dbc_path()
    assert "site-packages" in str(path) or "dist-packages" in str(path), path
    assert path.read_bytes() == (ROOT / "dbc" / "mecanum_robot.dbc").read_bytes()
    text = (ROOT / "dbc" / "mecanum_robot.dbc").read_text()
    assert f'CM_ "Mecanum robot CAN protocol, version {mecanum_drive.protocol_version()} ' in text
    assert (pathlib.Path(mecanum_drive.__file__).parent / "py.typed").is_file()


def test_the_keep_alive_streams_at_its_rate_with_an_alive_counter(channel: str) -> None:
    """50 Hz by default: over 1.5 s the robot receives 75 frames (within 10 %: the thread
    keeps absolute deadlines but restarts its schedule when the OS runs it late, as on a
    loaded two-core machine), no gap as long as the firmware's 100 ms command timeout, and
    `seq` counting up by one, wrapping at 256. (The rate's jitter is a figure for a
    benchmark, not for this test.)"""
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.enable()
        robot.wait_state("ENABLED", timeout=1.0)
        robot.drive(0.2, 0.0, 0.0)
        time.sleep(0.2)
        t0 = time.monotonic()
        time.sleep(1.5)
        window = [r for r in fake.frames("TWIST_CMD") if r.t >= t0][:-1]
        time.sleep(0.15)
        counters = robot.counters
    assert abs(len(window) - 75) <= 7, len(window)
    # The robot took every frame as new (version 3's rule), and said so.
    assert fake.repeated_seq == 0
    assert counters is not None and counters.repeated_seq == 0
    gaps = [b.t - a.t for a, b in zip(window, window[1:])]
    assert max(gaps) < 0.1, max(gaps)
    assert statistics.mean(gaps) == pytest.approx(0.02, rel=0.1)
    seqs = [r.signals["seq"] for r in window]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:])), seqs
    assert all(r.signals["vx"] == pytest.approx(0.2) for r in window)


def test_the_robot_moves_and_odometry_arrives_by_callback_and_iterator(channel: str) -> None:
    seen: list[mecanum_drive.Odometry] = []
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.on_odometry(seen.append)
        robot.enable()
        robot.wait_state("ENABLED", timeout=1.0)
        robot.drive(0.5, 0.0, 0.0)
        updates = list(itertools.islice(robot.odometry_updates(timeout=1.0), 30))
        time.sleep(0.5)
        odom, status = robot.odometry, robot.status
    # 30 updates at 100 Hz in order, x rising at 0.5 m/s.
    assert len(updates) == 30
    assert all(b.received >= a.received for a, b in zip(updates, updates[1:]))
    assert updates[-1].x > updates[0].x
    assert odom is not None and odom.vx == pytest.approx(0.5, abs=1e-3)
    assert odom.x == pytest.approx(fake.pose[0], abs=0.02)
    assert len(seen) >= 60
    assert status is not None and status.state == "ENABLED" and status.motors_online == (True,) * 4


def test_estop_goes_out_at_once_and_no_motion_follows_it(channel: str) -> None:
    """Streaming at 200 Hz: the ESTOP reaches the robot within 20 ms of the call, and every
    twist after it is zero; the robot latches ESTOP."""
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True, rate_hz=200) as robot:
        robot.enable()
        robot.wait_state("ENABLED", timeout=1.0)
        robot.drive(1.0, 0.5, 0.2)
        time.sleep(0.3)
        called = time.monotonic()
        robot.estop()
        robot.wait_state("ESTOP", timeout=1.0)
        time.sleep(0.2)
        (estop,) = fake.frames("ESTOP")
        after = [r for r in fake.frames("TWIST_CMD") if r.t > estop.t]
    assert estop.t - called < 0.02, estop.t - called
    assert estop.signals["magic"] == 0xE5
    assert len(after) >= 20
    assert all((r.signals["vx"], r.signals["vy"], r.signals["wz"]) == (0, 0, 0) for r in after)


def test_leaving_the_block_sends_a_zero_twist_then_disable(channel: str) -> None:
    for how in ("normally", "by an exception"):
        with ScriptedRobot(channel + how) as fake:
            try:
                with Robot(host_bus(channel + how), owns_bus=True) as robot:
                    robot.enable()
                    robot.wait_state("ENABLED", timeout=1.0)
                    robot.drive(0.3, 0.0, 0.1)
                    time.sleep(0.1)
                    if how != "normally":
                        raise KeyError("the user's program failed")
            except KeyError:
                pass
            time.sleep(0.1)
            last_two = [(r.name, r.signals) for r in fake.received[-2:]]
            assert fake.state == "DISABLED", how
        assert last_two[0][0] == "TWIST_CMD" and (last_two[0][1]["vx"], last_two[0][1]["wz"]) == (0, 0), how
        assert last_two[1] == ("MODE_CMD", {"request": 0}), how


def test_the_interpreters_exit_stops_the_robot(tmp_path: pathlib.Path) -> None:
    """A program that drives and ends without closing: at exit the package sends a zero twist
    and the disable (the robot in the same process records them; its report is printed by an
    exit handler registered before the robot's, so it runs after it)."""
    script = tmp_path / "forgetful.py"
    script.write_text(textwrap.dedent(
        f"""
        import atexit, json, sys, time
        sys.path.insert(0, {str(ROOT / "tests")!r})
        import can
        from scripted_robot import FAULTS, ScriptedRobot
        from mecanum_drive import Robot

        fake = ScriptedRobot("exit").__enter__()
        def report():
            # The robot's thread receives what the package sent at exit: wait for the disable
            # to arrive there (not for the package: it has sent it already).
            deadline = time.monotonic() + 10
            while not any(r.signals == {{"request": 0}} for r in fake.frames("MODE_CMD")):
                if time.monotonic() > deadline:
                    break
                time.sleep(0.01)
            print(json.dumps([(r.name, r.signals) for r in fake.received[-2:]]))
        atexit.register(report)
        robot = Robot(can.Bus(interface="virtual", channel="exit"))
        robot.enable()
        robot.wait_state("ENABLED", timeout=5.0)  # a loaded machine starts threads slowly
        robot.drive(0.4, 0.0, 0.0)
        time.sleep(0.2)
        sys.exit(0)  # no close(), no with block
        """
    ))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    last_two = json.loads(proc.stdout.strip().splitlines()[-1])
    assert last_two[0][0] == "TWIST_CMD" and last_two[0][1]["vx"] == 0, last_two
    assert last_two[1] == ["MODE_CMD", {"request": 0}], last_two


@pytest.mark.parametrize(
    ("twist", "field"),
    [((40.0, 0, 0), "vx"), ((0, -33.0, 0), "vy"), ((0, 0, 1e9), "wz"), ((math.nan, 0, 0), "vx"), ((0, math.inf, 0), "vy")],
)
def test_speeds_outside_the_protocol_are_refused_naming_the_field(channel: str, twist, field: str) -> None:
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        with pytest.raises(ValueError, match=rf"^{field} = "):
            robot.drive(*twist)
        assert robot.setpoint == (0.0, 0.0, 0.0)
        assert fake.frames("TWIST_CMD") == []


def test_bad_settings_are_refused(channel: str) -> None:
    bus = host_bus(channel)
    try:
        with pytest.raises(ValueError, match="rate_hz = 5.*at least 20 Hz"):
            Robot(bus, rate_hz=5)
        with pytest.raises(ValueError, match="rate_hz = nan"):
            Robot(bus, rate_hz=math.nan)
        with ScriptedRobot(channel) as _fake, Robot(bus) as robot:
            with pytest.raises(ValueError, match="'MOVING': not one of"):
                robot.wait_state("MOVING")
            with pytest.raises(TimeoutError, match="did not reach ESTOP within 0.3 s"):
                robot.wait_state("ESTOP", timeout=0.3)
        with pytest.raises(RuntimeError, match="closed"):
            robot.drive(0, 0, 0)
    finally:
        bus.shutdown()


def test_a_silent_robot_is_not_responding(channel: str) -> None:
    """Three heartbeat periods (0.3 s) without a HEARTBEAT: flagged and raised, naming how long."""
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        robot.check()
        fake.heartbeats = False
        time.sleep(0.45)
        assert not robot.responding
        with pytest.raises(NotResponding, match=r"no HEARTBEAT from the robot for 0\.\d\d s"):
            robot.drive(0.1, 0, 0)
        fake.heartbeats = True
        time.sleep(0.25)
        assert robot.responding
        robot.check()
    # Nobody on the bus at all: a second for the first heartbeat, then not responding.
    with Robot(host_bus(channel + "-empty"), owns_bus=True) as robot:
        time.sleep(0.8)
        assert robot.responding
        time.sleep(0.3)
        with pytest.raises(NotResponding, match=r"no HEARTBEAT from the robot in the 1\.\d\d s since"):
            robot.enable()


def test_nothing_but_estop_and_disable_goes_out_before_the_first_heartbeat(channel: str) -> None:
    """The robot's first HEARTBEAT says its CiA 402 drives no longer take the protocol's block
    as their RPDO2 (docs/protocol.md, "The RPDO2 window"): until it comes, the keep-alive
    stream sends no twist and `enable` waits; DISABLE goes out at once. Counted in this
    process (`twists_sent`, the waiting call's thread), not from the fake's receive times."""
    fake = ScriptedRobot(channel)
    fake.heartbeats = False
    with fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.stop()  # starts the stream, at zero
        robot.disable()
        enabling = threading.Thread(target=robot.enable)
        enabling.start()
        time.sleep(0.3)
        assert robot.twists_sent == 0
        assert enabling.is_alive(), "enable() did not wait for the first HEARTBEAT"
        assert [r.signals for r in fake.frames("MODE_CMD")] == [{"request": 0}]
        fake.heartbeats = True
        enabling.join(timeout=1.0)
        assert not enabling.is_alive()
        robot.wait_state("ENABLED", timeout=1.0)
        assert robot.twists_sent > 0
        assert [r.signals for r in fake.frames("MODE_CMD")] == [{"request": 0}, {"request": 1}]


def test_a_process_that_reads_late_is_not_taken_for_a_silent_robot(channel: str) -> None:
    """The receiving thread stalls for 0.6 s (a busy computer, a long garbage collection) while
    the robot's HEARTBEATs wait on the bus: the robot responded all along, and `check` says
    so during the stall and after; a silence read on the bus is still one (the test above)."""
    with ScriptedRobot(channel), Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        stalled = threading.Event()
        on_message = robot._on_message

        def slow(msg: can.Message) -> None:
            if not stalled.is_set():
                stalled.set()
                time.sleep(0.6)
            on_message(msg)

        robot._on_message = slow  # type: ignore[method-assign]
        assert stalled.wait(1.0)
        time.sleep(0.45)  # 0.45 s into the stall: the last HEARTBEAT read is that old
        assert robot.responding
        robot.check()
        time.sleep(0.3)  # the stall is over and the waiting frames are read
        assert robot.responding


def test_wait_state_sees_a_state_reported_and_left_before_it_looked(channel: str) -> None:
    """The robot reports ENABLED and, before the waiting caller looks again, DISABLED (its
    watchdog stopped it): `wait_state("ENABLED")` returns that ENABLED STATUS, as the robot
    did reach it, instead of timing out with "last: DISABLED"."""
    db = protocol.database()

    def status(state: int, fault: int, seq: int) -> can.Message:
        data = db.get_message_by_name("STATUS").encode(
            {"state": state, "fault": fault, "rx_errors": 0, "unknown_ids": 0, "motors_online": 15,
             "heading_source": 0, "seq": seq})
        return can.Message(arbitration_id=0x312, data=data, is_extended_id=False, timestamp=time.time())

    with Robot(host_bus(channel), owns_bus=True) as robot:
        looking = threading.Event()
        check = robot.check

        def checking() -> None:  # wait_state has taken note of where it began
            looking.set()
            check()

        robot.check = checking  # type: ignore[method-assign]
        result: list[object] = []
        waiter = threading.Thread(target=lambda: result.append(robot.wait_state("ENABLED", timeout=1.0)))
        waiter.start()
        assert looking.wait(1.0)
        with robot._lock:  # both arrive before the waiter can look again
            robot._on_message(status(1, 0, 1))
            robot._on_message(status(0, 4, 2))
        waiter.join(2.0)
        assert len(result) == 1 and getattr(result[0], "state", None) == "ENABLED", result
        assert robot.status is not None and (robot.status.state, robot.status.fault) == ("DISABLED", "WATCHDOG")


def test_a_receiving_thread_that_stopped_is_reported_not_taken_for_a_live_robot(channel: str) -> None:
    """An `on_odometry` callback raises: the receiving thread stops, and from then on `check`
    raises NotResponding naming the error (nothing read, so no silence could be proven)."""
    with ScriptedRobot(channel), Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)

        def broken(odometry: object) -> None:
            raise ZeroDivisionError("a callback's bug")

        robot.on_odometry(broken)
        time.sleep(0.2)
        with pytest.raises(NotResponding, match=r"stopped reading the bus .*ZeroDivisionError"):
            robot.check()


def test_liveness_counts_only_a_silence_read_on_the_bus() -> None:
    """`_Liveness` by numbers: a silence is proven by frames read after the last HEARTBEAT
    (their stamps) or by the bus found empty, never by the reader's own lateness."""
    from mecanum_drive.robot import _Liveness

    live = _Liveness(start=100.0)
    assert live.silence() == 0.0
    live.empty(100.5)  # nothing on the bus for half a second since listening began
    assert live.silence() == pytest.approx(0.5)
    live.frame(1000.0)
    live.heartbeat(1000.0, 100.6)
    assert live.silence() == 0.0
    # Read late (no newer frame, the bus not found empty): nothing proven, however late.
    assert live.silence() == 0.0
    # Frames that arrived 0.35 s after the HEARTBEAT (their own stamps), read whenever.
    live.frame(1000.35)
    assert live.silence() == pytest.approx(0.35)
    # The bus found empty 0.5 s after the HEARTBEAT was read.
    live.empty(101.1)
    assert live.silence() == pytest.approx(0.5)
    # Frames without stamps prove nothing by stamps.
    other = _Liveness(start=0.0)
    other.frame(math.nan)
    other.heartbeat(math.nan, 1.0)
    other.frame(math.nan)
    assert other.silence() == 0.0


def test_missed_heartbeats_sets_how_long_a_silent_robot_is_tolerated(channel: str) -> None:
    """With `missed_heartbeats=6` a 0.45 s silence is tolerated (3 would not), 0.75 s is not;
    a value below 1 is refused naming it."""
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True, missed_heartbeats=6) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        fake.heartbeats = False
        time.sleep(0.45)
        assert robot.responding
        time.sleep(0.3)
        with pytest.raises(NotResponding, match=r"more than 6 periods"):
            robot.check()
    bus = host_bus(channel + "-bad")
    try:
        for bad in (0, -1, 2.5, True):
            with pytest.raises(ValueError, match=rf"missed_heartbeats = {bad!r}"):
                Robot(bus, missed_heartbeats=bad)  # type: ignore[arg-type]
    finally:
        bus.shutdown()


def test_another_protocol_version_is_refused_and_never_driven(channel: str) -> None:
    version = mecanum_drive.protocol_version()
    with ScriptedRobot(channel, protocol_version=version + 7) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.stop()  # the stream runs
        time.sleep(0.25)
        with pytest.raises(ProtocolMismatch, match=rf"protocol version {version + 7}; this package speaks version {version}"):
            robot.drive(0.5, 0, 0)
        with pytest.raises(ProtocolMismatch):
            robot.enable()
        time.sleep(0.1)
        twists = fake.frames("TWIST_CMD")
    assert len(twists) >= 10
    assert all(r.signals["vx"] == 0 for r in twists)


def test_a_fault_is_raised_by_name_and_reset_clears_it(channel: str) -> None:
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.enable()
        robot.wait_state("ENABLED", timeout=1.0)
        robot.drive(0.2, 0, 0)
        fake.set_fault("MOTOR_STALE")
        with pytest.raises(RobotFault, match="MOTOR_STALE") as caught:
            robot.wait_state("ESTOP", timeout=1.0)
        assert caught.value.fault == "MOTOR_STALE"
        assert robot.wait_state("FAULT", timeout=0.5).fault == "MOTOR_STALE"
        with pytest.raises(RobotFault):
            robot.drive(0.2, 0, 0)
        robot.reset()
        robot.wait_state("DISABLED", timeout=1.0)
        robot.check()


def test_a_status_stamped_before_the_reset_is_not_the_robots_state(channel: str) -> None:
    """A FAULT STATUS the kernel received before `reset()` went out, read only after it (the
    receiving thread running late), is older than the reset and must not make `check` or
    `wait_state` raise; one stamped after the reset still does. The frames carry chosen
    receive stamps (python-can's virtual bus with preserve_timestamps)."""
    status = protocol.database().get_message_by_name("STATUS")
    counters = protocol.database().get_message_by_name("STATUS_COUNTERS")

    def frame(message: Any, stamp: float, **signals: int) -> can.Message:
        return can.Message(arbitration_id=message.frame_id, data=message.encode(signals), is_extended_id=False,
                           timestamp=stamp)

    def fault(stamp: float) -> can.Message:
        return frame(status, stamp, state=2, fault=FAULTS["MOTOR_STALE"], rx_errors=0, unknown_ids=0,
                     motors_online=0x0F, heading_source=0, seq=0)

    def marker(stamp: float, n: int) -> can.Message:  # read after the frame before it
        return frame(counters, stamp, repeated_seq=n, wrong_dlc=0, out_of_range=0, non_finite=0)

    injector = can.Bus(interface="virtual", channel=channel, receive_own_messages=False, preserve_timestamps=True)
    try:
        with Robot(host_bus(channel), owns_bus=True) as robot, ScriptedRobot(channel, period_s=60.0):
            robot.wait_state("DISABLED", timeout=1.0)  # the scripted robot's first STATUS
            before = time.time()
            robot.reset()
            injector.send(fault(before - 0.001))
            injector.send(marker(before - 0.001, 1001))
            deadline = time.monotonic() + 1.0
            while (robot.counters is None or robot.counters.repeated_seq != 1001) and time.monotonic() < deadline:
                time.sleep(0.005)
            assert robot.counters is not None and robot.counters.repeated_seq == 1001
            assert robot.status is None, robot.status
            robot.check()
            after = time.time()
            injector.send(fault(after))
            injector.send(marker(after, 1002))
            deadline = time.monotonic() + 1.0
            while (robot.counters is None or robot.counters.repeated_seq != 1002) and time.monotonic() < deadline:
                time.sleep(0.005)
            assert robot.status is not None and robot.status.state == "FAULT", robot.status
            with pytest.raises(RobotFault, match="MOTOR_STALE"):
                robot.check()
    finally:
        injector.shutdown()


def test_the_heading_source_is_decoded_by_name(channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    """STATUS.heading_source (high nibble of byte 6, beside motors_online) by its DBC name; the
    command line shows it when it is not plain wheel heading."""
    common = ["--interface", "virtual", "--channel", channel]
    with ScriptedRobot(channel) as fake, Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        status = robot.status
        assert status is not None and status.heading_source == "WHEELS"
        fake.heading_source = 2
        time.sleep(0.25)
        status = robot.status
        assert status is not None and status.heading_source == "WHEELS_GYRO_SILENT"
        assert status.motors_online == (True,) * 4
        assert cli.main([*common, "status", "--once"]) == 0
        out = capsys.readouterr().out
        assert "heading   from WHEELS_GYRO_SILENT" in out
        assert f"protocol version {mecanum_drive.protocol_version()}, configuration id 0x0000" in out, out
        fake.heading_source = 1
        assert cli.main([*common, "status", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["heading_source"] == "GYRO"


def test_the_odometry_source_and_the_slip_are_decoded(channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    """ODOM_SLIP (protocol version 7, a robot with tracking pods): `Robot.slip` holds the slip
    estimate to the frame's resolution (0.001) and the source by its DBC name, which
    `odometry_source` reports; a change of source is seen with the next sample. The command
    line shows both."""
    common = ["--interface", "virtual", "--channel", channel]
    sent = (0.123, -0.0456, 0.0789)  # the last two between LSBs: the frame rounds them
    with ScriptedRobot(channel, odometry_source="PODS3", slip=sent) as fake, \
            Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        deadline = time.monotonic() + 1.0
        while robot.slip is None and time.monotonic() < deadline:
            time.sleep(0.005)
        slip = robot.slip
        assert slip is not None, "no ODOM_SLIP decoded within 1 s"
        print(f"Robot.slip: {slip}, age {slip.age() * 1e3:.1f} ms")
        assert isinstance(slip, mecanum_drive.Slip)
        assert (slip.vx, slip.vy, slip.wz) == pytest.approx(sent, abs=1e-3)
        assert (slip.vx, slip.vy, slip.wz) == pytest.approx((0.123, -0.046, 0.079), abs=1e-9)  # the frame's values
        assert slip.source == "PODS3" and robot.odometry_source == "PODS3"
        assert 0 <= slip.age() < 0.5
        fake.set_odometry_source("WHEELS_PODS_SILENT")  # slip 0, as the firmware sends it then
        time.sleep(0.1)
        assert robot.odometry_source == "WHEELS_PODS_SILENT"
        slip = robot.slip
        assert slip is not None and (slip.vx, slip.vy, slip.wz) == (0.0, 0.0, 0.0)
        fake.set_odometry_source("PODS2_GYRO", (-1.5, 2.25, -0.5))
        time.sleep(0.1)
        assert robot.odometry_source == "PODS2_GYRO"
        capsys.readouterr()
        assert cli.main([*common, "status", "--once"]) == 0
        out = capsys.readouterr().out
        assert "slip      vx -1.500 m/s  vy +2.250 m/s  wz -0.500 rad/s   odometry from PODS2_GYRO" in out, out
        assert cli.main([*common, "status", "--json"]) == 0
        status = json.loads(capsys.readouterr().out)
        assert status["odometry_source"] == "PODS2_GYRO"
        assert status["slip"] == pytest.approx({"vx": -1.5, "vy": 2.25, "wz": -0.5})


def test_a_robot_without_pods_has_wheel_odometry_and_no_slip(channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    """No ODOM_SLIP (a robot configured without tracking pods): `slip` stays None and
    `odometry_source` is WHEELS, while odometry arrives; the command line's view shows no
    slip line, its JSON the source WHEELS and a null slip."""
    common = ["--interface", "virtual", "--channel", channel]
    with ScriptedRobot(channel), Robot(host_bus(channel), owns_bus=True) as robot:
        robot.wait_state("DISABLED", timeout=1.0)
        time.sleep(0.1)  # ten odometry samples
        assert robot.odometry is not None
        assert robot.slip is None
        assert robot.odometry_source == "WHEELS"
        assert cli.main([*common, "status", "--once"]) == 0
        out = capsys.readouterr().out
        assert "slip" not in out and "odometry from" not in out, out
        assert cli.main([*common, "status", "--json"]) == 0
        status = json.loads(capsys.readouterr().out)
        assert (status["odometry_source"], status["slip"]) == ("WHEELS", None)


def test_the_command_line_on_a_virtual_bus(channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    """`mecanum-drive` commands in this process, against the scripted robot."""
    common = ["--interface", "virtual", "--channel", channel]
    with ScriptedRobot(channel, config_id=0xC0DE) as fake:
        assert cli.main([*common, "status", "--json"]) == 0
        status = json.loads(capsys.readouterr().out)
        assert status["state"] == "DISABLED" and status["responding"] and status["motors_online"] == [True] * 4
        assert status["protocol_version"] == mecanum_drive.protocol_version()
        assert status["config_id"] == "0xc0de"
        assert status["counters"] == {"repeated_seq": 0, "wrong_dlc": 0, "out_of_range": 0, "non_finite": 0}

        assert cli.main([*common, "drive", "--vx", "0.5", "--duration", "0.4"]) == 0
        out = capsys.readouterr().out
        assert "state     ENABLED" in out
        # The command returns once the robot reported DISABLED (the scripted robot's own state
        # changed before it sent that STATUS).
        assert out.rstrip().endswith("disabled: the robot reports DISABLED"), out
        # 0.5 m/s for 0.4 s, and until the stop's first frame (20 ms later at most, on a
        # quiet machine).
        assert fake.pose[0] == pytest.approx(0.2, abs=0.06), fake.pose
        assert fake.state == "DISABLED"

        assert cli.main([*common, "estop"]) == 0
        assert fake.state == "ESTOP"
        assert cli.main([*common, "reset"]) == 0
        assert fake.state == "DISABLED"

        assert cli.main([*common, "drive", "--vx", "99", "--duration", "0.1"]) == 1
        assert "vx = 99.0 m/s is outside the protocol's range" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--duration -1.0: must be a positive number"):
        cli.main([*common, "drive", "--duration", "-1"])
    with pytest.raises(SystemExit):
        cli.main([*common, "drive"])  # --duration is required
    capsys.readouterr()
    # Nobody answers: the error says so and the status is 1.
    assert cli.main(["--interface", "virtual", "--channel", channel + "-none", "--timeout", "0.4", "status", "--json"]) == 1
    assert "no HEARTBEAT" in capsys.readouterr().err


def test_the_package_type_checks_strictly() -> None:
    """`py.typed` is a promise: the installed package passes `mypy --strict`."""
    proc = subprocess.run([sys.executable, "-m", "mypy", "--strict", "--no-incremental", "-p", "mecanum_drive"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # The ROS 2 bridge's five modules included (mecanum_drive.ros2: rclpy is in this
    # environment, scripts/test.sh installs ./python[ros2,ray]), and the Ray driver's.
    assert "no issues found in 13 source files" in proc.stdout, proc.stdout


#: Python that runs with rclpy made unimportable (as where the ros2 extra is not installed).
WITHOUT_RCLPY = "import sys; sys.modules['rclpy'] = None; "


def test_the_package_works_without_rclpy_and_ros2_says_how_to_get_it() -> None:
    """Without ROS 2's Python client the package, its command line and mecanum_drive.ros2
    import (rclpy is imported only when the bridge starts); `mecanum-drive ros2` and
    `python -m mecanum_drive.ros2` exit 1 saying how to install it."""
    imports = subprocess.run(
        [sys.executable, "-c", WITHOUT_RCLPY + "import mecanum_drive, mecanum_drive.cli, mecanum_drive.ros2; "
         "assert 'rclpy' not in [m for m in sys.modules if sys.modules[m] is not None]; print('ok')"],
        capture_output=True, text=True, timeout=60, check=False)
    assert imports.returncode == 0 and imports.stdout.strip() == "ok", imports.stdout + imports.stderr
    for code, prog in [
        ("from mecanum_drive.cli import main; sys.exit(main(['ros2', '--channel', 'can0']))", "mecanum-drive ros2"),
        ("import runpy; sys.argv = ['x', '--ros-args', '-p', 'channel:=can0']; "
         "runpy.run_module('mecanum_drive.ros2', run_name='__main__')", "python -m mecanum_drive.ros2"),
    ]:
        proc = subprocess.run([sys.executable, "-c", WITHOUT_RCLPY + code], capture_output=True, text=True,
                              timeout=60, check=False)
        print(proc.stderr.strip())
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert proc.stderr.startswith(f"{prog}: the ROS 2 Python client is not importable ("), proc.stderr
        assert "pip install './python[ros2]'" in proc.stderr and "source /opt/ros/jazzy/setup.bash" in proc.stderr
