"""The firmware as the CANopen master of two CiA 402 drives, on a real vcan0.

`mecanum-runner --iface vcan0 --config <cia402>` is the master; two simulated drives
(tests/cia402_peer.py, nodes 1 and 2, dual-axis: node 1 the front wheels, node 2 the rear) are
its nodes; candump records the bus; the test is the host, through the Python package's API
(`mecanum_drive.Robot`, unchanged). tests/vcan_cia402.py starts and stops them. Each session
below is one run of the runner; the tests check what crossed the bus:

- the enable trace: 0x06, 0x07, 0x0F to each node, each only after its statusword showed
  the state before, at the first cycle after it did (docs/protocol.md, "CANopen CiA 402");
- motion: the targets of a twist (signs, the right side mirrored; `target_rpm_per_unit`) and
  the odometry against the drives' reported velocities;
- e-stop: quick stop (0x02) with zero targets at the next cycle;
- a drive's heartbeat lost: FAULT DRIVE_SILENT, quick stop within the consumer time and a
  cycle;
- the runner killed: each drive's heartbeat consumer trips (EMCY 0x8130) within its 0x1016
  time and the drive goes pre-operational (CiA 301's 0x1029 = 0); the runner started again
  resets, configures and starts them, and the robot drives again after the host's reset and
  enable, with no power cycle of the drives;
- a drive rebooted: FAULT DRIVE_REBOOTED, configured again, no motion until the host's reset
  and enable, then driving again;
- the package's square on this robot (issue item 7: the host package needs no change);
- the runner's report names the drive issue and counts the EMCY frames.

Every time measured is a difference of candump's kernel timestamps (one clock), or of the
core's step times in the runner's own log; never this process's clock after the fact.
`Robot.marks` (wall times) only find the phases of a session.
"""

from __future__ import annotations

import bisect
import itertools
import math
import pathlib
import struct
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from typing import Any

import cantools
import pytest
from vcan_cia402 import (
    BOOT_UP,
    EMCY_HEARTBEAT,
    ENABLE_OPERATION,
    HEARTBEAT_ID,
    MASTER_NODE,
    NMT_START,
    NODES,
    OPERATION_ENABLED,
    QUICK_STOP,
    READY_TO_SWITCH_ON,
    RPDO1,
    SDO_REQUEST,
    SDO_RESPONSE,
    SHUTDOWN,
    STATE_MASK,
    SWITCH_ON,
    SWITCHED_ON,
    SYNC,
    TPDO1,
    TPDO2,
    WHEEL_AXES,
    Cia402Robot,
    LogFrame,
    ACTUAL_PER_TARGET,
    before,
    read_runner_log,
    read_runner_steps,
    step_lateness,
)
from vcan_robot import (
    ANSWER_S,
    ESTOP,
    MODE_CMD,
    MODE_ENABLE,
    MODE_RESET,
    MOTIONS,
    ODOM_POSITION,
    ODOM_VELOCITY,
    ROOT,
    STATE_DISABLED,
    STATE_ENABLED,
    STATE_ESTOP,
    SQUARE,
    STATE_FAULT,
    STATUS,
    TIMING_SLACK_S,
    TWIST_CMD,
    drive_square,
    open_api,
)

import mecanum_drive

pytestmark = pytest.mark.vcan

#: The configuration every session runs: config/cia402.toml but for timing.stale_periods
#: (its comments say why); nothing else may differ.
CONFIG = pathlib.Path(__file__).resolve().parent / "cia402_vcan.toml"
_CFG = tomllib.loads(CONFIG.read_text())
_EXAMPLE = tomllib.loads((ROOT / "config" / "cia402.toml").read_text())
assert {**_CFG, "timing": {**_CFG["timing"], "stale_periods": None}} == {
    **_EXAMPLE, "timing": {**_EXAMPLE["timing"], "stale_periods": None}}, (
    f"{CONFIG} differs from config/cia402.toml in more than timing.stale_periods")

CONTROL_PERIOD_S = 1.0 / float(_CFG["timing"]["control_hz"])
CYCLE_S = 1.0 / float(_CFG["timing"]["setpoint_hz"])  # the CANopen cycle: SYNC, RPDOs, TPDOs
ODOMETRY_PERIOD_S = 1.0 / float(_CFG["timing"]["odometry_hz"])
HEARTBEAT_S = float(_CFG["drive"]["heartbeat_ms"]) / 1000
CONSUMER_S = float(_CFG["drive"]["heartbeat_timeout_ms"]) / 1000  # both ways: master and drives
TARGET_RPM_PER_UNIT = float(_CFG["drive"]["target_rpm_per_unit"])
ACTUAL_RPM_PER_UNIT = float(_CFG["drive"]["actual_rpm_per_unit"])
GEAR = float(_CFG["drive"]["gear_ratio"])
SIGN = [-1.0 if inv else 1.0 for inv in _CFG["drive"]["inverted"]]
LX, LY = float(_CFG["geometry"]["lx"]), float(_CFG["geometry"]["ly"])
RADIUS = float(_CFG["geometry"]["wheel_radius"])
MAX_LINEAR_ACCEL = float(_CFG["limits"]["max_linear_accel"])
RPM = 2 * math.pi / 60  # rad/s per rpm

# TIMING_SLACK_S, ANSWER_S and MISSED_HEARTBEATS: the lane's conventions (tests/vcan_robot.py).

#: The peer's heartbeat consumer is a Python timer: the deadline is set when the peer's
#: notifier thread has taken the master's heartbeat off its socket, and checked when its
#: timing thread wakes from `Event.wait`. Each of the two may wait for the interpreter's lock
#: for up to one switch interval (`sys.getswitchinterval()`, 5 ms) while another thread of
#: this process runs: the peer's timer resolution, on top of its 0x1016 time.
PEER_TIMER_RESOLUTION_S = 2 * sys.getswitchinterval()

#: ODOM_POSITION against the integral of the drives' reported velocities (`counted_odometry`):
#: half the frame's 0.1 mm, and 0.05 mm for the core's f32 (its wheel speeds and increments;
#: its sums are compensated). ODOM_VELOCITY.heading: half its 0.1 mrad, and 0.01 mrad.
POSE_TOL = 0.00005 + 0.00005
HEADING_TOL = 0.00005 + 0.00001

#: Each twist of MOTIONS (tests/vcan_robot.py) is held for PHASE_S; the first is set before
#: the enable.
PHASE_S = 1.5
#: From a phase's first TWIST_CMD until its targets and the drives' velocities have settled:
#: the acceleration limits (at most |dv| 0.64 m/s at 4 m/s², 1 rad/s at 12 rad/s²: 0.16 s),
#: then the peer's motor (a 50 ms lag: within a tenth of a raw unit of 0.1 rpm after 12 time
#: constants of a 300-unit step, 0.6 s); with margin.
SETTLE_S = 0.9
#: ODOM_VELOCITY against the forward kinematics of the velocities the drives reported: the
#: frame's resolution (0.001 m/s, rad/s: half of it) and the core's f32 arithmetic (relative
#: 1e-6 of speeds below 2 m/s: 2e-6), nothing else: the core's measured velocity is the
#: forward kinematics of the last TPDO of each wheel, and nothing filters it.
ODOM_TOL = 0.0005 + 2e-6


# --- the kinematics of the configuration (docs: kinematics::MecanumKinematics::standard) ----

def wheel_speeds(vx: float, vy: float, wz: float) -> list[float]:
    """FL, FR, RL, RR in rad/s, robot-forward positive."""
    k = LX + LY
    return [(vx - vy - k * wz) / RADIUS, (vx + vy + k * wz) / RADIUS,
            (vx + vy - k * wz) / RADIUS, (vx - vy + k * wz) / RADIUS]


