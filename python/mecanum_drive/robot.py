"""`Robot`: one mecanum robot on a CAN bus, driven through the robot protocol.

A `Robot` owns three things on any python-can bus:

- a **keep-alive stream**: a thread that sends the current twist setpoint as TWIST_CMD at a
  fixed rate (default 50 Hz, a period well inside the firmware's command timeout of 100 ms),
  with the alive counter (`seq`) that the protocol asks for incremented on every frame: the
  robot refuses a twist that repeats the last accepted `seq`, so a stuck sender (this process
  frozen, an adapter repeating its last frame) lets its watchdog stop it;
- a **receiver**: a thread that reads the bus and decodes ODOM_POSITION, ODOM_VELOCITY,
  ODOM_SLIP, STATUS, STATUS_COUNTERS and HEARTBEAT into the latest `Odometry`, `Slip`,
  `Status`, `Counters` and `Heartbeat`, and watches the heartbeat (`_Liveness`: a silence is one this process has read
  on the bus, so a slow process is not mistaken for a silent robot);
- **the way out**: leaving the `with` block, an exception through it, `close()` and the
  interpreter's exit all stop the stream, send a zero twist and MODE_CMD disable.

Commands that change the robot's mode (`enable`, `disable`, `reset`, `estop`) are sent at
once from the caller's thread; sends are serialised by a lock, so an e-stop waits for at most
one twist frame already being written, never for a queue. Before the robot's first HEARTBEAT
only ESTOP and DISABLE go out (docs/protocol.md, "The RPDO2 window").

Problems the robot reports are raised from the next call that depends on the robot
(`drive`, `enable`, `wait_state`, `check`): `NotResponding` when no HEARTBEAT arrived for three
periods, `ProtocolMismatch` when the robot speaks another protocol version (the stream then
sends only zero twists), `RobotFault` when STATUS or HEARTBEAT says FAULT, naming the fault.
"""

from __future__ import annotations

import atexit
import collections
import dataclasses
import math
import queue
import threading
import time
import weakref
from collections.abc import Callable, Iterator, Mapping
from typing import Any, cast

import can

from . import protocol

#: The firmware's default command timeout, s (config `command_timeout_ms = 100`).
DEFAULT_COMMAND_TIMEOUT_S = 0.1

#: The firmware's default STATUS and HEARTBEAT period, s (config `status_hz = 10`).
DEFAULT_HEARTBEAT_PERIOD_S = 0.1

#: Heartbeat periods without a HEARTBEAT after which the robot is not responding.
MISSED_HEARTBEATS = 3

#: How long a new `Robot` waits for the first HEARTBEAT before it says the robot is not
#: responding, s (then the three periods count).
FIRST_HEARTBEAT_S = 1.0


class RobotError(Exception):
    """Something the robot reported, or its silence."""


class NotResponding(RobotError):
    """No HEARTBEAT from the robot for three heartbeat periods."""


class ProtocolMismatch(RobotError):
    """The robot speaks another protocol version than this package."""


class RobotFault(RobotError):
    """The robot is in FAULT; `fault` names why (MOTOR_STALE, ...)."""

    def __init__(self, fault: str, message: str) -> None:
        super().__init__(message)
        self.fault = fault


@dataclasses.dataclass(frozen=True)
class Odometry:
    """The robot's odometry: pose in its odometry frame and body-frame velocity (SI units, x
    forward, y left, yaw counter-clockwise), and when this process received it."""

    x: float
    y: float
    heading: float
    vx: float
    vy: float
    wz: float
    received: float  # time.monotonic() when this process decoded the ODOM_VELOCITY frame
    #: When the frame arrived: python-can's `Message.timestamp` (on SocketCAN the kernel's
    #: receive time, seconds since the epoch: the clock candump prints), NaN if not known.
    stamp: float = math.nan

    def age(self) -> float:
        """Seconds since the frame arrived: from `stamp` where it is this computer's wall
        clock (SocketCAN), so that a process that decoded it late does not make it look
        younger; else since it was decoded."""
        return _age(self.stamp, self.received)


