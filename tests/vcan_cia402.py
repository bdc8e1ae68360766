"""The firmware as the CANopen master of two CiA 402 drives on a real vcan0, for the tests
marked `vcan` (tests/test_vcan_cia402.py, tests/test_vcan_cia402_outages.py).

`Cia402Robot` starts `mecanum-runner --iface vcan0 --config <a cia402 configuration>` (the
control core, the master) and two simulated drives, `Cia402Peer`s of tests/cia402_peer.py
(nodes 1 and 2, the dual-axis EDS: each drives two wheels), with candump recording every
frame. It is `vcan_robot.Robot` with the peers in place of `hostsim plant`: the same start
(candump first, then the drives, then the runner; ready when STATUS reports every motor
online and no fault), the same host-side helpers and the same end (the runner stopped by SIGINT, candump
caught up, `frames` parsed with the kernel's receive timestamps, the runner's `--stats-json`
loaded). The peers go off the bus after the runner and before candump stops.

The drives run in this Python process, on its threads (python-can notifiers and the peer's
timing thread). In the micro-VM of the vcan lane they share its one CPU with the runner (a
real-time process there), candump and the test: a drive's answer to SYNC is late by the
interpreter's scheduling, which a drive's firmware would not be. The test configuration
(tests/cia402_vcan.toml) says what that costs.

Times: the tests measure between frames of candump's record (kernel timestamps, one clock)
or between records of the runner's own log (`runner_log=True`: `--log`, the core's step
times, read by `read_runner_log`); never with this process's clock after the fact.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import os
import pathlib
import stat
import struct
import subprocess
import time
import tomllib
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import can
from cia402_peer import DUAL_EDS, Cia402Peer
from vcan_robot import READY_TIMEOUT_S, SLOW_CPU, STATE_DISABLED, STATE_FAULT, STATUS, Frame, Robot
from vcan_robot import ANSWER_S, MODE_CMD, MODE_ENABLE, ROOT

if TYPE_CHECKING:
    import mecanum_drive

#: The nodes of config/cia402.toml: node 1 the front wheels (axis 1 FL, axis 2 FR), node 2
#: the rear (axis 1 RL, axis 2 RR).
NODES = (1, 2)
WHEEL_AXES = {0: (1, 0), 1: (1, 1), 2: (2, 0), 3: (2, 1)}  # wheel -> (node, axis index)
MASTER_NODE = 127

# CANopen ids (docs/protocol.md, "CANopen CiA 402"): function code + node.
NMT, SYNC = 0x000, 0x080
EMCY, TPDO1, TPDO2, RPDO1, RPDO3 = 0x080, 0x180, 0x280, 0x200, 0x400
SDO_RESPONSE, SDO_REQUEST, HEARTBEAT_ID = 0x580, 0x600, 0x700
NMT_START, NMT_RESET_COMMUNICATION = 0x01, 0x82
BOOT_UP = 0x00
EMCY_HEARTBEAT = 0x8130

# Controlwords the master sends.
SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, QUICK_STOP = 0x06, 0x07, 0x0F, 0x02
# Statuswords under mask 0x6F (docs/protocol.md: a master masks bits 4 and 9 and the others).
READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED = 0x21, 0x23, 0x27
STATE_MASK = 0x6F


#: The drives of config/cia402.toml take 0x60FF in rpm and report 0x606C in 0.1 rpm (a
#: ZLAC8015D's units: `target_rpm_per_unit = 1.0`, `actual_rpm_per_unit = 0.1`).
ACTUAL_PER_TARGET = 10


def before(series: list[tuple[float, int]], t: float, n: int = 1) -> list[int]:
    """The values of the last `n` entries of a time-ordered series strictly before `t`."""
    i = bisect.bisect_left(series, (t, -(1 << 62)))
    return [v for _, v in series[max(0, i - n):i]]


@dataclasses.dataclass(frozen=True)
class LogFrame:
    """A frame in the runner's own log: the core's time of the step that took it (rx) or
    sent it (tx), s since the runner's first step."""

    t: float
    tx: bool
    id: int
    data: bytes