def body_velocity(w: list[float]) -> tuple[float, float, float]:
    """The forward kinematics (least squares, exact for the standard layout)."""
    fl, fr, rl, rr = w
    return (RADIUS / 4 * (fl + fr + rl + rr), RADIUS / 4 * (-fl + fr + rl - rr),
            RADIUS / (4 * (LX + LY)) * (-fl + fr - rl + rr))


def exact_targets(vx: float, vy: float, wz: float) -> list[float]:
    """Each wheel's 0x60FF target before rounding, raw units (rpm / target_rpm_per_unit)."""
    return [s * w * GEAR / RPM / TARGET_RPM_PER_UNIT for s, w in zip(SIGN, wheel_speeds(vx, vy, wz))]


def actual_to_wheel(raw: int, wheel: int) -> float:
    """A 0x606C value of `wheel` as the core reads it: rad/s, robot-forward positive."""
    return SIGN[wheel] * raw * ACTUAL_RPM_PER_UNIT * RPM / GEAR


# --- fixtures ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cia402_factory(runner_bin: pathlib.Path, can_utils: Callable[[str], str], vcan: str,
                   tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Cia402Robot]:
    def make(name: str, **kw: Any) -> Cia402Robot:
        return Cia402Robot(runner=runner_bin, candump=can_utils("candump"), iface=vcan, config=CONFIG,
                           workdir=tmp_path_factory.mktemp(name), **kw)

    return make


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


def drive_forward(api: mecanum_drive.Robot) -> None:
    """From DISABLED: the enable, then forward at 0.3 m/s for a second (the sessions that
    then break something: a drive's heartbeat, the runner, a drive's power)."""
    api.wait_state("DISABLED", timeout=ANSWER_S)
    api.enable()
    api.wait_state("ENABLED", timeout=ANSWER_S)
    api.drive(0.3, 0.0, 0.0)
    time.sleep(1.0)


def first(frames: list[Any], what: str) -> Any:
    assert frames, f"no {what}"
    return frames[0]


def enable_frame(session: Cia402Robot, after: float) -> float:
    """The candump time of the first MODE_CMD enable at or after `after` (a wall mark, less a
    little: the mark is taken just before the API sends)."""
    frames = [f for f in session.of(MODE_CMD, after - 0.01) if f.data == bytes([MODE_ENABLE])]
    return float(first(frames, f"MODE_CMD enable after {after}").t)


def peer_latency(session: Cia402Robot, t0: float, t1: float) -> str:
    """How fast the peers answered SYNC with TPDO1 in [t0, t1), and the longest gap between
    two TPDO1 of a node (what timing.stale_periods must cover): figures for the log."""
    syncs = [f.t for f in session.of(SYNC, t0, t1)]
    parts = []
    for node in NODES:
        tpdos = [f.t for f in session.of(TPDO1 + node, t0, t1 + 0.1)]
        lat = sorted(tpdos[i] - s if (i := bisect.bisect_left(tpdos, s)) < len(tpdos) else math.inf for s in syncs)
        gap = max((b - a for a, b in zip(tpdos, tpdos[1:])), default=math.nan)
        if lat:
            parts.append(f"node {node} p50 {lat[len(lat) // 2] * 1e3:.2f} ms, max {lat[-1] * 1e3:.2f} ms "
                         f"({len(syncs)} SYNC), longest TPDO1 gap {gap * 1e3:.1f} ms")
    return "; ".join(parts)


# --- session 1: enable, motion, e-stop, a drive fault ------------------------------------------

@pytest.fixture(scope="module")
def drive(cia402_factory: Callable[..., Cia402Robot], vcan: str) -> Iterator[Cia402Robot]:
    """The twist of MOTIONS[0] streamed, then the enable; each twist of MOTIONS for PHASE_S;
    ESTOP; the host's reset; then node 1 faults (inject_fault) while disabled."""
    with cia402_factory("drive") as session:
        with open_api(vcan) as api:
            api.wait_state("DISABLED", timeout=ANSWER_S)
            _, vx, vy, wz = MOTIONS[0]
            api.drive(vx, vy, wz)  # streaming before the enable: the targets wait for it
            time.sleep(0.1)
            session.marks["enable"] = time.time()
            api.enable()
            api.wait_state("ENABLED", timeout=ANSWER_S)
            for name, vx, vy, wz in MOTIONS:
                session.marks[name] = time.time()
                api.drive(vx, vy, wz)
                time.sleep(PHASE_S)
            session.marks["estop"] = time.time()
            api.estop()
            api.wait_state("ESTOP", timeout=ANSWER_S)
            time.sleep(0.5)
            reset_and_wait_disabled(api, session)
            time.sleep(0.2)
            session.marks["fault"] = time.time()
            session.peers[1].inject_fault()
            api.wait_state("FAULT", timeout=ANSWER_S)
            session.marks["faulted"] = time.time()
            session.notes["traces"] = {n: p.trace for n, p in session.peers.items()}
            time.sleep(0.3)
    yield session


def test_enable_trace_each_step_after_the_statusword_showed_the_last(drive: Cia402Robot) -> None:
    """After the host's MODE_CMD enable each node gets 0x06 -> 0x07 -> 0x0F in RPDO1, each
    controlword only after the node's TPDO1 showed the state the one before asked for (ready
    to switch on, switched on), and at the first cycle after the core took that TPDO1 (its
    next step). Targets stay zero until both nodes are operation enabled, although the host
    streamed a twist before the enable."""
    t_enable = enable_frame(drive, drive.marks["enable"])
    t_estop = first(drive.of(ESTOP, t_enable), "ESTOP").t
    # The core takes a frame at its next step: an RPDO sent more than a control period after
    # the frame came from a step that started after it (a step takes some 0.1 ms).
    react = CONTROL_PERIOD_S
    enabled_at = {}
    report = []
    for node in NODES:
        rpdos = drive.rpdos(node, -math.inf, t_estop)
        tpdos = drive.tpdos(node, t_enable, t_estop)
        disabled = [r for r in rpdos if r[0] < t_enable]
        after = [r for r in rpdos if r[0] >= t_enable]
        assert disabled and disabled[-1][1] == SHUTDOWN, f"node {node}: not in shutdown (0x06) while disabled"
        # The controlwords after the enable: runs of 0x06, 0x07, 0x0F, in that order.
        runs = [cw for cw, _ in itertools.groupby(r[1] for r in after)]
        assert runs in ([SHUTDOWN, SWITCH_ON, ENABLE_OPERATION], [SWITCH_ON, ENABLE_OPERATION]), (
            f"node {node}: controlwords after the enable {[hex(c) for c in runs]}")
        steps = {}
        previous_t = t_enable
        for controlword, shown in ((SWITCH_ON, READY_TO_SWITCH_ON), (ENABLE_OPERATION, SWITCHED_ON)):
            sent = first([r for r in after if r[1] == controlword], f"node {node}: controlword {controlword:#x}")[0]
            # The statusword that allowed it: the first TPDO1 after the step before (the enable,
            # or the previous controlword's first RPDO1) showing the state.
            shows = [t for t, sw, _ in tpdos if previous_t < t and sw & STATE_MASK == shown]
            t_shown = first(shows, f"node {node}: statusword {shown:#x} after {previous_t}")
            assert t_shown < sent, f"node {node}: {controlword:#x} sent before the statusword showed {shown:#x}"
            # ... and sent at the first cycle once the core had it: no RPDO1 with the old
            # controlword after the step that took the statusword.
            late = [r for r in after if t_shown + react < r[0] < sent]
            assert not late, f"node {node}: {len(late)} cycles more with the old controlword after {shown:#x}"
            steps[controlword] = (sent - t_enable, t_shown - t_enable)
            previous_t = sent
        t_oe = first([t for t, sw, _ in tpdos if t > previous_t and sw & STATE_MASK == OPERATION_ENABLED],
                     f"node {node}: operation enabled")
        enabled_at[node] = t_oe
        # Once enable operation was sent, it stays until the e-stop.
        assert all(r[1] == ENABLE_OPERATION for r in after if r[0] >= previous_t)
        report.append(f"node {node}: 0x07 at {steps[SWITCH_ON][0] * 1e3:.1f} ms (statusword 0x21 at "
                      f"{steps[SWITCH_ON][1] * 1e3:.1f}), 0x0F at {steps[ENABLE_OPERATION][0] * 1e3:.1f} ms "
                      f"(0x23 at {steps[ENABLE_OPERATION][1] * 1e3:.1f}), operation enabled at "
                      f"{(t_oe - t_enable) * 1e3:.1f} ms")
    # The peers' own record: each received 0x06, 0x07, 0x0F in that order and answered with
    # ready to switch on, switched on, operation enabled (bit 4 and 9 set, as the peer does).
    traces = drive.notes["traces"]
    for node in NODES:
        got = [(e.controlword, e.statusword) for e in traces[node] if e.controlword is not None]
        i = got.index((ENABLE_OPERATION, 0x0237))
        assert got[i - 2:i + 1] == [(SHUTDOWN, 0x0231), (SWITCH_ON, 0x0233), (ENABLE_OPERATION, 0x0237)], got
    # Zero targets until every node is operation enabled (the host's twist was streaming).
    all_enabled = max(enabled_at.values())
    for node in NODES:
        moving = [r for r in drive.rpdos(node, t_enable, t_estop) if r[2] or r[3]]
        t_move = first(moving, f"node {node}: a nonzero target")[0]
        assert t_move > all_enabled, f"node {node}: a target before every node was operation enabled"
    print(f"enable trace (from the MODE_CMD enable, candump): {'; '.join(report)}; first nonzero "
          f"targets {(min(r[0] for n in NODES for r in drive.rpdos(n, t_enable, t_estop) if r[2] or r[3]) - t_enable) * 1e3:.1f} ms "
          f"(cycle {CYCLE_S * 1e3:.0f} ms); from the runner's first SYNC to the e-stop, the peers' SYNC->TPDO1 "
          f"{peer_latency(drive, drive.of(SYNC)[0].t, t_estop)}")