@dataclasses.dataclass(frozen=True)
class Slip:
    """The robot's last ODOM_SLIP (protocol version 7), which only a robot configured with
    tracking pods sends, with every odometry sample: where the odometry comes from and the slip
    estimate.

    `source`, by the DBC's name: "PODS2_GYRO" (two pods' translation, the gyro's rotation),
    "PODS3" (three pods: translation and rotation) or "WHEELS_PODS_SILENT" (configured for pods
    that sent no valid POD_COUNTS within their timeout: wheel odometry, a warning; the robot
    keeps driving). "WHEELS" is never sent: a robot without pods sends no ODOM_SLIP
    (`Robot.slip` is None, `Robot.odometry_source` "WHEELS").

    `vx`, `vy` (m/s), `wz` (rad/s): the wheels' body velocity less the pods' (body frame),
    low-pass filtered (time constant 0.1 s), to the frame's resolution (0.001); large while the
    body slides and the wheels turn; 0 while the pods are silent."""

    vx: float
    vy: float
    wz: float
    source: str
    received: float  # time.monotonic() when this process decoded the ODOM_SLIP frame
    stamp: float = math.nan  # the frame's receive time (see `Odometry.stamp`)

    def age(self) -> float:
        """Seconds since the frame arrived (as `Odometry.age`)."""
        return _age(self.stamp, self.received)


@dataclasses.dataclass(frozen=True)
class Status:
    """The robot's last STATUS: state and fault by name (the DBC's value tables), counters,
    which motors are online (wheel order FL, FR, RL, RR), and where the odometry's heading
    comes from: "WHEELS" (no gyro configured), "GYRO", or "WHEELS_GYRO_SILENT" (configured for
    a gyro that sent no valid IMU_YAW_RATE within its timeout: a warning, the robot keeps
    driving on wheel heading)."""

    state: str
    fault: str
    rx_errors: int
    unknown_ids: int
    motors_online: tuple[bool, bool, bool, bool]
    heading_source: str
    received: float  # time.monotonic()
    stamp: float = math.nan  # the frame's receive time (see `Odometry.stamp`)


@dataclasses.dataclass(frozen=True)
class Counters:
    """The robot's last STATUS_COUNTERS (protocol version 3 and later): twists it refused as repeats of
    the last accepted `seq` (a sender stuck on one frame), and frames of its own protocols it
    rejected by kind. Saturating counts since the robot started."""

    repeated_seq: int
    wrong_dlc: int
    out_of_range: int
    non_finite: int
    received: float  # time.monotonic()
    stamp: float = math.nan  # the frame's receive time (see `Odometry.stamp`)


@dataclasses.dataclass(frozen=True)
class WheelTestResult:
    """The end of a wheel test (WHEEL_TEST_RESULT, protocol version 4): the wheel (0-3, FL, FR,
    RL, RR), how it ended ("DONE", "STOPPED", "FAULT", "REFUSED"), how far that wheel's own
    encoder says it turned (rad, robot-forward positive as configured: no encoder can tell
    which wheel really turned, or which way) and the largest current commanded (A, signed;
    0 for velocity-mode drives)."""

    wheel: int
    outcome: str
    angle: float
    peak_current: float
    received: float  # time.monotonic()
    stamp: float = math.nan  # the frame's receive time (see `Odometry.stamp`)


@dataclasses.dataclass(frozen=True)
class Heartbeat:
    """The robot's last HEARTBEAT."""

    uptime_ms: int
    state: str
    protocol_version: int
    config_id: int  # the id of the robot's drive configuration (protocol version 5 and later)
    received: float  # time.monotonic()
    stamp: float = math.nan  # the frame's receive time (see `Odometry.stamp`)


#: A receive stamp further than this from `time.time()` is on some other clock (an adapter's
#: own), not the wall clock: `_age` then counts from when the frame was decoded.
_STAMP_CLOCK_TOLERANCE_S = 60.0


def _age(stamp: float, received: float) -> float:
    """Seconds since a frame arrived, from its receive `stamp` (wall clock) if usable, else
    from `received` (time.monotonic() when it was decoded)."""
    decoded_age = time.monotonic() - received
    if math.isfinite(stamp):
        age = time.time() - stamp
        if -_STAMP_CLOCK_TOLERANCE_S < age < _STAMP_CLOCK_TOLERANCE_S:
            return max(age, decoded_age)
    return decoded_age


