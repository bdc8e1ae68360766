"""The vcan lane's own pytest hooks (conftest.py registers them): progress, and the guest's
state when something fails. Active only where scripts/vcan.sh runs the tests
(MECANUM_VCAN_MODE set); elsewhere every hook returns at once.

Progress: one `lane: start [n/N] NODEID (guest T s)` line as a test starts and one
`lane: end [n/N] OUTCOME NODEID in S s (guest T s) cpu B s, I idles: pytest P s, children C s`
as it ends, S being the test's setup, call and teardown, B the time the machine's CPUs ran
tasks during it and I how often they went idle (the guest's clock jumps over idle time, but
each wake-up costs the host), P this process's CPU time and C that of the children it reaped
meanwhile (the programs under test, candump, `mecanum-drive`). In the micro-VM these are guest times (the guest's clock counts its executed
instructions, and jumps to its next timer while every guest process waits, also on the host:
scripts/vcan.sh --help); scripts/vcan-vm.py stamps each line with the host's wall time as well
(target/vcan-lane/timeline.tsv), and scripts/lane-times.py sets the two side by side.

A test's budget is kept by the host, in wall time (scripts/vcan-vm.py --test-timeout), not here:
while every guest process waits on the host, the guest's clock jumps to its next timer, and a
budget timer of the guest's own would be that timer.

A failed test in the VM carries the guest's blocked tasks and the kernel log's tail in its
report (the `guest` section): where a guest command overran, what it waited on.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time

import pytest

IN_LANE = bool(os.environ.get("MECANUM_VCAN_MODE"))
IN_VM = os.environ.get("MECANUM_VCAN_MODE") == "vm"
_state: dict[str, object] = {"n": 0, "total": 0, "started": 0.0, "config": None, "cpu": (0.0, 0.0, 0.0, 0.0)}


def guest_state(lines: int = 80) -> str:
    """The guest's blocked tasks (SysRq w, into the kernel log) and the log's last `lines`
    lines; empty outside the VM."""
    if not IN_VM:
        return ""
    try:
        with open("/proc/sysrq-trigger", "w") as trigger:
            trigger.write("w")
    except OSError as err:
        return f"(SysRq w: {err})"
    try:
        out = subprocess.run(["dmesg"], capture_output=True, text=True, timeout=30, check=False).stdout
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"(dmesg: {err})"
    return "\n".join(out.splitlines()[-lines:])


def _say(line: str) -> None:
    config = _state["config"]
    reporter = config.pluginmanager.get_plugin("terminalreporter") if isinstance(config, pytest.Config) else None
    if reporter is not None:
        reporter.ensure_newline()
        reporter.write_line(line)
    else:
        print(line, flush=True)
    sys.stdout.flush()


def pytest_collection_finish(session: pytest.Session) -> None:
    _state["total"] = len(session.items)  # after -m and -k deselected theirs


def pytest_runtest_logstart(nodeid: str, location: object) -> None:
    if not IN_LANE:
        return
    _state["n"] = int(_state["n"]) + 1  # type: ignore[call-overload]
    _state["started"] = time.monotonic()
    _state["cpu"] = _cpu()
    _say(f"lane: start [{_state['n']}/{_state['total']}] {nodeid} (guest {_uptime()} s)")


def pytest_runtest_logfinish(nodeid: str, location: object) -> None:
    if not IN_LANE:
        return
    took = time.monotonic() - float(_state["started"])  # type: ignore[arg-type]
    outcome = _OUTCOMES.pop(nodeid, "passed")
    busy, idles, own, children = (b - a for a, b in zip(_state["cpu"], _cpu()))  # type: ignore[call-overload]
    _say(f"lane: end [{_state['n']}/{_state['total']}] {outcome} {nodeid} in {took:.1f} s (guest {_uptime()} s) "
         f"cpu {busy:.1f} s, {idles:.0f} idles: pytest {own:.1f} s, children {children:.1f} s")


_OUTCOMES: dict[str, str] = {}


def pytest_configure(config: pytest.Config) -> None:
    _state["config"] = config


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    outcome = yield
    report = outcome.get_result()
    if not IN_LANE:
        return
    if report.failed:
        _OUTCOMES[item.nodeid] = "FAILED" if report.when == "call" else f"ERROR ({report.when})"
        state = guest_state()
        if state:
            report.sections.append(("guest: blocked tasks and kernel log", state))
    elif report.skipped and item.nodeid not in _OUTCOMES:
        _OUTCOMES[item.nodeid] = "skipped"


def _cpu() -> tuple[float, float, float, float]:
    """(seconds the machine's CPUs ran tasks, times they went idle, this process's CPU seconds,
    its reaped children's), for deltas. The first two are the scheduler's own counts
    (/proc/schedstat), not /proc/stat's ticks, which sample bursts of microseconds badly; an
    emulated CPU's every wake-up from idle costs the host tens of microseconds."""
    times = os.times()
    busy = idles = float("nan")
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/schedstat") as f:
            cpus = [line.split() for line in f if line.startswith("cpu")]
        busy = sum(int(c[7]) for c in cpus) / 1e9
        idles = sum(int(c[4]) for c in cpus)
    return busy, idles, times.user + times.system, times.children_user + times.children_system


def _uptime() -> str:
    """The guest's (or the machine's) uptime, the lane's common clock, as `123.4`."""
    try:
        with open("/proc/uptime") as f:
            return f"{float(f.read().split()[0]):.1f}"
    except (OSError, ValueError):
        return "?"