def phase_windows(session: Cia402Robot) -> list[tuple[str, float, float, float, float, float]]:
    """(name, vx, vy, wz, t0, t1) of each motion phase, on candump's clock: from the first
    TWIST_CMD with its twist + SETTLE_S to the next phase's first TWIST_CMD (or the ESTOP)."""
    t_enable = enable_frame(session, session.marks["enable"])
    twists = session.decoded(TWIST_CMD, t_enable)
    t_estop = first(session.of(ESTOP, t_enable), "ESTOP").t
    starts: list[tuple[str, float, float, float, float]] = []
    for name, vx, vy, wz in MOTIONS:
        t_prev = starts[-1][4] if starts else t_enable
        t = first([t for t, v in twists if t >= t_prev and (v["vx"], v["vy"], v["wz"]) == (vx, vy, wz)],
                  f"the {name} twist")
        starts.append((name, vx, vy, wz, t))
    # (The forward twist was streaming before the enable: its phase starts at its first
    # TWIST_CMD after the enable; the enable trace takes some 20 ms of SETTLE_S.)
    ends = [s[4] for s in starts[1:]] + [t_estop]
    return [(name, vx, vy, wz, t0 + SETTLE_S, t1) for (name, vx, vy, wz, t0), t1 in zip(starts, ends)]


@pytest.mark.parametrize("phase", [m[0] for m in MOTIONS])
def test_twist_targets_have_the_signs_and_scale_of_the_configuration(drive: Cia402Robot, phase: str) -> None:
    """In the settled part of each phase every RPDO carries each wheel's target as the
    configuration says: the inverse kinematics, the right side mirrored (`inverted`), in
    units of `target_rpm_per_unit` rpm, rounded to the nearest (within the core's f32: the
    exact value is within half a unit and 1e-3 of it); and each drive reports, via TPDO, its
    velocity actual in tenths of that unit (0.1 rpm) settled at ten times its target."""
    name, vx, vy, wz, t0, t1 = next(w for w in phase_windows(drive) if w[0] == phase)
    want = exact_targets(vx, vy, wz)
    got: dict[int, set[int]] = {w: set() for w in range(4)}
    for node in NODES:
        rpdos = drive.rpdos(node, t0, t1)
        assert len(rpdos) >= 0.9 * (t1 - t0) / CYCLE_S, f"node {node}: {len(rpdos)} cycles in {t1 - t0:.2f} s"
        for t, controlword, *targets in rpdos:
            assert controlword == ENABLE_OPERATION
            for axis, raw in enumerate(targets):
                wheel = next(w for w, na in WHEEL_AXES.items() if na == (node, axis))
                got[wheel].add(raw)
    for wheel in range(4):
        assert len(got[wheel]) == 1, f"{name}: wheel {wheel} targets changed in the settled window: {got[wheel]}"
        raw = got[wheel].pop()
        assert abs(raw - want[wheel]) <= 0.5 + 1e-3, f"{name}: wheel {wheel} target {raw}, configuration {want[wheel]:.3f}"
        if abs(want[wheel]) >= 1:
            assert math.copysign(1, raw) == math.copysign(1, want[wheel])
        got[wheel].add(raw)
    if name == "forward":
        # Forward: the left wheels positive, the right ones (mirrored motors) negative.
        assert [math.copysign(1, next(iter(got[w]))) for w in range(4)] == [1, -1, 1, -1]
    # The drives' velocity actual values: settled at 10 x the target (0.1 rpm units).
    actual = {0: [v for _, _, v in drive.tpdos(1, t0, t1)], 1: [v for _, v in drive.tpdo2s(1, t0, t1)],
              2: [v for _, _, v in drive.tpdos(2, t0, t1)], 3: [v for _, v in drive.tpdo2s(2, t0, t1)]}
    for wheel, values in actual.items():
        target = next(iter(got[wheel]))
        assert values and all(abs(v - ACTUAL_PER_TARGET * target) <= 1 for v in values), (
            f"{name}: wheel {wheel} velocity actual {sorted(set(values))} for target {target}")
    body = body_velocity([actual_to_wheel(actual[w][-1], w) for w in range(4)])
    print(f"{name}: twist ({vx}, {vy}, {wz}) -> targets {[next(iter(got[w])) for w in range(4)]} rpm "
          f"(exact {[round(x, 2) for x in want]}), settled velocity actual -> body "
          f"({body[0]:.4f}, {body[1]:.4f}, {body[2]:.4f})")