def read_runner_log(path: pathlib.Path) -> list[LogFrame]:
    """The /can/rx and /can/tx records of a runner's `--log` MCAP file, in log order: rx
    stamped with the step that passed the frame to the core, tx with the step that sent it
    (its publish time)."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None, f"{path}: no summary (was the runner stopped cleanly?)"
        store = get_typestore(Stores.ROS2_HUMBLE)
        for schema in summary.schemas.values():
            types = get_types_from_msg(schema.data.decode(), schema.name)
            store.register({name: fields for name, fields in types.items() if name not in store.fielddefs})
        for _, channel, message in reader.iter_messages(topics=["/can/rx", "/can/tx"]):
            frame: Any = store.deserialize_cdr(message.data, "can_msgs/msg/Frame")
            tx = channel.topic == "/can/tx"
            t_ns = message.publish_time if tx else message.log_time
            out.append(LogFrame(t_ns / 1e9, tx, int(frame.id), bytes(frame.data[: frame.dlc])))
    return out


def warm_this_process() -> None:
    """Reads every file this process maps (the interpreter, its shared libraries, the
    extension modules imported), whole, into the page cache: `vcan_robot.warm_page_cache`'s
    reason, for the peers' Python. The micro-VM reads them through 9p, and its clock runs on
    while a process waits on the host: a peer that first runs its PDO code (the first SYNC
    after NMT start) would stall on page faults while the master's cycle goes on."""
    paths = set()
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split(maxsplit=5)
            if len(fields) == 6 and fields[5].startswith("/"):
                paths.add(fields[5].strip())
    for path in sorted(paths):
        try:
            with open(path, "rb") as data:
                # Regular files only, up to their size: a shared anonymous mapping shows as
                # `/dev/zero (deleted)`, and /dev/zero never ends.
                st = os.fstat(data.fileno())
                if not stat.S_ISREG(st.st_mode):
                    continue
                left = st.st_size
                while left > 0 and (chunk := data.read(min(left, 1 << 20))):
                    left -= len(chunk)
        except OSError:
            pass  # gone (a deleted mapping's file)


