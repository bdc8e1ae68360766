"""The CiA 402 robot of tests/test_vcan_cia402.py, on a real vcan0, when a node goes away.

The runner is the CANopen master of two simulated drives (tests/cia402_peer.py, nodes 1 and
2; tests/vcan_cia402.py starts and stops them), candump records the bus, and the test is the
host, through the Python package's API. Each session below is one run of the runner:

- a drive's heartbeat lost: FAULT DRIVE_SILENT, quick stop within the consumer time and a
  cycle;
- the runner killed: each drive's heartbeat consumer trips (EMCY 0x8130) within its 0x1016
  time and the drive goes pre-operational (CiA 301's 0x1029 = 0); the runner started again
  resets, configures and starts them, and the robot drives again after the host's reset and
  enable, with no power cycle of the drives;
- a drive rebooted: FAULT DRIVE_REBOOTED, configured again, no motion until the host's reset
  and enable, then driving again.

Times are differences of candump's kernel timestamps, or of the core's step times in the
runner's own log; never this process's clock after the fact.
"""

from __future__ import annotations

import itertools
import math
import struct
import sys
import time
from collections.abc import Callable, Iterator

import pytest
from vcan_cia402 import (
    BOOT_UP,
    CFG,
    CONTROL_PERIOD_S,
    CYCLE_S,
    EMCY_HEARTBEAT,
    ENABLE_OPERATION,
    HEARTBEAT_ID,
    MASTER_NODE,
    NMT_START,
    NODES,
    OPERATION_ENABLED,
    QUICK_STOP,
    RPDO1,
    SDO_REQUEST,
    SDO_RESPONSE,
    SETTLE_S,
    SHUTDOWN,
    STATE_MASK,
    SYNC,
    WHEEL_AXES,
    Cia402Robot,
    ACTUAL_PER_TARGET,
    enable_frame,
    exact_targets,
    first,
    read_runner_log,
    read_runner_steps,
    reset_and_wait_disabled,
    step_lateness,
)
from vcan_robot import (
    ANSWER_S,
    MODE_CMD,
    MODE_RESET,
    ODOM_VELOCITY,
    STATE_DISABLED,
    STATE_ENABLED,
    STATE_FAULT,
    STATUS,
    TIMING_SLACK_S,
    TWIST_CMD,
    open_api,
)

import mecanum_drive

pytestmark = pytest.mark.vcan

# The configuration every session runs (CONFIG, CFG) and the figures of it that both test
# modules use are in tests/vcan_cia402.py; those only this module uses:
HEARTBEAT_S = float(CFG["drive"]["heartbeat_ms"]) / 1000
CONSUMER_S = float(CFG["drive"]["heartbeat_timeout_ms"]) / 1000  # both ways: master and drives

# TIMING_SLACK_S, ANSWER_S and MISSED_HEARTBEATS: the lane's conventions (tests/vcan_robot.py).

#: The peer's heartbeat consumer is a Python timer: the deadline is set when the peer's
#: notifier thread has taken the master's heartbeat off its socket, and checked when its
#: timing thread wakes from `Event.wait`. Each of the two may wait for the interpreter's lock
#: for up to one switch interval (`sys.getswitchinterval()`, 5 ms) while another thread of
#: this process runs: the peer's timer resolution, on top of its 0x1016 time.
PEER_TIMER_RESOLUTION_S = 2 * sys.getswitchinterval()


def drive_forward(api: mecanum_drive.Robot) -> None:
    """From DISABLED: the enable, then forward at 0.3 m/s for a second (the sessions that
    then break something: a drive's heartbeat, the runner, a drive's power)."""
    api.wait_state("DISABLED", timeout=ANSWER_S)
    api.enable()
    api.wait_state("ENABLED", timeout=ANSWER_S)
    api.drive(0.3, 0.0, 0.0)
    time.sleep(1.0)


# --- session 1: a drive's heartbeat lost ---------------------------------------------------

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


# --- session 2: the runner killed ----------------------------------------------------------

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


# --- session 3: a drive rebooted ------------------------------------------------------------

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