def test_odometry_follows_the_velocities_the_drives_reported(drive: Cia402Robot) -> None:
    """Every ODOM_VELOCITY from the enable to the e-stop is the forward kinematics of the
    velocities the drives reported (TPDO1/TPDO2 in 0.1 rpm, the right side mirrored): of the
    last TPDO of each wheel before it, or the one before that (a TPDO that arrived while the
    core's step ran is taken at the next step); within ODOM_TOL. And in each settled phase
    its mean is the commanded twist within the targets' rounding to whole rpm."""
    t_enable = enable_frame(drive, drive.marks["enable"])
    t_estop = first(drive.of(ESTOP, t_enable), "ESTOP").t
    actuals = drive.wheel_actuals()
    odoms = drive.decoded(ODOM_VELOCITY, t_enable, t_estop)
    assert len(odoms) > 0.9 * (t_estop - t_enable) / ODOMETRY_PERIOD_S, len(odoms)
    worst = 0.0
    moving = 0
    for t, v in odoms:
        candidates = []
        for wheel in range(4):
            last2 = before(actuals[wheel], t, 2)
            assert last2, f"no TPDO of wheel {wheel} before the ODOM_VELOCITY at {t}"
            candidates.append({actual_to_wheel(raw, wheel) for raw in last2})
        err = min(
            max(abs(fk[0] - v["vx"]), abs(fk[1] - v["vy"]), abs(fk[2] - v["wz"]))
            for fk in (body_velocity(list(combo)) for combo in itertools.product(*candidates))
        )
        worst = max(worst, err)
        moving += any(abs(v[k]) > 0.05 for k in ("vx", "vy", "wz"))
        assert err <= ODOM_TOL, f"ODOM_VELOCITY at {t}: {v}, {err:.5f} from the drives' reported velocities"
    assert moving > 0.5 * len(odoms), "the robot hardly moved"
    # Each wheel within half an rpm of its exact target, and its actual within 1 raw unit
    # (0.1 rpm) of ten times the target: the body within the forward kinematics of that on
    # every wheel, plus the frame's half unit.
    wheel_err = (0.5 * TARGET_RPM_PER_UNIT + ACTUAL_RPM_PER_UNIT) * RPM / GEAR
    tol = {"vx": RADIUS * wheel_err + 0.0005, "vy": RADIUS * wheel_err + 0.0005,
           "wz": RADIUS * wheel_err / (LX + LY) + 0.0005}
    lines = []
    for name, vx, vy, wz, t0, t1 in phase_windows(drive):
        window = [v for t, v in odoms if t0 <= t < t1]
        assert window, name
        mean = {k: sum(v[k] for v in window) / len(window) for k in ("vx", "vy", "wz")}
        for axis, want in zip(("vx", "vy", "wz"), (vx, vy, wz)):
            assert abs(mean[axis] - want) <= tol[axis], f"{name}: odometry {axis} {mean[axis]:.4f}, commanded {want}"
        lines.append(f"{name} ({mean['vx']:.4f}, {mean['vy']:.4f}, {mean['wz']:.4f})")
    print(f"odometry: {len(odoms)} ODOM_VELOCITY, worst {worst * 1e3:.3f} mm/s (mrad/s) from the forward "
          f"kinematics of the drives' reported velocities (tolerance {ODOM_TOL * 1e3:.3f}); settled means "
          f"{'; '.join(lines)}")


def test_estop_quick_stops_every_node_at_the_next_cycle(drive: Cia402Robot) -> None:
    """ESTOP: from the first cycle after the core took it (its next step), every node gets
    quick stop (0x02) with zero targets, until the host's reset; the robot reports ESTOP; the
    drives go through quick stop active to switch on disabled (quick stop option code 2).

    Budget on candump's clock, a control period and a cycle: the core takes the ESTOP at its
    next step (within a control period) and sends the quick stop at the first cycle step from
    there (at most 3 steps on: a cycle is 4), which leaves a control period for that step's
    lateness and its sending."""
    t_estop = first(drive.of(ESTOP, drive.marks["estop"] - 0.01), "ESTOP").t
    t_reset = first([f.t for f in drive.of(MODE_CMD, t_estop) if f.data == bytes([MODE_RESET])], "reset")
    budget = CONTROL_PERIOD_S + CYCLE_S + TIMING_SLACK_S
    latencies = []
    for node in NODES:
        driving = drive.rpdos(node, t_estop - 0.1, t_estop)
        assert driving and driving[-1][1] == ENABLE_OPERATION and (driving[-1][2] or driving[-1][3]), (
            f"node {node} was not driving before the e-stop: {driving[-1:]}")
        rpdos = drive.rpdos(node, t_estop, t_reset)
        stop = first([r for r in rpdos if r[1] == QUICK_STOP], f"node {node}: quick stop")
        # Before it only a cycle the core sent before its step took the ESTOP.
        assert all(r[0] <= t_estop + CONTROL_PERIOD_S for r in rpdos if r[0] < stop[0])
        assert all((r[1], r[2], r[3]) == (QUICK_STOP, 0, 0) for r in rpdos if r[0] >= stop[0]), (
            f"node {node}: not quick stop with zero targets until the reset")
        latencies.append(stop[0] - t_estop)
        words = [sw & STATE_MASK for _, sw, _ in drive.tpdos(node, stop[0], t_reset)]
        assert 0x07 in words and words[-1] & 0x4F == 0x40, f"node {node}: statuswords {[hex(w) for w in words]}"
    statuses = drive.decoded(STATUS, t_estop + max(latencies), t_reset)
    assert statuses and all(s["state"] == STATE_ESTOP for _, s in statuses), statuses[:3]
    print(f"e-stop: quick stop with zero targets {', '.join(f'node {n} {l * 1e3:.2f} ms' for n, l in zip(NODES, latencies))} "
          f"after the ESTOP frame (budget {budget * 1e3:.2f} ms: a control period and a cycle"
          f"{f', {TIMING_SLACK_S * 1e3:.0f} ms emulation slack' if TIMING_SLACK_S else ''})")
    assert max(latencies) <= budget


def test_a_drive_fault_is_reported_with_its_emcy(drive: Cia402Robot) -> None:
    """Node 1 faults (statusword fault bit, EMCY 0x2310) while the robot is disabled: FAULT
    DRIVE_ERROR, quick stop to both nodes; the runner's report names the node, its statusword
    and its EMCY (`controller.drive_issue`) and counts every EMCY it received (`drive_emcy`)."""
    t_fault = first([t for t, code, _ in drive.emcys(1, drive.marks["fault"] - 0.01) if code == 0x2310], "EMCY 0x2310")
    statuses = drive.decoded(STATUS, t_fault)
    t_status = first([t for t, s in statuses if s["state"] == STATE_FAULT], "STATUS FAULT")
    assert drive.status_in(t_status, math.inf)["fault"] == 3  # DRIVE_ERROR
    for node in NODES:
        rpdos = drive.rpdos(node, t_status, t_status + 0.2)
        assert rpdos and all(r[1:] == (QUICK_STOP, 0, 0) for r in rpdos), rpdos[:2]
    controller = drive.runner_stats["controller"]
    assert controller["drive_issue"] == "node 1: statusword 0x0208 (FAULT), last EMCY 0x2310", controller
    # Every EMCY the drives sent while the runner ran (at the end they trip on its silence).
    t_last = max(f.t for f in drive.frames if f.id == SYNC)
    emcys = [e for node in NODES for e in drive.emcys(node, t1=t_last)]
    assert controller["drive_emcy"] == len(emcys) == 1, (controller, emcys)
    print(f"drive fault: report drive_issue {controller['drive_issue']!r}, drive_emcy {controller['drive_emcy']}")


# --- session 2: a drive's heartbeat lost ---------------------------------------------------

@pytest.fixture(scope="module")
def silent(cia402_factory: Callable[..., Cia402Robot], vcan: str) -> Iterator[Cia402Robot]:
    """Driving forward, node 2 stops its heartbeat (it still answers SYNC)."""
    with cia402_factory("silent", runner_log=True) as session:
        with open_api(vcan) as api:
            drive_forward(api)
            session.marks["silent"] = time.time()
            session.peers[2].stop_heartbeat()
            api.wait_state("FAULT", timeout=ANSWER_S)
            time.sleep(0.5)
    yield session