def read_runner_steps(path: pathlib.Path) -> list[float]:
    """The time of every step in a runner's `--log` (its /firmware/steps records, the
    shutdown's last), s since its first step: what the core was given as `now`."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [message.log_time / 1e9 for _, _, message in make_reader(f).iter_messages(topics=["/firmware/steps"])]


def step_lateness(steps: list[float], period_s: float) -> list[float]:
    """Each step's lateness after its deadline, s, as the runner's loop schedules them
    (mecanum_linux's `Schedule`): deadlines one period apart from the first step's clock
    reading (time 0), re-anchored at a step more than a period late (an overrun). Step times
    are whole microseconds, as the log has them."""
    period_us = round(period_s * 1e6)
    anchor, k = 0, 0
    out = []
    for t in steps:
        t_us = round(t * 1e6)
        late = max(0, t_us - (anchor + k * period_us))
        if late > period_us:
            anchor, k = t_us, 0
        out.append(late / 1e6)
        k += 1
    return out


class Cia402Robot(Robot):
    """`mecanum-runner` as the CANopen master of two `Cia402Peer`s (nodes 1 and 2,
    `ACTUAL_PER_TARGET`, each socket filtered to its own frames) on
    `iface`, candump recording, a host to command them (`vcan_robot.Robot`'s helpers).
    `peers` maps node id to its peer while the session runs."""

    def __init__(
        self,
        *,
        runner: pathlib.Path,
        candump: str,
        iface: str,
        config: pathlib.Path,
        workdir: pathlib.Path,
        runner_args: Sequence[str] = (),
        runner_log: bool = False,
    ) -> None:
        # No plant: the peers are the drives (`hostsim` is never started).
        super().__init__(runner=runner, hostsim=pathlib.Path("/nonexistent/hostsim"), candump=candump,
                         iface=iface, config=config, workdir=workdir, runner_args=runner_args,
                         runner_log=runner_log)
        self.peers: dict[int, Cia402Peer] = {}
        self.peer_errors: dict[int, list[BaseException]] = {}
        #: What a session keeps of its peers before they close (traces, states).
        self.notes: dict[str, Any] = {}

    def __enter__(self) -> Cia402Robot:
        super().__enter__()
        return self

    def _start(self) -> None:
        self._status_rx = can.Bus(
            interface="socketcan", channel=self.iface, can_filters=[{"can_id": STATUS, "can_mask": 0x7FF}]
        )
        self._tx = can.Bus(interface="socketcan", channel=self.iface)
        with open(self.candump_log, "w") as log, open(self.workdir / "candump.err", "w") as err:
            self._procs["candump"] = subprocess.Popen(self._candump_cmd, stdout=log, stderr=err)
        self._wait_for_candump()
        if SLOW_CPU:
            warm_this_process()
        # The drives power up (each sends its boot-up) before the master runs: the master's
        # NMT reset communication at its first step has each boot again.
        for node in NODES:
            self.peers[node] = Cia402Peer(self.iface, node, DUAL_EDS, actual_per_target=ACTUAL_PER_TARGET,
                                          own_frames_only=True)
        status = self._start_runner("ready")
        assert status["state"] == STATE_DISABLED, f"the robot faulted while its drives came up: {status}"

    def _start_runner(self, what: str) -> dict:
        """Starts the runner; returns its first STATUS with both nodes configured and started
        and every wheel's TPDOs arriving, or FAULT."""
        self._spawn("runner", self._cmds["runner"])
        return self.wait_status(lambda s: s["motors_online"] == 0x0F or s["state"] == STATE_FAULT,
                                READY_TIMEOUT_S, what)

    def restart_runner(self) -> dict:
        """Starts the runner again after `kill("runner")`, with the same command line (its
        output and `--stats-json` written anew; the session's end expects it to exit cleanly).
        The drives are left as they are: no power cycle. Returns its first STATUS as
        `_start_runner` says (STATUS frames of the killed runner still queued are dropped)."""
        assert "runner" in self.killed, "restart_runner follows kill(\"runner\")"
        assert self._status_rx is not None
        while self._status_rx.recv(timeout=0) is not None:
            pass
        self.killed.discard("runner")
        return self._start_runner("ready after the restart")

    def _close_peers(self) -> None:
        for node, peer in list(self.peers.items()):
            peer.close()
            self.peer_errors[node] = peer.errors
        self.peers.clear()

    def _let_candump_catch_up(self) -> None:
        # The runner has stopped: the drives leave the bus (else their heartbeats would keep
        # candump's log growing), then candump writes what it has.
        self._close_peers()
        super()._let_candump_catch_up()

    def _stop_all(self) -> None:
        try:
            super()._stop_all()
        finally:
            self._close_peers()
        errors = {node: e for node, e in self.peer_errors.items() if e}
        assert not errors, f"the peers raised while handling frames: {errors}"

    # --- the CANopen side of the record ----------------------------------------------------

    def rpdos(self, node: int, t0: float = -math.inf, t1: float = math.inf) -> list[tuple[float, int, int, int]]:
        """Each cycle's RPDOs to `node`: (time of RPDO1, controlword, target axis 1, target
        axis 2), the RPDO3 paired with the first one at or after the RPDO1 (the master sends
        RPDO1 then RPDO3)."""
        rpdo3 = self.of(RPDO3 + node, t0, t1 + 0.1)
        times3 = [f.t for f in rpdo3]
        out = []
        for f in self.of(RPDO1 + node, t0, t1):
            controlword, target1 = struct.unpack("<Hi", f.data)
            i = bisect.bisect_left(times3, f.t)
            assert i < len(rpdo3), f"no RPDO3 to node {node} after its RPDO1 at {f.t}"
            (target2,) = struct.unpack("<i", rpdo3[i].data)
            out.append((f.t, controlword, target1, target2))
        return out

    def wheel_actuals(self) -> dict[int, list[tuple[float, int]]]:
        """Each wheel's 0x606C velocity actual value as its drive sent it, raw: wheel ->
        [(time, raw)] (TPDO1 carries axis 1's, TPDO2 axis 2's)."""
        out: dict[int, list[tuple[float, int]]] = {}
        for wheel, (node, axis) in WHEEL_AXES.items():
            if axis == 0:
                out[wheel] = [(f.t, struct.unpack_from("<i", f.data, 2)[0]) for f in self.of(TPDO1 + node)]
            else:
                out[wheel] = [(f.t, struct.unpack("<i", f.data)[0]) for f in self.of(TPDO2 + node)]
        return out

    def tpdos(self, node: int, t0: float = -math.inf, t1: float = math.inf) -> list[tuple[float, int, int]]:
        """TPDO1 of `node`: (time, statusword, velocity actual of axis 1)."""
        return [(f.t, *struct.unpack("<Hi", f.data)) for f in self.of(TPDO1 + node, t0, t1)]

    def tpdo2s(self, node: int, t0: float = -math.inf, t1: float = math.inf) -> list[tuple[float, int]]:
        """TPDO2 of `node`: (time, velocity actual of axis 2)."""
        return [(f.t, struct.unpack("<i", f.data)[0]) for f in self.of(TPDO2 + node, t0, t1)]

    def emcys(self, node: int, t0: float = -math.inf, t1: float = math.inf) -> list[tuple[float, int, int]]:
        """EMCY of `node`: (time, error code, error register)."""
        return [(f.t, *struct.unpack_from("<HB", f.data)) for f in self.of(EMCY + node, t0, t1)]

    def nmt(self, t0: float = -math.inf, t1: float = math.inf) -> list[tuple[float, int, int]]:
        """NMT commands: (time, command, node)."""
        return [(f.t, f.data[0], f.data[1]) for f in self.of(NMT, t0, t1)]


# --- the sessions of tests/test_vcan_cia402.py and tests/test_vcan_cia402_outages.py ----------

#: The configuration every session runs: config/cia402.toml but for timing.stale_periods
#: (its comments say why); nothing else may differ.
CONFIG = pathlib.Path(__file__).resolve().parent / "cia402_vcan.toml"
CFG = tomllib.loads(CONFIG.read_text())
_EXAMPLE = tomllib.loads((ROOT / "config" / "cia402.toml").read_text())
assert {**CFG, "timing": {**CFG["timing"], "stale_periods": None}} == {
    **_EXAMPLE, "timing": {**_EXAMPLE["timing"], "stale_periods": None}}, (
    f"{CONFIG} differs from config/cia402.toml in more than timing.stale_periods")

CONTROL_PERIOD_S = 1.0 / float(CFG["timing"]["control_hz"])
CYCLE_S = 1.0 / float(CFG["timing"]["setpoint_hz"])  # the CANopen cycle: SYNC, RPDOs, TPDOs
TARGET_RPM_PER_UNIT = float(CFG["drive"]["target_rpm_per_unit"])
GEAR = float(CFG["drive"]["gear_ratio"])
SIGN = [-1.0 if inv else 1.0 for inv in CFG["drive"]["inverted"]]
LX, LY = float(CFG["geometry"]["lx"]), float(CFG["geometry"]["ly"])
RADIUS = float(CFG["geometry"]["wheel_radius"])
RPM = 2 * math.pi / 60  # rad/s per rpm

#: From a phase's first TWIST_CMD until its targets and the drives' velocities have settled:
#: the acceleration limits (at most |dv| 0.64 m/s at 4 m/s², 1 rad/s at 12 rad/s²: 0.16 s),
#: then the peer's motor (a 50 ms lag: within a tenth of a raw unit of 0.1 rpm after 12 time
#: constants of a 300-unit step, 0.6 s); with margin.
SETTLE_S = 0.9


# --- the kinematics of the configuration (docs: kinematics::MecanumKinematics::standard) ----

def wheel_speeds(vx: float, vy: float, wz: float) -> list[float]:
    """FL, FR, RL, RR in rad/s, robot-forward positive."""
    k = LX + LY
    return [(vx - vy - k * wz) / RADIUS, (vx + vy + k * wz) / RADIUS,
            (vx + vy - k * wz) / RADIUS, (vx - vy + k * wz) / RADIUS]


def exact_targets(vx: float, vy: float, wz: float) -> list[float]:
    """Each wheel's 0x60FF target before rounding, raw units (rpm / target_rpm_per_unit)."""
    return [s * w * GEAR / RPM / TARGET_RPM_PER_UNIT for s, w in zip(SIGN, wheel_speeds(vx, vy, wz))]


# --- the host's steps and the record's -------------------------------------------------------

def reset_and_wait_disabled(api: mecanum_drive.Robot, session: Cia402Robot) -> None:
    """`api.reset()`, then the robot's STATUS DISABLED, from the package's latest STATUS.

    Not `api.wait_state("DISABLED")`: the package drops a STATUS stamped before its reset was
    sent (tests/test_package.py), but one the runner sent after the reset reached its socket
    and before its next step took it still reports FAULT; stored after the reset, it makes
    `wait_state` raise RobotFault (through `check`), though the robot is DISABLED at its next
    STATUS. Such a STATUS is kept in `session.notes["stale_after_reset"]` with its kernel
    timestamp less the wall time the reset was sent (the tests check the STATUS frames on
    candump's record)."""
    session.marks["reset"] = time.time()
    api.reset()
    sent = time.time()
    deadline = time.monotonic() + ANSWER_S
    seen = set()
    while True:
        status = api.status
        if status is not None and status.state == "DISABLED":
            return
        if status is not None and status.stamp not in seen:
            seen.add(status.stamp)
            session.notes.setdefault("stale_after_reset", []).append((status.state, status.fault, status.stamp - sent))
        assert time.monotonic() < deadline, f"not DISABLED within {ANSWER_S} s of the reset: {status}"
        time.sleep(0.005)


def first(frames: list[Any], what: str) -> Any:
    assert frames, f"no {what}"
    return frames[0]


def enable_frame(session: Cia402Robot, after: float) -> float:
    """The candump time of the first MODE_CMD enable at or after `after` (a wall mark, less a
    little: the mark is taken just before the API sends)."""
    frames = [f for f in session.of(MODE_CMD, after - 0.01) if f.data == bytes([MODE_ENABLE])]
    return float(first(frames, f"MODE_CMD enable after {after}").t)
