"""Smoke tests of a real SocketCAN interface (vcan0): python-can and can-utils on the kernel's bus.

Marked `vcan`: without vcan0 they skip ("vcan0 not present (run via scripts/vcan.sh)"), and with
MECANUM_VCAN_REQUIRED=1 (scripts/vcan.sh sets it) a missing vcan0 or can-utils is a failure.
Run them with `scripts/vcan.sh -- .venv/bin/python -m pytest tests -m vcan -q`.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable

import can
import pytest

pytestmark = pytest.mark.vcan

FRAMES = 1000
# Frames sent before the receiver is drained: well below what a default socket receive buffer
# holds (about 200 KiB, some 250 CAN frames), so a slow receiver (software-emulated VM) drops none.
BURST = 100
RECV_TIMEOUT_S = 10.0


def _frame(i: int) -> can.Message:
    """Frame i of the sequence: its index in the identifier and in the first two data bytes."""
    return can.Message(
        arbitration_id=0x100 + (i % 0x400),
        data=[i & 0xFF, i >> 8, 0xA5, 0x5A, 0, 0, 0, i % 251],
        is_extended_id=False,
    )


def _recv(bus: can.BusABC, timeout: float = RECV_TIMEOUT_S) -> can.Message:
    msg = bus.recv(timeout=timeout)
    assert msg is not None, f"no frame within {timeout} s"
    return msg


def test_python_can_1000_frames_in_order(vcan: str) -> None:
    with (
        can.Bus(interface="socketcan", channel=vcan) as rx,
        can.Bus(interface="socketcan", channel=vcan) as tx,
    ):
        received: list[can.Message] = []
        for start in range(0, FRAMES, BURST):
            for i in range(start, min(start + BURST, FRAMES)):
                tx.send(_frame(i), timeout=1.0)
            while len(received) < min(start + BURST, FRAMES):
                received.append(_recv(rx))
        assert rx.recv(timeout=0.2) is None, "more frames than were sent"

    assert len(received) == FRAMES
    for i, msg in enumerate(received):
        want = _frame(i)
        assert (msg.arbitration_id, bytes(msg.data)) == (want.arbitration_id, bytes(want.data)), (
            f"frame {i} out of order or corrupted: {msg}"
        )
        assert not msg.is_extended_id and not msg.is_error_frame and not msg.is_remote_frame
        assert msg.channel == vcan


def test_cansend_seen_by_python_can(vcan: str, can_utils: Callable[[str], str]) -> None:
    cansend = can_utils("cansend")
    with can.Bus(interface="socketcan", channel=vcan) as rx:
        subprocess.run([cansend, vcan, "123#DEADBEEF"], check=True, timeout=30)
        msg = _recv(rx)
    assert msg.arbitration_id == 0x123
    assert not msg.is_extended_id
    assert bytes(msg.data) == bytes.fromhex("DEADBEEF")


def test_python_can_seen_by_candump(vcan: str, can_utils: Callable[[str], str]) -> None:
    candump = can_utils("candump")
    # -n 1: exit after one frame; -L: log-file format, "(time) vcan0 1ABCDEF0#C0FFEE" on stdout.
    proc = subprocess.Popen(
        [candump, "-n", "1", "-L", vcan],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        msg = can.Message(
            arbitration_id=0x1ABCDEF0, data=bytes.fromhex("C0FFEE"), is_extended_id=True
        )
        with can.Bus(interface="socketcan", channel=vcan) as tx:
            # candump may not be listening yet: resend until it has seen one (all frames are equal).
            deadline = time.monotonic() + 30.0
            while proc.poll() is None and time.monotonic() < deadline:
                tx.send(msg, timeout=1.0)
                try:
                    proc.wait(timeout=0.2)
                except subprocess.TimeoutExpired:
                    pass
        assert proc.poll() is not None, "candump saw no frame within 30 s"
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, f"candump failed: {err}"
    fields = out.split()
    assert fields[1:] == [vcan, "1ABCDEF0#C0FFEE"], out