def test_a_lost_drive_heartbeat_faults_drive_silent_and_quick_stops(silent: Cia402Robot) -> None:
    """The runner's STATUS shows FAULT DRIVE_SILENT, and quick stop (0x02) with zero targets
    reaches both nodes within the consumer time (150 ms) and a cycle after node 2's last
    heartbeat, and not before the consumer time:

    - on the core's own record (its log): from the step that took the heartbeat to the step
      that sent the quick stop, at least 150 steps and at most 150 + 4 (the consumer time
      and a cycle, in control periods);
    - on candump's clock: from the heartbeat frame to the quick stop's RPDO1, at most the
      consumer time, a cycle, and a control period more (the core takes a frame at its next
      step), plus the lateness of the step that sent it (replayed from the log's step times
      as the loop schedules them)."""
    # Operational heartbeats (0x05: before, boot-ups and pre-operational ones).
    hb = [f.t for f in silent.of(HEARTBEAT_ID + 2) if f.data == b"\x05"]
    t_last = hb[-1]
    assert silent.marks["silent"] - HEARTBEAT_S - 0.01 < t_last < silent.marks["silent"] + 0.01, (
        "node 2's heartbeat did not stop when asked, or had stopped before")
    gaps = [b - a for a, b in zip(hb, hb[1:])]
    assert gaps and max(gaps) < CONSUMER_S and abs(sum(gaps) / len(gaps) - HEARTBEAT_S) < 0.002, (
        "node 2's heartbeat was not regular before it stopped")
    latencies = []
    for node in NODES:
        rpdos = silent.rpdos(node, t_last)
        stop = first([r for r in rpdos if r[1] == QUICK_STOP], f"node {node}: quick stop")
        assert all((r[1], r[2], r[3]) == (QUICK_STOP, 0, 0) for r in rpdos if r[0] >= stop[0])
        assert any(r[2] or r[3] for r in rpdos if r[0] < stop[0]), f"node {node} was not driving"
        latencies.append(stop[0] - t_last)
    status = silent.status_in(max(latencies) + t_last, math.inf)
    assert (status["state"], status["fault"]) == (STATE_FAULT, 9), status  # DRIVE_SILENT
    assert silent.runner_stats["controller"]["drive_issue"] == "node 2: heartbeat lost"
    # The runner's log: the step that took node 2's last heartbeat, the steps that sent the
    # quick stops.
    assert silent.runner_mcap is not None
    log = read_runner_log(silent.runner_mcap)
    steps = read_runner_steps(silent.runner_mcap)
    lateness = step_lateness(steps, CONTROL_PERIOD_S)
    took = [f.t for f in log if not f.tx and f.id == HEARTBEAT_ID + 2][-1]
    i = steps.index(took)
    counted, late = [], []
    for node in NODES:
        sent = first([f.t for f in log if f.tx and f.id == RPDO1 + node and f.t > took
                      and struct.unpack_from("<H", f.data)[0] == QUICK_STOP], f"node {node}: logged quick stop")
        j = steps.index(sent)
        counted.append(j - i)
        late.append(lateness[j])
    consumer_steps = round(CONSUMER_S / CONTROL_PERIOD_S)
    cycle_steps = round(CYCLE_S / CONTROL_PERIOD_S)
    budgets = [CONSUMER_S + CYCLE_S + CONTROL_PERIOD_S + lj + TIMING_SLACK_S for lj in late]
    print(f"heartbeat lost: quick stop {', '.join(f'node {n} {l * 1e3:.2f} ms' for n, l in zip(NODES, latencies))} "
          f"after node 2's last heartbeat on candump (budget {', '.join(f'{b * 1e3:.3f}' for b in budgets)} ms: "
          f"consumer {CONSUMER_S * 1e3:.0f} + cycle {CYCLE_S * 1e3:.0f} + the step that takes the frame "
          f"{CONTROL_PERIOD_S * 1e3:.0f} + that step's lateness); on the core's record {counted} steps "
          f"(budget {consumer_steps}-{consumer_steps + cycle_steps})")
    assert all(consumer_steps <= n <= consumer_steps + cycle_steps for n in counted), counted
    assert all(CONSUMER_S <= l <= b for l, b in zip(latencies, budgets)), (latencies, budgets)


# --- session 3: the runner killed ----------------------------------------------------------

@pytest.fixture(scope="module")
def killed(cia402_factory: Callable[..., Cia402Robot], vcan: str) -> Iterator[Cia402Robot]:
    """Driving forward, the runner is SIGKILLed: no shutdown frames, its heartbeat stops.
    Then the same runner is started again (the drives left as they are, no power cycle); the
    host resets, enables and drives forward for RESTART_DRIVE_S."""
    with cia402_factory("killed") as session:
        with open_api(vcan) as api:
            drive_forward(api)
            session.marks["kill"] = session.kill("runner")
            time.sleep(4 * CONSUMER_S)
            session.notes["states"] = {n: p.state for n, p in session.peers.items()}
            session.notes["nmt"] = {n: p.nmt_state for n, p in session.peers.items()}
        session.marks["restart"] = time.time()
        session.notes["restart_status"] = session.restart_runner()
        with open_api(vcan) as api:
            reset_and_wait_disabled(api, session)
            session.marks["enable"] = time.time()
            api.enable()
            api.drive(0.3, 0.0, 0.0)
            api.wait_state("ENABLED", timeout=ANSWER_S)
            time.sleep(RESTART_DRIVE_S)
            session.marks["end"] = time.time()
    yield session


def test_each_drive_faults_on_the_killed_masters_silence(killed: Cia402Robot) -> None:
    """Each drive's heartbeat consumer (0x1016:01 = 127 << 16 | 150) trips: EMCY 0x8130 on the
    bus within its 0x1016 time after the master's last heartbeat frame, plus the peer's timer
    resolution (PEER_TIMER_RESOLUTION_S); never before; and the drive is in fault."""
    t_restart = restart_frame(killed)
    master_hb = killed.of(HEARTBEAT_ID + MASTER_NODE, t1=t_restart)
    t_last = master_hb[-1].t
    assert t_last <= killed.marks["kill"] + 0.01, "the master's heartbeat went on after the kill"
    assert not killed.of(SYNC, killed.marks["kill"] + 0.01, t_restart), "the master's cycle went on after the kill"
    budget = CONSUMER_S + PEER_TIMER_RESOLUTION_S + TIMING_SLACK_S
    latencies = []
    for node in NODES:
        assert killed.rpdos(node, t_last - 0.1, t_last)[-1][1] == ENABLE_OPERATION, f"node {node} was not enabled"
        emcys = killed.emcys(node, t_last, t_restart)
        assert [(code, register) for _, code, register in emcys] == [(EMCY_HEARTBEAT, 0x11)], emcys
        latencies.append(emcys[0][0] - t_last)
        assert killed.notes["states"][node].name == "FAULT"
    print(f"runner killed: EMCY 0x8130 {', '.join(f'node {n} {l * 1e3:.2f} ms' for n, l in zip(NODES, latencies))} "
          f"after the master's last heartbeat (0x1016 time {CONSUMER_S * 1e3:.0f} ms + the peer's timer "
          f"resolution {PEER_TIMER_RESOLUTION_S * 1e3:.0f} ms)")
    assert all(CONSUMER_S <= l <= budget for l in latencies), latencies


#: How long the host drives after the restarted runner's enable: SETTLE_S and 0.3 s settled.
RESTART_DRIVE_S = 1.2


def restart_frame(session: Cia402Robot) -> float:
    """The candump time of the restarted runner's first frame: the master's own boot-up
    (0x700 + its node id, 0x00; docs/protocol.md), after the kill."""
    boots = [f.t for f in session.of(HEARTBEAT_ID + MASTER_NODE, session.marks["kill"]) if f.data == bytes([BOOT_UP])]
    return float(first(boots, "the restarted runner's boot-up"))


def nmt_runs(session: Cia402Robot, node: int, t0: float, t1: float) -> list[int]:
    """The NMT states `node`'s heartbeats (and boot-ups) said in [t0, t1), repeats folded."""
    return [state for state, _ in itertools.groupby(f.data[0] for f in session.of(HEARTBEAT_ID + node, t0, t1))]


