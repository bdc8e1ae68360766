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
- a drive fault: the runner's report names the drive issue and counts the EMCY frames;
- the package's square on this robot (issue item 7: the host package needs no change).

A drive's heartbeat lost, the runner killed, a drive rebooted: tests/test_vcan_cia402_outages.py.

Every time measured is a difference of candump's kernel timestamps (one clock), or of the
core's step times in the runner's own log; never this process's clock after the fact.
`Robot.marks` (wall times) only find the phases of a session.
"""

from __future__ import annotations

import bisect
import itertools
import math
import struct
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import cantools
import pytest
from vcan_cia402 import (
    CFG,
    CONTROL_PERIOD_S,
    CYCLE_S,
    ENABLE_OPERATION,
    GEAR,
    LX,
    LY,
    NODES,
    OPERATION_ENABLED,
    QUICK_STOP,
    RADIUS,
    READY_TO_SWITCH_ON,
    RPM,
    SETTLE_S,
    SHUTDOWN,
    SIGN,
    STATE_MASK,
    SWITCH_ON,
    SWITCHED_ON,
    SYNC,
    TARGET_RPM_PER_UNIT,
    TPDO1,
    TPDO2,
    WHEEL_AXES,
    Cia402Robot,
    LogFrame,
    ACTUAL_PER_TARGET,
    before,
    enable_frame,
    exact_targets,
    first,
    read_runner_log,
    reset_and_wait_disabled,
)
from vcan_robot import (
    ANSWER_S,
    ESTOP,
    MODE_CMD,
    MODE_RESET,
    MOTIONS,
    ODOM_POSITION,
    ODOM_VELOCITY,
    ROOT,
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

pytestmark = pytest.mark.vcan

# The configuration every session runs (CONFIG, CFG) and the figures of it that both test
# modules use are in tests/vcan_cia402.py; those only this module uses:
ODOMETRY_PERIOD_S = 1.0 / float(CFG["timing"]["odometry_hz"])
ACTUAL_RPM_PER_UNIT = float(CFG["drive"]["actual_rpm_per_unit"])
MAX_LINEAR_ACCEL = float(CFG["limits"]["max_linear_accel"])

# TIMING_SLACK_S, ANSWER_S and MISSED_HEARTBEATS: the lane's conventions (tests/vcan_robot.py).

#: ODOM_POSITION against the integral of the drives' reported velocities (`counted_odometry`):
#: half the frame's 0.1 mm, and 0.05 mm for the core's f32 (its wheel speeds and increments;
#: its sums are compensated). ODOM_VELOCITY.heading: half its 0.1 mrad, and 0.01 mrad.
POSE_TOL = 0.00005 + 0.00005
HEADING_TOL = 0.00005 + 0.00001

#: Each twist of MOTIONS (tests/vcan_robot.py) is held for PHASE_S; the first is set before
#: the enable.
PHASE_S = 1.5
#: ODOM_VELOCITY against the forward kinematics of the velocities the drives reported: the
#: frame's resolution (0.001 m/s, rad/s: half of it) and the core's f32 arithmetic (relative
#: 1e-6 of speeds below 2 m/s: 2e-6), nothing else: the core's measured velocity is the
#: forward kinematics of the last TPDO of each wheel, and nothing filters it.
ODOM_TOL = 0.0005 + 2e-6


# --- the kinematics of the configuration (docs: kinematics::MecanumKinematics::standard) ----
# The inverse (wheel_speeds, exact_targets): tests/vcan_cia402.py.

def body_velocity(w: list[float]) -> tuple[float, float, float]:
    """The forward kinematics (least squares, exact for the standard layout)."""
    fl, fr, rl, rr = w
    return (RADIUS / 4 * (fl + fr + rl + rr), RADIUS / 4 * (-fl + fr + rl - rr),
            RADIUS / (4 * (LX + LY)) * (-fl + fr - rl + rr))


def actual_to_wheel(raw: int, wheel: int) -> float:
    """A 0x606C value of `wheel` as the core reads it: rad/s, robot-forward positive."""
    return SIGN[wheel] * raw * ACTUAL_RPM_PER_UNIT * RPM / GEAR


# --- helpers ---------------------------------------------------------------------------------

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


# --- session 2: the package's square (issue item 7) -------------------------------------------

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
