"""The vcan lane's time-outs follow the emulator's measured pace (scripts/vcan-vm.py): a slower
host stretches the guest's fixed work, and the limits with it, so a slow host is not taken for a
hang; a hang still meets a finite limit. Fed with the console lines of a real lane (busy run 3 of
docs/reliability.md's series, whose boot leapt 85 s of guest time in 0.5 s of wall time)."""

from __future__ import annotations

import importlib.util
import pathlib
from types import ModuleType

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def vm() -> ModuleType:
    spec = importlib.util.spec_from_file_location("vcan_vm", ROOT / "scripts" / "vcan-vm.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # its main() runs only as a script
    return module


def feed(console, clock: list[float], lines: list[tuple[float, str]]) -> None:
    for wall, line in lines:
        clock[0] = wall
        console.feed(line.encode() + b"\n")


#: (host wall s since QEMU started, console line), as run 3's lane printed them.
BOOT = [
    (27.66, "vcan-guest: kernel 6.1.0-57-amd64, up after 3.70 s"),
    (28.19, "vcan-guest: vcan0 up, running the command after 89.21 s"),
]
FIRST_TESTS = [
    (62.38, "lane: start [1/85] tests/test_cia402_peer.py::test_configuration_enable_and_velocity (guest 122.3 s)"),
    (66.50, ".lane: end [1/85] passed tests/test_cia402_peer.py::test_configuration_enable_and_velocity in 1.9 s "
            "(guest 124.2 s) cpu 0.5 s, 100 idles: pytest 0.4 s, children 0.0 s"),
    (66.51, "lane: start [2/85] tests/test_cia402_peer.py::test_enable_refused_outside_profile_velocity (guest 124.2 s)"),
]


def test_no_pace_before_the_tests_span_enough_guest_time(vm, tmp_path) -> None:
    clock = [0.0]
    console = vm.Console(tmp_path, 0.0, clock=lambda: clock[0])
    feed(console, clock, BOOT + FIRST_TESTS)
    # 1.9 s of guest time measured: too little to judge the emulator by, and the boot's leap
    # (85 s of guest time in 0.5 s) is not counted at all.
    assert console.pace() is None
    assert console.first == (62.38, 122.3)
    assert console.test_started == 66.51
    console.close()
    assert (tmp_path / "timeline.tsv").read_text().count("\n") == 5


def test_the_pace_is_wall_over_guest_time_from_the_first_test(vm, tmp_path) -> None:
    clock = [0.0]
    console = vm.Console(tmp_path, 0.0, clock=lambda: clock[0])
    feed(console, clock, BOOT + FIRST_TESTS + [
        # Run 3's ROS 2 session: 32.2 s of guest time in 196.2 s of wall time.
        (600.0, "lane: start [47/85] tests/test_vcan_ros2.py::test_enable_service_enables_the_robot (guest 270.0 s)"),
        (796.2, "lane: end [47/85] passed tests/test_vcan_ros2.py::test_enable_service_enables_the_robot in 32.2 s "
                "(guest 302.2 s) cpu 14.2 s, 41844 idles: pytest 5.2 s, children 8.9 s"),
    ])
    assert console.pace() == pytest.approx((796.2 - 62.38) / (302.2 - 122.3), rel=1e-9)
    assert console.test_started is None
    console.close()


def test_limits_grow_with_a_slower_emulator_and_never_shrink(vm) -> None:
    # Set for 3.6 wall s per guest s (scripts/test.sh): 1,530 s for the VM, 390 s a test.
    assert vm.scaled_limits(1530, 390, None, 3.6) == (1530, 390)
    assert vm.scaled_limits(1530, 390, 1.2, 3.6) == (1530, 390)
    assert vm.scaled_limits(1530, 390, 3.6, 3.6) == (1530, 390)
    vm_limit, test_limit = vm.scaled_limits(1530, 390, 5.4, 3.6)
    assert vm_limit == pytest.approx(2295.0) and test_limit == pytest.approx(585.0)
    # 0: fixed limits (scripts/vcan.sh's default), however slow the emulator.
    assert vm.scaled_limits(1530, 390, 50.0, 0.0) == (1530, 390)
    # No per-test limit stays none.
    assert vm.scaled_limits(1530, 0, 7.2, 3.6) == (pytest.approx(3060.0), 0)