def test_a_killed_runner_restarted_drives_again_after_reset_and_enable(killed: Cia402Robot) -> None:
    """The runner killed while driving, then started again; the drives are not power cycled:

    - each drive leaves operational on its consumer's time-out: its 0x7F heartbeat right
      after its EMCY 0x8130 (the same pass of the peer's timing thread), and stays
      pre-operational (CiA 301's 0x1029 = 0) until the restarted runner's NMT reset
      communication: the NMT state sequence operational, pre-operational, boot-up,
      (pre-operational,) operational;
    - the restarted runner configures each node with the same SDO requests as the first did
      and starts it; the drives kept their fault (reset communication leaves the drive's
      state alone), so the robot reports FAULT and sends no target until the host's reset;
    - the host's reset and enable: a fault reset (EMCY 0x0000 from each node), then 0x06,
      0x07, 0x0F and operation enabled; the wheels follow their targets (the peers' velocity
      actual settled at ten times the target) and the odometry shows the twist.
    Times on candump's clock."""
    t_kill = killed.marks["kill"]
    t_restart = restart_frame(killed)
    t_enable = enable_frame(killed, killed.marks["enable"])
    t_reset = first([f.t for f in killed.of(MODE_CMD, t_restart) if f.data == bytes([MODE_RESET])], "reset")
    end = killed.marks["end"]
    assert t_kill < t_restart < t_reset < t_enable < end
    assert killed.notes["nmt"] == {1: 0x7F, 2: 0x7F}, killed.notes["nmt"]
    report = []
    for node in NODES:
        (t_emcy, code, _), = killed.emcys(node, t_kill - 0.2, t_restart)
        assert code == EMCY_HEARTBEAT
        pre_op = first([f.t for f in killed.of(HEARTBEAT_ID + node, t_emcy, t_restart) if f.data == b"\x7f"],
                       f"node {node}: a 0x7F heartbeat after its EMCY")
        assert pre_op - t_emcy <= PEER_TIMER_RESOLUTION_S + TIMING_SLACK_S, (node, pre_op - t_emcy)
        runs = nmt_runs(killed, node, t_kill - 0.2, end)
        assert runs in ([0x05, 0x7F, BOOT_UP, 0x05], [0x05, 0x7F, BOOT_UP, 0x7F, 0x05]), (node, runs)
        # The configuration again, request for request, every transfer answered; NMT start.
        node_starts = [t for t, cmd, n in killed.nmt() if (cmd, n) == (NMT_START, node)]
        assert len(node_starts) == 2 and t_restart < node_starts[1] < t_reset, node_starts
        first_setup = [f.data for f in killed.of(SDO_REQUEST + node, t1=node_starts[0])]
        again = killed.of(SDO_REQUEST + node, t_restart, node_starts[1])
        assert [f.data for f in again] == first_setup, (node, len(again), len(first_setup))
        answers = killed.of(SDO_RESPONSE + node, t_restart, node_starts[1])
        assert len(answers) == len(again) and all(a.data[0] != 0x80 for a in answers)
        # Still in fault (statusword 0x0208 under 0x4F) from its start to the reset; no target.
        words = {sw & 0x4F for _, sw, _ in killed.tpdos(node, node_starts[1], t_reset)}
        assert words == {0x08}, (node, {hex(w) for w in words})
        assert all(r[2] == r[3] == 0 for r in killed.rpdos(node, t_restart, t_enable)), f"node {node}: a target"
        # The reset: fault reset (bit 7) to the node, its EMCY 0x0000; then the enable.
        resets = [r[0] for r in killed.rpdos(node, t_reset, end) if r[1] & 0x80]
        t_fault_reset = first(resets, f"node {node}: a fault reset")
        assert [(c, reg) for _, c, reg in killed.emcys(node, t_fault_reset, end)] == [(0x0000, 0x00)]
        t_oe = first([t for t, sw, _ in killed.tpdos(node, t_enable, end) if sw & STATE_MASK == OPERATION_ENABLED],
                     f"node {node}: operation enabled")
        report.append(f"node {node}: NMT {'-'.join(f'0x{s:02X}' for s in runs)}, 0x7F "
                      f"{(pre_op - t_emcy) * 1e3:.2f} ms after EMCY 0x8130; started {(node_starts[1] - t_restart) * 1e3:.1f} ms "
                      f"after the restart ({len(again)} SDO transfers), operation enabled {(t_oe - t_restart) * 1e3:.0f} ms "
                      f"after the restart, {(t_oe - t_enable) * 1e3:.1f} ms after the enable")
    # Driving: from SETTLE_S after the enable, each wheel's velocity actual at ten times its
    # target (raw 0.1 rpm against rpm, within a unit), the targets those of 0.3 m/s forward.
    settled = t_enable + SETTLE_S
    assert end - settled >= 0.2, end - settled
    want = exact_targets(0.3, 0.0, 0.0)
    follow = []
    for wheel, (node, axis) in WHEEL_AXES.items():
        targets = {r[2 + axis] for r in killed.rpdos(node, settled, end)}
        assert len(targets) == 1, (wheel, targets)
        target = targets.pop()
        assert abs(target - want[wheel]) <= 0.5 + 1e-3, (wheel, target, want[wheel])
        actuals = [v for t, v in killed.wheel_actuals()[wheel] if settled <= t < end]
        assert actuals and all(abs(v - ACTUAL_PER_TARGET * target) <= 1 for v in actuals), (wheel, target, actuals[:3])
        follow.append(f"{target} rpm -> {actuals[-1] / ACTUAL_PER_TARGET:.1f}")
    vel = killed.decoded(ODOM_VELOCITY, settled, end)
    assert vel and all(abs(v["vx"] - 0.3) < 0.01 for _, v in vel), vel[-3:]
    statuses = killed.decoded(STATUS, t_enable + 0.1, end)
    assert statuses and all(s["state"] == STATE_ENABLED for _, s in statuses)
    restart_status = killed.notes["restart_status"]
    print(f"runner restarted {(t_restart - t_kill) * 1e3:.0f} ms after the kill, first STATUS state "
          f"{restart_status['state']} fault {restart_status['fault']}; {'; '.join(report)}; wheels (target -> "
          f"actual) {', '.join(follow)}; odometry vx {vel[-1][1]['vx']:.3f} m/s; the restart to the end took "
          f"{end - killed.marks['restart']:.2f} s of the session")


# --- session 4: a drive rebooted ------------------------------------------------------------

@pytest.fixture(scope="module")
def rebooted(cia402_factory: Callable[..., Cia402Robot], vcan: str) -> Iterator[Cia402Robot]:
    """Driving forward, node 1 reboots (a power cycle); the host keeps streaming the twist,
    then resets and enables again and drives on."""
    with cia402_factory("rebooted") as session:
        with open_api(vcan) as api:
            drive_forward(api)
            session.marks["reboot"] = time.time()
            session.peers[1].reboot()
            api.wait_state("FAULT", timeout=ANSWER_S)
            time.sleep(1.0)  # the twist keeps coming: nothing may move
            reset_and_wait_disabled(api, session)
            session.marks["enable"] = time.time()
            api.enable()
            api.wait_state("ENABLED", timeout=ANSWER_S)
            time.sleep(1.0)
            session.marks["end"] = time.time()
    yield session