class _Liveness:
    """How long the robot has been silent, from what the receiving thread has read.

    Only two things prove a silence: frames read after the last HEARTBEAT (their receive
    stamps, on the bus's own clock, say how much later they arrived), and the bus found empty
    (nothing left to read at that moment, so every HEARTBEAT that arrived before it has been
    read). A process that is merely slow, its receiving thread behind with HEARTBEATs waiting
    in the socket, has neither, and its robot is not called silent; a silent robot is found
    within the limit plus one poll of an empty bus. Times: `mono` is time.monotonic() when a
    frame was read (or the bus found empty), `stamp` the frame's receive stamp (NaN if none).
    """

    def __init__(self, start: float) -> None:
        self.start = start
        self.heartbeat_stamp = math.nan
        self.heartbeat_mono: float | None = None
        self.first_stamp = math.nan  # of the first frame read (for the first heartbeat)
        self.latest_stamp = math.nan  # of the latest frame read
        self.empty_mono = -math.inf  # when the bus was last found empty

    def frame(self, stamp: float) -> None:
        if math.isnan(self.first_stamp):
            self.first_stamp = stamp
        if not stamp <= self.latest_stamp:  # NaN-safe max
            self.latest_stamp = stamp

    def heartbeat(self, stamp: float, mono: float) -> None:
        self.heartbeat_stamp, self.heartbeat_mono = stamp, mono

    def empty(self, mono: float) -> None:
        self.empty_mono = mono

    def silence(self) -> float:
        """The longest silence proven so far: since the last HEARTBEAT (or, before one, since
        listening began), s; 0 where nothing proves one."""
        if self.heartbeat_mono is None:
            by_stamps = self.latest_stamp - self.first_stamp
            by_empty = self.empty_mono - self.start
        else:
            by_stamps = self.latest_stamp - self.heartbeat_stamp
            by_empty = self.empty_mono - self.heartbeat_mono
        return max(0.0, by_empty, by_stamps if math.isfinite(by_stamps) else 0.0)


def _check_speed(name: str, value: float, unit: str) -> float:
    low, high = protocol.signal_range("TWIST_CMD", name)
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} = {value} {unit}: not a finite number")
    if not low <= value <= high:
        raise ValueError(f"{name} = {value} {unit} is outside the protocol's range {low}..{high} {unit}")
    return value