def test_a_rebooted_drive_is_configured_again_and_waits_for_the_host(rebooted: Cia402Robot) -> None:
    """Node 1's boot-up: FAULT DRIVE_REBOOTED; the node is configured again (the same SDO
    sequence as at the start, each transfer answered, then NMT start); from the step that
    took the boot-up on, no RPDO with a nonzero target to any node until the host's reset and
    enable, though its twist kept coming; then both nodes drive again."""
    boots = [f.t for f in rebooted.of(HEARTBEAT_ID + 1) if f.data == bytes([BOOT_UP])]
    t_boot = first([t for t in boots if t >= rebooted.marks["reboot"] - 0.01], "node 1's boot-up")
    t_enable = enable_frame(rebooted, rebooted.marks["enable"])
    t_reset = first([f.t for f in rebooted.of(MODE_CMD, t_boot) if f.data == bytes([MODE_RESET])], "reset")
    end = rebooted.marks["end"]
    assert t_boot < t_reset < t_enable < end
    took = t_boot + CONTROL_PERIOD_S  # the core takes the boot-up at its next step
    # FAULT DRIVE_REBOOTED from the next STATUS until the reset.
    statuses = rebooted.decoded(STATUS, took, t_reset)
    assert statuses and all((s["state"], s["fault"]) == (STATE_FAULT, 10) for _, s in statuses), statuses[:2]
    # The reset clears it for good: DISABLED from the step that took it to the enable (the
    # package waited for a DISABLED STATUS, which that very step may have sent).
    statuses = rebooted.decoded(STATUS, t_reset, t_enable)
    assert any(s["state"] == STATE_DISABLED for _, s in statuses), statuses
    assert all(s["state"] == STATE_DISABLED for t, s in statuses
               if t > t_reset + CONTROL_PERIOD_S), statuses
    # The configuration again: what the master sent node 1 at the start, request for request
    # (command, index, sub-index, data), each answered (no abort), then NMT start.
    starts = [t for t, cmd, node in rebooted.nmt() if (cmd, node) == (NMT_START, 1)]
    assert len(starts) == 2 and t_boot < starts[1] < t_reset, starts
    first_setup = [f.data for f in rebooted.of(SDO_REQUEST + 1, t1=starts[0])]
    again = rebooted.of(SDO_REQUEST + 1, t_boot, starts[1])
    assert [f.data for f in again] == first_setup, (len(again), len(first_setup))
    # RPDO2 off first (a download), the device type read (an upload), 34 downloads
    # (docs/protocol.md's steps 2-5 for a dual-axis node: 3 objects, 2 option codes, 7 + 6 for
    # RPDO1 and RPDO3, 7 + 6 for TPDO1 and TPDO2, 3 PDOs off), the mode display read last.
    assert [f.data[0] & 0xE0 for f in again] == [0x20, 0x40] + [0x20] * 34 + [0x40]
    assert [struct.unpack_from("<HB", again[i].data, 1) for i in (0, 1, -1)] == [
        (0x1401, 1), (0x1000, 0), (0x6061, 0)]
    answers = rebooted.of(SDO_RESPONSE + 1, t_boot, starts[1])
    assert len(answers) == len(again) and all(a.data[0] != 0x80 for a in answers)
    # No motion from the step that took the boot-up to the new enable: zero targets to every
    # node (quick stop while faulted, shutdown after the reset), although the twist kept coming.
    twists = rebooted.decoded(TWIST_CMD, t_boot, t_enable)
    assert len(twists) > 0.8 * 50 * (t_enable - t_boot) and all(v["vx"] == 0.3 for _, v in twists)
    for node in NODES:
        rpdos = rebooted.rpdos(node, took, t_enable)
        assert rpdos and all(r[2] == r[3] == 0 for r in rpdos), f"node {node}: a target while faulted"
        faulted = [r[1] for r in rpdos if r[0] < t_reset]
        assert faulted and set(faulted) == {QUICK_STOP}, {hex(c) for c in faulted}
        assert {r[1] for r in rpdos if r[0] > t_reset + CONTROL_PERIOD_S} <= {SHUTDOWN}
    assert rebooted.rpdos(1, starts[1], t_reset), "no cycle to node 1 once it was started again"
    # Driving again after the reset and the enable: both nodes operation enabled with nonzero
    # targets, their reported velocities and the odometry forward.
    for node in NODES:
        rpdos = rebooted.rpdos(node, t_enable, end)
        assert any(r[1] == ENABLE_OPERATION and r[2] and r[3] for r in rpdos), f"node {node} does not drive"
        assert any(v > 0 for _, sw, v in rebooted.tpdos(node, t_enable, end) if sw & STATE_MASK == OPERATION_ENABLED)
    vel = rebooted.decoded(ODOM_VELOCITY, end - 0.3, end)
    assert vel and all(abs(v["vx"] - 0.3) < 0.01 for _, v in vel), vel[-3:]
    statuses = rebooted.decoded(STATUS, t_enable + 0.1, end)
    assert statuses and all(s["state"] == STATE_ENABLED for _, s in statuses)
    issue = rebooted.runner_stats["controller"]["drive_issue"]
    assert issue == "node 1: booted again, configured anew", issue
    print(f"reboot: FAULT DRIVE_REBOOTED; node 1 configured again ({len(again)} SDO transfers, the last "
          f"answered {(answers[-1].t - t_boot) * 1e3:.1f} ms after its boot-up, NMT start at "
          f"{(starts[1] - t_boot) * 1e3:.1f} ms); {len(twists)} TWIST_CMD of 0.3 m/s and no target "
          f"until the host's reset and enable ({(t_enable - t_boot) * 1e3:.0f} ms after the boot-up); "
          f"driving again, odometry vx {vel[-1][1]['vx']:.3f} m/s; report {issue!r}; STATUS the package "
          f"took after its reset() before DISABLED: {rebooted.notes.get('stale_after_reset', [])}")


# --- session 5: the package's square (issue item 7) -------------------------------------------

# SQUARE, LEG_S and drive_square: tests/test_vcan_drive.py's square (tests/vcan_robot.py).


@pytest.fixture(scope="module")
def square(cia402_factory: Callable[..., Cia402Robot], vcan: str) -> Iterator[Cia402Robot]:
    """tests/test_vcan_drive.py's square through the API, as written there, on this robot."""
    with cia402_factory("square", runner_log=True) as session:
        with open_api(vcan) as robot:
            session.marks["enable"] = time.time()
            corners, session.notes["final"] = drive_square(robot)
            session.notes["status"] = robot.status
            session.notes["corners"] = corners
            session.notes["tau"] = {n: p.time_constant_s for n, p in session.peers.items()}
            time.sleep(0.3)
            session.marks["end"] = time.time()
    yield session


def counted_odometry(log: list[LogFrame]) -> list[tuple[float, float, float, float, float]]:
    """The odometry the core reports, recounted from its own log: at each ODOM_VELOCITY it
    sent, (its step's time, the x and y of the recount less ODOM_POSITION's, the recount's
    heading, ODOM_VELOCITY's heading). Each step adds up the TPDOs it took (a TPDO's velocity for one cycle, 0.1 rpm, the right side
    mirrored), and the forward kinematics of the sum moves the pose along the arc from its
    heading (`Pose2::exp`). ODOM_POSITION precedes its ODOM_VELOCITY in the same step."""
    wheel_of = {(TPDO1 if axis == 0 else TPDO2) + node: (wheel, axis) for wheel, (node, axis) in WHEEL_AXES.items()}
    x = y = h = 0.0
    pending = [0.0] * 4
    out = []
    position: tuple[float, float] | None = None
    db: Any = cantools.database.load_file(str(ROOT / "dbc" / "mecanum_robot.dbc"))

    def apply() -> None:
        nonlocal x, y, h, pending
        dx, dy, dh = body_velocity(pending)
        sinc = math.sin(dh / 2) / (dh / 2) if dh else 1.0
        mid = h + dh / 2
        x += (math.cos(mid) * dx - math.sin(mid) * dy) * sinc
        y += (math.sin(mid) * dx + math.cos(mid) * dy) * sinc
        h += dh
        pending = [0.0] * 4

    step = -math.inf
    for f in log:
        if f.t != step:  # a new step: the last one's TPDOs, all taken before it sent anything
            apply()
            step = f.t
        if not f.tx and f.id in wheel_of:
            wheel, axis = wheel_of[f.id]
            raw = struct.unpack_from("<i", f.data, 2 if axis == 0 else 0)[0]
            pending[wheel] += actual_to_wheel(raw, wheel) * CYCLE_S
        elif f.tx and f.id == ODOM_POSITION:
            apply()  # this step's TPDOs
            p = db.decode_message(ODOM_POSITION, f.data)
            position = (float(p["x"]), float(p["y"]))
        elif f.tx and f.id == ODOM_VELOCITY:
            assert position is not None
            v = db.decode_message(ODOM_VELOCITY, f.data)
            out.append((f.t, x - position[0], y - position[1], h, float(v["heading"])))
    return out


def test_the_packages_square_runs_unchanged_on_the_cia402_robot(square: Cia402Robot) -> None:
    """The package's square (tests/test_vcan_drive.py's, through the same API calls)
    completes on this robot with every STATUS ENABLED and sensible odometry:

    - every pose the core sent is the integral of the velocities the drives reported, as the
      runner's log says its steps took them (`counted_odometry`: each TPDO for one cycle,
      0.1 rpm, the right side mirrored), within POSE_TOL and HEADING_TOL;
    - the heading stays within what the two nodes' sampling skew gives;
    - each corner, and the end after the stop, is the legs' as the robot received them, less
      the lag of the drives' motion behind the command;
    - the package's last odometry is the robot's last ODOM frames."""
    session = square
    t_enable = enable_frame(session, session.marks["enable"])
    t_end = session.marks["end"]
    statuses = session.decoded(STATUS, t_enable + 0.1, t_end)
    assert statuses and all(s["state"] == STATE_ENABLED for _, s in statuses), [
        s for _, s in statuses if s["state"] != STATE_ENABLED][:1]
    status = session.notes["status"]
    assert status is not None and status.state == "ENABLED"
    taus = set(session.notes["tau"].values())
    assert len(taus) == 1
    tau = taus.pop()
    positions = session.decoded(ODOM_POSITION, t_enable, t_end)
    headings = session.decoded(ODOM_VELOCITY, t_enable, t_end)
    final = positions[-1][1]
    api_final = session.notes["final"]
    # The API reports what the robot said.
    assert api_final is not None and (api_final.x, api_final.y) == pytest.approx((final["x"], final["y"]), abs=2e-4)

    # The heading: the targets of a translation are symmetric, but node 1 (the front wheels)
    # and node 2 (the rear) sample their motors when each answers SYNC: while a strafe's
    # wheel speeds change (by 4 rad/s at each start and stop of a 0.4 m/s strafe), the front
    # and rear differ by that change's rate times the difference of the two answers' times,
    # which the forward kinematics read as a turn of r / (2 (lx + ly)) times it: at most the
    # largest difference of the two nodes' answer times per change of speed.
    syncs = [f.t for f in session.of(SYNC, t_enable, t_end)]
    answers = {node: [f.t for f in session.of(TPDO1 + node, t_enable, t_end + 0.1)] for node in NODES}
    delays = {node: [answers[node][bisect.bisect_left(answers[node], s)] - s for s in syncs[:-1]] for node in NODES}
    delay = max(max(d) for d in delays.values())
    skew = max(abs(a - b) for a, b in zip(delays[1], delays[2]))
    strafe_changes = sum(abs(a[1] - b[1]) for a, b in zip([(0.0, 0.0), *SQUARE], [*SQUARE, (0.0, 0.0)]))
    heading_tol = strafe_changes / (2 * (LX + LY)) * skew + 0.0001
    heading = max(abs(v["heading"]) for _, v in headings)
    print(f"square heading: at most {heading * 1e3:.3f} mrad (tolerance {heading_tol * 1e3:.3f} mrad: the nodes' "
          f"answers up to {skew * 1e3:.2f} ms apart)")
    assert heading <= heading_tol, "the heading moved"

    # The odometry is the integral of the drives' reports, on the core's own record (which
    # TPDOs each step took: the core integrates a TPDO at the step that takes it, and the
    # two TPDOs of a node often land in two steps, so only its own record gives the same
    # sums): every pose it sent against `counted_odometry`.
    assert session.runner_mcap is not None
    counted = counted_odometry(read_runner_log(session.runner_mcap))
    assert len(counted) >= 0.9 * len(positions), (len(counted), len(positions))
    errors = [math.hypot(ex, ey) for _, ex, ey, _, _ in counted]
    heading_errors = [abs(h - sent) for _, _, _, h, sent in counted]
    print(f"square: {len(counted)} odometry frames in the runner's log, worst {max(errors) * 1e3:.3f} mm from the "
          f"integral of the drives' reported velocities (tolerance {POSE_TOL * 1e3:.2f} mm), heading "
          f"{max(heading_errors) * 1e3:.3f} mrad (tolerance {HEADING_TOL * 1e3:.2f}); end x {final['x']:+.4f} y "
          f"{final['y']:+.4f}; the API's corners {[(round(x, 3), round(y, 3)) for x, y in session.notes['corners']]}; "
          f"state {status.state}")
    assert max(errors) <= POSE_TOL
    assert max(heading_errors) <= HEADING_TOL

    # The corners, and the end after the stop: where the odometry was when the next leg's
    # first TWIST_CMD came (candump), against the square as the robot received it: each leg at
    # its speed (as its whole-rpm targets give it) for the time between the first TWIST_CMDs
    # of two legs, on candump's clock. The drives' motion trails that by each change of
    # velocity dv times its mean delay: the motor's tau and half the acceleration ramp
    # (|dv| / max_linear_accel), which the expected point includes. What is left: the twist
    # taken at the core's next step and the target sent at the next cycle (a control period
    # and a cycle), applied by the peer when its thread takes the RPDO (up to the run's
    # largest SYNC->TPDO1 delay and a switch interval of the interpreter's lock); a common
    # delay cancels but for the last leg's speed, their spread does not (half of it for each
    # change); and a cycle and an odometry period of sampling (the TPDO, the frame before).
    twists = session.decoded(TWIST_CMD, t_enable, t_end)
    starts: list[float] = []
    for vx, vy in [*SQUARE, (0.0, 0.0)]:
        after = starts[-1] if starts else t_enable
        starts.append(first([t for t, v in twists if t > after and (v["vx"], v["vy"]) == (vx, vy)], f"leg {vx}, {vy}"))
    ideal = [0.0, 0.0]
    trail = [0.0, 0.0]
    previous, spread, lines, checks = (0.0, 0.0), 0.0, [], []
    react = CONTROL_PERIOD_S + CYCLE_S + delay + sys.getswitchinterval()
    for (vx, vy), t0, t1 in zip([*SQUARE, (0.0, 0.0)], starts, [*starts[1:], t_end]):
        v = body_velocity([s * round(x) * TARGET_RPM_PER_UNIT * RPM / GEAR for s, x in zip(SIGN, exact_targets(vx, vy, 0.0))])
        ideal = [ideal[0] + v[0] * (t1 - t0), ideal[1] + v[1] * (t1 - t0)]
        dv = (previous[0] - vx, previous[1] - vy)
        mean_delay = tau + math.hypot(*dv) / MAX_LINEAR_ACCEL / 2
        trail = [trail[0] + dv[0] * mean_delay, trail[1] + dv[1] * mean_delay]
        spread += math.hypot(*dv) * react / 2
        speed_k = math.hypot(vx, vy)
        tol_k = speed_k * react + spread + speed_k * (CYCLE_S + ODOMETRY_PERIOD_S)
        want_k = (ideal[0] + trail[0], ideal[1] + trail[1])
        x, y = (lambda p: (p["x"], p["y"]))(session.decoded(ODOM_POSITION, t1=t1)[-1][1])
        err = math.hypot(x - want_k[0], y - want_k[1])
        checks.append((err, tol_k))
        lines.append(f"({x:+.4f}, {y:+.4f}): legs ({ideal[0]:+.4f}, {ideal[1]:+.4f}) less the lag "
                     f"({want_k[0]:+.4f}, {want_k[1]:+.4f}), off by {err * 1e3:.1f} mm (tolerance {tol_k * 1e3:.1f})")
        previous = (vx, vy)
    print(f"square corners and end: {'; '.join(lines)}")
    print(f"square: the peers' SYNC->TPDO1 from the runner's first SYNC on {peer_latency(session, session.of(SYNC)[0].t, t_end)}")
    assert all(err <= tol for err, tol in checks), lines