class Robot:
    """A robot on `bus`. See the module documentation.

    `rate_hz`: keep-alive rate; its period must be at most half `command_timeout_s` (the
    firmware's command timeout), so that one lost frame does not stop the robot.
    `heartbeat_period_s`: the robot's HEARTBEAT period (its `status_hz`).
    `missed_heartbeats`: heartbeat periods without one after which the robot counts as not
    responding (`NotResponding`); more tolerates a computer that stalls for longer.
    `owns_bus`: shut `bus` down on `close()` (as `Robot.open` does).

    What the robot reports, the latest of each (None before the first): `odometry`, `status`,
    `counters`, `heartbeat`, and, from a robot configured with tracking pods (protocol version
    7), `slip`; `odometry_source` names where the odometry comes from ("WHEELS" from a robot
    without pods, else the latest `slip.source`), `status.heading_source` where its heading
    comes from.
    """

    def __init__(
        self,
        bus: can.BusABC,
        *,
        rate_hz: float = 50.0,
        command_timeout_s: float = DEFAULT_COMMAND_TIMEOUT_S,
        heartbeat_period_s: float = DEFAULT_HEARTBEAT_PERIOD_S,
        missed_heartbeats: int = MISSED_HEARTBEATS,
        owns_bus: bool = False,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz = {rate_hz}: must be a positive number")
        if 1.0 / rate_hz > command_timeout_s / 2:
            raise ValueError(
                f"rate_hz = {rate_hz}: a period of {1000 / rate_hz:.1f} ms is more than half the "
                f"command timeout ({command_timeout_s * 1000:.0f} ms); use at least "
                f"{2 / command_timeout_s:.0f} Hz"
            )
        if not (math.isfinite(heartbeat_period_s) and heartbeat_period_s > 0):
            raise ValueError(f"heartbeat_period_s = {heartbeat_period_s}: must be a positive number")
        if isinstance(missed_heartbeats, bool) or not isinstance(missed_heartbeats, int) or missed_heartbeats < 1:
            raise ValueError(f"missed_heartbeats = {missed_heartbeats!r}: must be a whole number >= 1")
        self.missed_heartbeats = missed_heartbeats
        self.bus = bus
        self.period_s = 1.0 / rate_hz
        self.heartbeat_period_s = heartbeat_period_s
        self._owns_bus = owns_bus
        self._db = protocol.database()
        self._msg = {name: self._db.get_message_by_name(name) for name in (
            "ESTOP", "TWIST_CMD", "MODE_CMD", "STATUS_REQ",
            "ODOM_POSITION", "ODOM_VELOCITY", "STATUS", "STATUS_COUNTERS", "HEARTBEAT",
            "WHEEL_TEST", "WHEEL_TEST_RESULT", "ODOM_SLIP",
        )}
        self._by_id = {m.frame_id: m for m in self._msg.values()}
        self._version = protocol.protocol_version()
        self._states = protocol.choices("STATUS", "state")
        self._faults = protocol.choices("STATUS", "fault")
        self._heading_sources = protocol.choices("STATUS", "heading_source")
        self._outcomes = protocol.choices("WHEEL_TEST_RESULT", "outcome")
        self._odometry_sources = protocol.choices("ODOM_SLIP", "source")

        self._send_lock = threading.Lock()
        self._lock = threading.Condition()
        self._setpoint = (0.0, 0.0, 0.0)
        self._seq = 0
        self._twists_sent = 0
        self._position: tuple[float, float] | None = None
        self._odometry: Odometry | None = None
        self._status: Status | None = None
        self._slip: Slip | None = None
        # When the latest reset() was sent (time.time()): a STATUS stamped before it is older
        # than the reset, however late the receiving thread reads it.
        self._reset_sent = -math.inf
        # The recent STATUS frames, numbered: `wait_state` looks at every one since it began,
        # not only the latest (ENABLED then, 20 ms later, DISABLED by the watchdog: it was
        # reached).
        self._statuses_seen = 0
        self._recent_statuses: collections.deque[tuple[int, Status]] = collections.deque(maxlen=64)
        self._counters: Counters | None = None
        self._heartbeat: Heartbeat | None = None
        self._wheel_test: WheelTestResult | None = None
        self._mismatch: ProtocolMismatch | None = None
        self._started = time.monotonic()
        self._liveness = _Liveness(self._started)
        self._receive_error: BaseException | None = None
        self._callbacks: list[Callable[[Odometry], None]] = []
        self._queues: list[queue.Queue[Odometry]] = []

        self._closed = False
        self._stop_stream = threading.Event()
        self._stream: threading.Thread | None = None
        self._stop_receiving = threading.Event()
        # An empty bus is noticed after this long without a frame: a quarter heartbeat period.
        self._poll_s = min(0.05, heartbeat_period_s / 4)
        self._receiver = threading.Thread(target=self._receive_loop, name="mecanum-drive receiver", daemon=True)
        self._receiver.start()
        # At interpreter exit: stop the robot even if nobody called close().
        ref = weakref.ref(self)

        def at_exit() -> None:
            robot = ref()
            if robot is not None:
                robot.close()

        self._atexit = at_exit
        atexit.register(at_exit)

    @classmethod
    def open(cls, channel: str = "can0", interface: str = "socketcan", **kwargs: Any) -> Robot:
        """A robot on a new python-can bus (`interface`, `channel`; other keyword arguments go
        to `Robot` if it takes them, else to `can.Bus`, e.g. `bitrate` for slcan or pcan).
        The bus is shut down on `close()`."""
        robot_keys = {"rate_hz", "command_timeout_s", "heartbeat_period_s", "missed_heartbeats"}
        robot_args = {k: v for k, v in kwargs.items() if k in robot_keys}
        bus_args = {k: v for k, v in kwargs.items() if k not in robot_keys}
        bus_args.setdefault("can_filters", cls.receive_filters())
        bus = can.Bus(channel=channel, interface=interface, **bus_args)
        try:
            return cls(bus, owns_bus=True, **robot_args)
        except BaseException:
            bus.shutdown()
            raise

    @staticmethod
    def receive_filters() -> list[can.typechecking.CanFilter]:
        """python-can filters that pass only the robot's frames (ODOM_*, STATUS, HEARTBEAT).
        `Robot.open` sets them; on a bus of your own, pass them as `can_filters` where the
        interface filters in hardware or in the kernel (SocketCAN), so that the drives'
        kilohertz traffic never reaches Python."""
        return [
            {"can_id": m.frame_id, "can_mask": 0x7FF, "extended": False}
            for m in protocol.database().messages
            if m.senders == ["ROBOT"]
        ]

    # --- context manager and closing --------------------------------------------------

    def __enter__(self) -> Robot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stops the stream, sends a zero twist and MODE_CMD disable, stops receiving (and
        shuts the bus down if this robot owns it). Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self._atexit)
        self._stop_stream.set()
        if self._stream is not None and self._stream is not threading.current_thread():
            self._stream.join(timeout=1.0)
        try:
            self._send_twist((0.0, 0.0, 0.0))
            self._send("MODE_CMD", request=self._mode("DISABLE"))
        except can.CanError:
            pass  # the bus is gone: nothing more can be said to the robot
        finally:
            self._stop_receiving.set()
            if self._receiver is not threading.current_thread():
                self._receiver.join(timeout=1.0)
            if self._owns_bus:
                self.bus.shutdown()

    # --- commands ------------------------------------------------------------------------

    def _mode(self, name: str) -> int:
        table = {v: k for k, v in protocol.choices("MODE_CMD", "request").items()}
        return table[name]

    def _send(self, name: str, **signals: float) -> None:
        message = self._msg[name]
        data = message.encode(signals, strict=True) if message.signals else b""
        frame = can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False)
        with self._send_lock:
            self.bus.send(frame, timeout=0.1)

    def _send_twist(self, twist: tuple[float, float, float]) -> None:
        with self._send_lock:
            seq = self._seq
            self._seq = (self._seq + 1) % 256
            data = self._msg["TWIST_CMD"].encode(
                {"vx": twist[0], "vy": twist[1], "wz": twist[2], "seq": seq, "reserved": 0}, strict=True
            )
            self.bus.send(can.Message(arbitration_id=self._msg["TWIST_CMD"].frame_id, data=data,
                                      is_extended_id=False), timeout=0.1)
            self._twists_sent += 1

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("this Robot is closed")

    def enable(self) -> None:
        """MODE_CMD enable. The keep-alive stream starts first (with a zero setpoint unless
        `drive` set one), since the robot's watchdog stops it again within its command timeout
        when no twist arrives; the robot then follows the stream's twists."""
        self._check_open()
        self._wait_first_heartbeat()
        self.check()
        self._ensure_stream()
        self._send("MODE_CMD", request=self._mode("ENABLE"))

    def disable(self) -> None:
        """MODE_CMD disable: motors off."""
        self._check_open()
        self._send("MODE_CMD", request=self._mode("DISABLE"))

    def reset(self) -> None:
        """MODE_CMD reset: clears a fault or the e-stop latch; the robot stays disabled."""
        self._check_open()
        self._wait_first_heartbeat()
        with self._lock:
            self._status = None  # a fault reported before the reset no longer counts
            self._reset_sent = time.time()
        self._send("MODE_CMD", request=self._mode("RESET"))

    def estop(self) -> None:
        """ESTOP, sent at once (after at most the one twist frame being written): the robot
        stops and latches until `reset()`. The stream's setpoint becomes zero."""
        with self._lock:
            self._setpoint = (0.0, 0.0, 0.0)
        self._send("ESTOP", magic=protocol.ESTOP_MAGIC)

    def wheel_test(self, wheel: int, speed: float, duration_s: float, timeout: float = 1.0) -> WheelTestResult:
        """The bring-up check's WHEEL_TEST: with the robot on blocks, drives wheel `wheel` (0-3:
        FL, FR, RL, RR) at `speed` rad/s (robot-forward positive, |speed| <= 10) for
        `duration_s` (0.001-3 s) and returns the robot's WHEEL_TEST_RESULT. Only a DISABLED
        robot runs it (a quarter of its current limit, the other wheels without torque); in
        any other state the result is "REFUSED". It ends early on `disable()` or `estop()`.

        Raises ValueError naming the argument out of range, TimeoutError when no result
        comes within `duration_s + timeout`.
        """
        self._check_open()
        if wheel not in range(4):
            raise ValueError(f"wheel = {wheel!r}: expected 0-3 (FL, FR, RL, RR)")
        if not (math.isfinite(speed) and 0 < abs(speed) <= 10):
            raise ValueError(f"speed = {speed!r}: expected a wheel speed in [-10, 10] rad/s, not 0")
        if not (math.isfinite(duration_s) and 0.001 <= duration_s <= 3.0):
            raise ValueError(f"duration_s = {duration_s!r}: expected 0.001-3 s")
        self._wait_first_heartbeat()
        self.check()
        with self._lock:
            self._wheel_test = None
        self._send("WHEEL_TEST", wheel=wheel, speed=speed, duration_ms=round(duration_s * 1000), reserved=0)
        deadline = time.monotonic() + duration_s + timeout
        with self._lock:
            while self._wheel_test is None or self._wheel_test.wheel != wheel:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"no WHEEL_TEST_RESULT for wheel {wheel} within {duration_s + timeout:.2f} s: "
                        "does the robot speak protocol version 4?"
                    )
                self._lock.wait(min(left, 0.05))
            return self._wheel_test

    def request_status(self) -> None:
        """STATUS_REQ: the robot answers with a STATUS at once."""
        self._check_open()
        self._wait_first_heartbeat()
        self._send("STATUS_REQ")

    def drive(self, vx: float, vy: float, wz: float) -> None:
        """Sets the twist setpoint (m/s, m/s, rad/s, body frame) that the keep-alive stream
        sends from now on, starting the stream if it is not running.

        Raises ValueError naming the field for a speed outside the protocol's range or not a
        number, and the robot's own error (`check`) if there is one.
        """
        self._check_open()
        twist = (_check_speed("vx", vx, "m/s"), _check_speed("vy", vy, "m/s"), _check_speed("wz", wz, "rad/s"))
        self._wait_first_heartbeat()
        self.check()
        with self._lock:
            self._setpoint = twist
        self._ensure_stream()

    def stop(self) -> None:
        """Zero twist: the stream goes on (the robot stays enabled and holds still)."""
        with self._lock:
            self._setpoint = (0.0, 0.0, 0.0)
        self._ensure_stream()

    @property
    def setpoint(self) -> tuple[float, float, float]:
        """The twist the stream sends."""
        with self._lock:
            return self._setpoint

    @property
    def twists_sent(self) -> int:
        """TWIST_CMD frames sent so far."""
        return self._twists_sent

    def _wait_first_heartbeat(self) -> None:
        """Before the robot's first HEARTBEAT, waits for it (until FIRST_HEARTBEAT_S after this
        robot's creation; `check` then says the robot is not responding). The robot sends
        nothing in its protocol's block until its CiA 402 drives no longer take 0x300 + node as
        their RPDO2, and its first HEARTBEAT says so (docs/protocol.md, "The RPDO2 window"):
        what this package sends, but ESTOP and DISABLE, waits for it."""
        deadline = self._started + FIRST_HEARTBEAT_S
        with self._lock:
            while self._heartbeat is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                self._lock.wait(min(left, 0.05))

    def _ensure_stream(self) -> None:
        if self._stream is None or not self._stream.is_alive():
            self._stop_stream.clear()
            self._stream = threading.Thread(target=self._stream_loop, name="mecanum-drive keep-alive", daemon=True)
            self._stream.start()

    def _stream_loop(self) -> None:
        next_t = time.monotonic()
        while not self._stop_stream.is_set():
            with self._lock:
                twist = self._setpoint if self._mismatch is None else (0.0, 0.0, 0.0)
                heard = self._heartbeat is not None  # none before the robot's first HEARTBEAT
            try:
                if heard:
                    self._send_twist(twist)
            except can.CanError:
                pass  # a full queue or a bus error: the next period tries again
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t = time.monotonic()  # late: restart the schedule rather than burst
                delay = 0
            self._stop_stream.wait(delay)

    # --- what the robot says ---------------------------------------------------------------

    def _receive_loop(self) -> None:
        """The receiving thread: every frame to `_on_message`; an empty bus noted (`_Liveness`)."""
        try:
            while not self._stop_receiving.is_set():
                msg = self.bus.recv(timeout=self._poll_s)
                if msg is None:
                    with self._lock:
                        self._liveness.empty(time.monotonic())
                else:
                    self._on_message(msg)
        except Exception as err:  # noqa: BLE001 - raised from check() as NotResponding
            # A bus that failed, or an `on_odometry` callback that raised: nothing is read any
            # more, so no silence could be proven; `check` says so instead.
            if not self._stop_receiving.is_set():
                with self._lock:
                    self._receive_error = err
                    self._lock.notify_all()

    def _before_reset(self, stamp: float) -> bool:
        """Whether a frame with receive `stamp` arrived before the latest reset() was sent.
        Only a wall-clock stamp (SocketCAN's kernel time) can say so; another clock says no.
        A STATUS the robot sends after the reset arrived but before its next step took it is
        not caught: at most one control period, then STATUS reports the reset's outcome."""
        return (math.isfinite(stamp) and abs(time.time() - stamp) < _STAMP_CLOCK_TOLERANCE_S
                and stamp < self._reset_sent)

    def _on_message(self, msg: can.Message) -> None:
        stamp = float(msg.timestamp) if msg.timestamp else math.nan
        with self._lock:
            self._liveness.frame(stamp)
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return
        message = self._by_id.get(msg.arbitration_id)
        if message is None or message.senders != ["ROBOT"]:
            return
        try:
            # Without choices, every value is a number.
            values = cast(Mapping[str, float], message.decode(bytes(msg.data), decode_choices=False, scaling=True))
        except Exception:  # noqa: BLE001 - a malformed frame is not this package's to raise
            return
        now = time.monotonic()
        odometry = None
        with self._lock:
            if message.name == "ODOM_POSITION":
                self._position = (float(values["x"]), float(values["y"]))
            elif message.name == "ODOM_VELOCITY":
                x, y = self._position if self._position is not None else (math.nan, math.nan)
                odometry = Odometry(x, y, float(values["heading"]), float(values["vx"]), float(values["vy"]),
                                    float(values["wz"]), now, stamp)
                self._odometry = odometry
            elif message.name == "ODOM_SLIP":
                self._slip = Slip(
                    vx=float(values["vx"]),
                    vy=float(values["vy"]),
                    wz=float(values["wz"]),
                    source=self._odometry_sources.get(int(values["source"]), str(values["source"])),
                    received=now,
                    stamp=stamp,
                )
            elif message.name == "STATUS" and self._before_reset(stamp):
                pass  # the robot sent it before the reset existed; its fault no longer counts
            elif message.name == "STATUS":
                mask = int(values["motors_online"])
                self._status = Status(
                    state=self._states.get(int(values["state"]), str(values["state"])),
                    fault=self._faults.get(int(values["fault"]), str(values["fault"])),
                    rx_errors=int(values["rx_errors"]),
                    unknown_ids=int(values["unknown_ids"]),
                    motors_online=tuple(bool(mask >> i & 1) for i in range(4)),  # type: ignore[arg-type]
                    heading_source=self._heading_sources.get(int(values["heading_source"]),
                                                             str(values["heading_source"])),
                    received=now,
                    stamp=stamp,
                )
                self._statuses_seen += 1
                self._recent_statuses.append((self._statuses_seen, self._status))
            elif message.name == "STATUS_COUNTERS":
                self._counters = Counters(
                    repeated_seq=int(values["repeated_seq"]),
                    wrong_dlc=int(values["wrong_dlc"]),
                    out_of_range=int(values["out_of_range"]),
                    non_finite=int(values["non_finite"]),
                    received=now,
                    stamp=stamp,
                )
            elif message.name == "WHEEL_TEST_RESULT":
                self._wheel_test = WheelTestResult(
                    wheel=int(values["wheel"]),
                    outcome=self._outcomes.get(int(values["outcome"]), str(values["outcome"])),
                    angle=float(values["angle"]),
                    peak_current=float(values["peak_current"]),
                    received=now,
                    stamp=stamp,
                )
            elif message.name == "HEARTBEAT":
                version = int(values["protocol_version"])
                self._heartbeat = Heartbeat(
                    uptime_ms=int(values["uptime_ms"]),
                    state=self._states.get(int(values["state"]), str(values["state"])),
                    protocol_version=version,
                    config_id=int(values["config_id"]),
                    received=now,
                    stamp=stamp,
                )
                self._liveness.heartbeat(stamp, now)
                if version != self._version and self._mismatch is None:
                    self._mismatch = ProtocolMismatch(
                        f"the robot speaks protocol version {version}; this package speaks version "
                        f"{self._version} (its DBC, {protocol.DBC_NAME}): update the package or the "
                        "robot's firmware so that they match. Until then only zero twists are sent."
                    )
            self._lock.notify_all()
            callbacks, queues = list(self._callbacks), list(self._queues)
        if odometry is not None:
            for q in queues:
                q.put(odometry)
            for callback in callbacks:
                callback(odometry)

    @property
    def odometry(self) -> Odometry | None:
        """The latest odometry, or None before the first."""
        with self._lock:
            return self._odometry

    @property
    def slip(self) -> Slip | None:
        """The latest ODOM_SLIP (the odometry source and the slip estimate), or None before the
        first: always None from a robot configured without tracking pods, which sends none."""
        with self._lock:
            return self._slip

    @property
    def odometry_source(self) -> str:
        """Where the robot's odometry comes from: the latest ODOM_SLIP's `source` ("PODS2_GYRO",
        "PODS3", "WHEELS_PODS_SILENT"), or "WHEELS" while none has arrived (a robot without
        tracking pods). Where its heading comes from is `Status.heading_source`."""
        with self._lock:
            return "WHEELS" if self._slip is None else self._slip.source

    @property
    def status(self) -> Status | None:
        """The latest STATUS, or None before the first."""
        with self._lock:
            return self._status

    @property
    def counters(self) -> Counters | None:
        """The latest STATUS_COUNTERS, or None before the first."""
        with self._lock:
            return self._counters

    @property
    def heartbeat(self) -> Heartbeat | None:
        """The latest HEARTBEAT, or None before the first."""
        with self._lock:
            return self._heartbeat

    @property
    def responding(self) -> bool:
        """False when no HEARTBEAT came for `missed_heartbeats` heartbeat periods, or none at all
        within FIRST_HEARTBEAT_S of this robot's creation, as far as this process has read the
        bus (a process too busy to read is not taken for a silent robot; see `_Liveness`)."""
        return self._silence() is None

    def _silence(self) -> tuple[float, float, bool] | None:
        """None while the robot responds, else (the silence, its limit, whether any HEARTBEAT
        came), in s."""
        with self._lock:
            silence = self._liveness.silence()
            heard = self._heartbeat is not None
        limit = self.missed_heartbeats * self.heartbeat_period_s
        if not heard:
            limit = max(FIRST_HEARTBEAT_S, limit)
        return None if silence <= limit else (silence, limit, heard)

    def _check_link(self) -> None:
        """Raises ProtocolMismatch or NotResponding if the robot cannot be talked to."""
        with self._lock:
            mismatch, receive_error = self._mismatch, self._receive_error
        if mismatch is not None:
            raise mismatch
        if receive_error is not None:
            raise NotResponding(f"this program stopped reading the bus ({self.bus.channel_info}): {receive_error!r}")
        silent = self._silence()
        if silent is None:
            return
        silence, _, heard = silent
        if not heard:
            raise NotResponding(
                f"no HEARTBEAT from the robot in the {silence:.2f} s since this program started "
                f"listening: is it powered, on this bus ({self.bus.channel_info}), at the same bitrate?"
            )
        raise NotResponding(
            f"no HEARTBEAT from the robot for {silence:.2f} s (more than {self.missed_heartbeats} periods of "
            f"{self.heartbeat_period_s:.2f} s): is it powered, on this bus ({self.bus.channel_info}), "
            "at the same bitrate?"
        )

    def check(self) -> None:
        """Raises what the robot reported: ProtocolMismatch, NotResponding, or RobotFault with
        the fault's name; returns if all is well."""
        self._check_link()
        with self._lock:
            status = self._status
        if status is not None and status.state == "FAULT":
            raise RobotFault(status.fault, f"the robot is in FAULT: {status.fault} (reset() clears it)")

    def wait_state(self, state: str, timeout: float = 1.0) -> Status:
        """Waits until STATUS reports `state` (DISABLED, ENABLED, FAULT, ESTOP), the latest one
        or any that arrives meanwhile (a state reached and left at once counts), and returns
        that STATUS. Raises ValueError for another name, TimeoutError after `timeout` s, and what
        `check` raises meanwhile (a FAULT only when waiting for another state)."""
        if state not in self._states.values():
            raise ValueError(f"state = {state!r}: not one of {sorted(self._states.values())}")
        deadline = time.monotonic() + timeout
        with self._lock:
            since = self._statuses_seen
        while True:
            with self._lock:
                status, seen = self._status, self._statuses_seen
                reached = [st for n, st in self._recent_statuses if n > since and st.state == state]
            if reached:
                return reached[0]
            if status is not None and status.state == state:
                return status
            if state == "FAULT":
                self._check_link()
            else:
                self.check()
            left = deadline - time.monotonic()
            if left <= 0:
                last = status.state if status is not None else "no STATUS yet"
                raise TimeoutError(f"the robot did not reach {state} within {timeout} s (last: {last})")
            with self._lock:
                if self._statuses_seen == seen:
                    self._lock.wait(min(left, 0.05))

    def on_odometry(self, callback: Callable[[Odometry], None]) -> None:
        """Calls `callback(odometry)` on every new odometry, from the receiving thread (keep it
        short)."""
        with self._lock:
            self._callbacks.append(callback)

    def odometry_updates(self, timeout: float | None = None) -> Iterator[Odometry]:
        """Every new odometry from now on, in order; ends when none arrives for `timeout` s
        (None: waits for ever)."""
        q: queue.Queue[Odometry] = queue.Queue()
        with self._lock:
            self._queues.append(q)
        try:
            while True:
                try:
                    yield q.get(timeout=timeout)
                except queue.Empty:
                    return
        finally:
            with self._lock:
                self._queues.remove(q)
