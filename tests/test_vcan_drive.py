"""The Python package (python/, `mecanum_drive`) driving the real firmware on a real vcan0.

`mecanum-runner` and `hostsim plant` run as processes (tests/vcan_robot.py starts them, with
candump recording the bus); the host is the package: its `Robot` API in this process, a child
program that is SIGKILLed mid-drive, and `mecanum-drive teleop` in a terminal under tmux. What
the tests check is what crossed the bus (candump's record) and where the plant's chassis
really ended (its ground truth).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import queue
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
from conftest import vcan_unavailable
from vcan_robot import (
    ANSWER_S,
    DJI_CMD_1_4,
    HOST_STALLS,
    LEG_S,
    MISSED_HEARTBEATS,
    MODE_CMD,
    ODOM_POSITION,
    ODOM_VELOCITY,
    ROOT,
    SLOW_CPU,
    SQUARE,
    STOP_BUDGET_S,
    TIMING_SLACK_S,
    TWIST_CMD,
    dji_currents,
    drive_square,
    open_api,
)

pytestmark = pytest.mark.vcan

# The square: SQUARE, each leg for LEG_S (tests/vcan_robot.py).
#: How far the odometry may end from the chassis's true pose. The rollers slip (a strafe
#: makes about 75 % of its commanded travel, which the odometry cannot see), and the emulated
#: machine's runner loses steps to overruns: there the bound is coarse.
END_POS_TOL_M = 0.35 if HOST_STALLS else 0.12
END_HEADING_TOL_RAD = math.radians(15 if HOST_STALLS else 5)
#: How the odometry's corners may differ from the commanded legs (0.6 m each).
CORNER_TOL_M = 0.25 if HOST_STALLS else 0.06
#: How late a key typed through tmux may act: it goes through the tmux server and the pane's
#: terminal to the teleop process, which the emulated machine may stall for a good part of a
#: second when it is busy.
KEY_SLACK_S = 1.5 if SLOW_CPU else 0.2

#: The README's example, as written there.
README = ROOT / "README.md"


def readme_example() -> str:
    """The Python block under "Drive a real robot" in the README."""
    text = README.read_text()
    section = text[text.index("## Drive a real robot") :]
    match = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert match, "the README's Drive a real robot section has no Python example"
    return match.group(1)


def test_a_square_through_the_api_ends_where_the_odometry_says(robot_factory, vcan) -> None:
    """Enable, drive a 0.6 m square leg by leg through `Robot.drive`, stop; leaving the block
    disables the robot. The keep-alive ran at 50 Hz with a counting `seq`, the API's last
    odometry is the robot's last ODOM frames, the odometry's corners are the legs', and the
    chassis ended where the odometry says (within END_POS_TOL_M / END_HEADING_TOL_RAD)."""
    with robot_factory("api-square") as session:
        with open_api(vcan) as robot:
            corners, final = drive_square(robot)
            time.sleep(0.3)
        time.sleep(0.3)
    truth = session.plant_stats["truth"]
    print(f"API square: corners {[(round(x, 3), round(y, 3)) for x, y in corners]}; odometry end "
          f"x {final.x:+.4f} y {final.y:+.4f} heading {final.heading:+.4f}; truth x {truth['x']:+.4f} "
          f"y {truth['y']:+.4f} heading {truth['heading']:+.4f}")

    # The keep-alive: 50 Hz, seq counting up by one.
    twists = session.decoded(TWIST_CMD)
    assert len(twists) > 0.8 * 50 * len(SQUARE) * LEG_S, len(twists)
    seqs = [v["seq"] for _, v in twists]
    assert sum((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:])) == len(seqs) - 1
    gaps = sorted(b - a for (a, _), (b, _) in zip(twists, twists[1:]))
    assert gaps[len(gaps) // 2] == pytest.approx(0.02, abs=0.005), gaps[len(gaps) // 2]

    # The API reports what the robot said (the frames' resolution: 0.1 mm, 0.1 mrad): the
    # ODOM_VELOCITY frame it decoded last is the one candump saw at the same kernel receive
    # time (odometry frames are 10 ms apart), with the ODOM_POSITION sent just before it.
    vel_t, last_vel = min(session.decoded(ODOM_VELOCITY), key=lambda tv: abs(tv[0] - final.stamp))
    assert abs(vel_t - final.stamp) < 0.001, (vel_t, final.stamp)
    last_pos = session.decoded(ODOM_POSITION, t1=vel_t + 1e-6)[-1][1]
    assert (final.x, final.y) == pytest.approx((last_pos["x"], last_pos["y"]), abs=2e-4)
    assert final.heading == pytest.approx(last_vel["heading"], abs=2e-4)
    assert (final.vx, final.vy, final.wz) == pytest.approx(
        (last_vel["vx"], last_vel["vy"], last_vel["wz"]), abs=2e-3)

    # The legs, as the odometry saw them.
    want = [(0.6, 0.0), (0.6, 0.6), (0.0, 0.6), (0.0, 0.0)]
    for (x, y), (wx, wy) in zip(corners, want):
        assert math.hypot(x - wx, y - wy) < CORNER_TOL_M, (corners, want)

    # The chassis is where the odometry says.
    assert math.hypot(final.x - truth["x"], final.y - truth["y"]) < END_POS_TOL_M
    assert abs(math.remainder(final.heading - truth["heading"], math.tau)) < END_HEADING_TOL_RAD

    # Leaving the block: a zero twist, then the disable, and nothing from the host after.
    host = [f for f in session.frames if f.id in (TWIST_CMD, MODE_CMD)]
    zero, disable = host[-2], host[-1]
    assert zero.id == TWIST_CMD and session.db.decode_message(TWIST_CMD, zero.data)["vx"] == 0
    assert disable.id == MODE_CMD and disable.data == bytes([0])


def test_a_program_killed_mid_drive_leaves_the_robot_stopped(robot_factory, vcan, tmp_path) -> None:
    """A program drives forward through the package and is SIGKILLed: nothing can run in it
    any more, so the robot's own watchdog stops it: every motor command is zero within the
    firmware's budget after the program's last TWIST_CMD."""
    program = tmp_path / "driver.py"
    program.write_text(textwrap.dedent(
        f"""
        import time
        import mecanum_drive

        robot = mecanum_drive.Robot.open(
            channel={vcan!r}, interface="socketcan", missed_heartbeats={MISSED_HEARTBEATS}
        )
        robot.enable()
        robot.wait_state("ENABLED", timeout={ANSWER_S})
        robot.drive(0.4, 0.0, 0.0)
        print("driving", flush=True)
        time.sleep(600)
        """
    ))
    with robot_factory("api-kill") as session:
        child = subprocess.Popen([sys.executable, str(program)], stdout=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "driving"
            time.sleep(1.0)
            child.send_signal(signal.SIGKILL)
            killed = time.time()
            child.wait(timeout=10)
        finally:
            if child.poll() is None:
                child.kill()
        time.sleep(0.5)
    last_twist = session.of(TWIST_CMD)[-1]
    assert killed - 0.1 < last_twist.t < killed + 0.05, (killed, last_twist.t)
    moving = [f for f in session.of(DJI_CMD_1_4, t1=last_twist.t) if any(dji_currents(f))]
    assert len(moving) > 100, "the program never drove"
    after = session.of(DJI_CMD_1_4, t0=last_twist.t)
    first_zero = next(f for f in after if not any(dji_currents(f)))
    latency = first_zero.t - last_twist.t
    print(f"killed program: zero currents {latency * 1000:.1f} ms after its last TWIST_CMD "
          f"(budget {STOP_BUDGET_S * 1000:.0f} ms + {TIMING_SLACK_S * 1000:.0f} ms emulation slack)")
    assert latency <= STOP_BUDGET_S + TIMING_SLACK_S
    assert all(not any(dji_currents(f)) for f in after if f.t >= first_zero.t)


class TmuxControl:
    """One control-mode client (`tmux -C`, pane output off) of the tmux server at `socket`:
    commands one a line on its stdin, each answered by a %begin ... %end block on its stdout.

    Every tmux command of the teleop test goes through it: a `tmux` process per command (a
    key, a look at the screen) takes the emulated machine a good part of a second each, so a
    key held at 50 repeats per second would repeat a few times a second, and the looks would
    slow the program they wait for."""

    def __init__(self, tmux: str, socket: str, answer_s: float) -> None:
        self.answer_s = answer_s
        self.proc = subprocess.Popen([tmux, "-S", socket, "-C", "attach-session", "-f", "no-output"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.unanswered = 1  # the attach-session command's own answer comes first
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:  # until the client exits: its stdout never fills
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def send(self, command: str) -> None:
        """Sends `command` without waiting for its answer (`run` checks it later)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        self.unanswered += 1

    def _answer(self) -> list[str]:
        """The next answer's lines; fails on an error answer or on none within answer_s."""
        out: list[str] | None = None
        deadline = time.monotonic() + self.answer_s
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"tmux -C: no answer within {self.answer_s} s") from None
            assert line is not None, f"tmux -C exited ({self.proc.poll()})"
            if out is None:
                if line.startswith("%begin"):
                    out = []
                continue  # a notification between answers
            if line.startswith(("%end", "%error")):
                assert line.startswith("%end"), f"tmux -C: {out}"
                return out
            out.append(line)

    def run(self, command: str) -> list[str]:
        """Sends `command` and returns its output lines, after checking every earlier answer."""
        self.send(command)
        while self.unanswered > 1:
            self._answer()
            self.unanswered -= 1
        self.unanswered = 0
        return self._answer()

    def screen(self) -> str:
        return "\n".join(self.run("capture-pane -p"))

    def hold_key(self, key: str, repeats: int, period_s: float) -> tuple[float, float]:
        """Types `key` `repeats` times, `period_s` apart, as a terminal's auto-repeat does;
        returns the wall times of the first and the last key sent."""
        pressed = time.time()
        for _ in range(repeats):
            self.send(f"send-keys {key}")
            time.sleep(period_s)
        released = time.time()
        self.run("display-message -p keys")  # every key answered, none refused
        return pressed, released

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()  # detaches the client
        self.proc.wait(timeout=30)
        self.reader.join(timeout=30)


def test_teleop_under_tmux_moves_forward_and_stops(robot_factory, vcan, tmp_path) -> None:
    """`mecanum-drive teleop` in a real terminal (tmux): holding `w` (the key repeated, as a
    terminal's auto-repeat does) drives forward; releasing it stops the twist within the
    release time; Esc quits and the robot is disabled."""
    tmux = shutil.which("tmux")
    if tmux is None:
        vcan_unavailable("tmux not installed", "tmux is not installed (scripts/vcan.sh installs it as root)")
    drive = pathlib.Path(sys.executable).with_name("mecanum-drive")
    assert drive.is_file(), f"{drive}: the package is not installed in this environment"
    socket = str(tmp_path / "tmux.sock")

    def tmux_cmd(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([tmux, "-S", socket, *args], capture_output=True, text=True, timeout=30, check=False)

    from mecanum_drive.cli import TELEOP_RELEASE_S

    with robot_factory("teleop") as session:
        started = tmux_cmd("new-session", "-d", "-x", "100", "-y", "30",
                           f"{drive} --channel {vcan} --timeout {ANSWER_S} teleop; sleep 30")
        assert started.returncode == 0, started.stderr
        control = TmuxControl(tmux, socket, 3 * ANSWER_S)
        try:
            deadline = time.monotonic() + 3 * ANSWER_S
            while "state     ENABLED" not in (screen := control.screen()):
                assert time.monotonic() < deadline, f"teleop never showed ENABLED:\n{screen}"
                time.sleep(0.2)
            pressed, released = control.hold_key("w", repeats=60, period_s=0.02)
            time.sleep(1.0)
            screen = control.screen()
            control.run("send-keys Escape")
            deadline = time.monotonic() + ANSWER_S
            while "teleop: stopped" not in (after := control.screen()):
                assert time.monotonic() < deadline, f"teleop did not quit:\n{after}"
                time.sleep(0.2)
        finally:
            control.close()
            tmux_cmd("kill-server")
        time.sleep(0.3)
    print(f"teleop screen while stopped:\n{screen}")
    twists = session.decoded(TWIST_CMD, t0=pressed)
    forward = [t for t, v in twists if v["vx"] > 0]
    assert forward, "holding w did not drive forward"
    assert forward[0] - pressed < KEY_SLACK_S, f"the first w acted {forward[0] - pressed:.3f} s after it was sent"
    assert all(v["vy"] == 0 and v["wz"] == 0 for _, v in twists)
    # Released: the twist is zero within the release time (plus the key delivery's jitter).
    stopped = next(t for t, v in twists if t > released and v["vx"] == 0)
    print(f"teleop: forward {forward[0] - pressed:.3f} s after the first key, zero twist "
          f"{stopped - released:.3f} s after the last (release time {TELEOP_RELEASE_S} s)")
    assert stopped - released < TELEOP_RELEASE_S + KEY_SLACK_S, stopped - released
    assert all(v["vx"] == 0 for t, v in twists if t > stopped)
    # The robot moved forward, and stands.
    pos = session.decoded(ODOM_POSITION)
    x0 = next(v["x"] for t, v in pos if t >= pressed)
    x1 = [v["x"] for t, v in pos if t <= released + 1.0][-1]
    assert x1 - x0 > 0.1, (x0, x1)
    vel = [v["vx"] for t, v in session.decoded(ODOM_VELOCITY) if released + 0.8 < t < released + 1.0]
    assert vel and max(abs(v) for v in vel) < 0.02, vel
    # Quitting disabled the robot.
    assert session.of(MODE_CMD)[-1].data == bytes([0])


def test_the_readme_example_runs_as_written(robot_factory, vcan) -> None:
    """The README's example, unchanged, on vcan0 (its channel comes from CAN_CHANNEL)."""
    example = readme_example()
    with robot_factory("readme") as session:
        proc = subprocess.run([sys.executable, "-c", example], capture_output=True, text=True, timeout=120,
                              env={**os.environ, "CAN_CHANNEL": vcan}, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    print(f"README example printed:\n{proc.stdout}")
    assert session.decoded(TWIST_CMD), "the example sent no twist"
    assert session.of(MODE_CMD)[-1].data == bytes([0])


# --- the bring-up check -------------------------------------------------------------------

WHEEL_TEST_RESULT = 0x314


@pytest.mark.parametrize("protocol, wiring", [("dji", ["--flip", "FR"]), ("odrive", ["--swap", "FL,RL"])])
def test_the_bring_up_check_reports_the_fix_of_a_miswired_robot(
    robot_factory, configs, plant_bin, vcan, protocol, wiring
) -> None:
    """`mecanum-drive check` against `mecanum-runner` and a miswired `hostsim plant --lifted`:
    the firmware runs the four wheel tests (WHEEL_TEST_RESULT DONE each, on the bus), and the
    check prints the fix. The person watching is played by the simulator: `hostsim check`
    with the same plant says which wheel turns which way, and its answers go to --observed."""
    config = configs[protocol]
    sim = subprocess.run([str(plant_bin), "check", "--config", str(config), "--json", *wiring],
                         capture_output=True, text=True, timeout=120, check=False)
    assert sim.returncode == 3, sim.stderr
    report = json.loads(sim.stdout)
    answers = ",".join(f"{w['turned']} {'f' if w['forward'] else 'b'}" for w in report["wheels"])
    with robot_factory(f"check-{protocol}", config=config, plant_args=["--lifted", *wiring]) as session:
        run = subprocess.run(
            [sys.executable, "-m", "mecanum_drive", "--channel", vcan, "--timeout", str(ANSWER_S), "check",
             "--config", str(config), "--observed", answers, "--yes", "--duration", "0.5"],
            capture_output=True, text=True, timeout=120, check=False,
        )
    print(run.stdout)
    assert run.returncode == 3, run.stderr
    for line in report["fix"]:
        assert f"    {line}\n" in run.stdout, (line, run.stdout)
    results = session.of(WHEEL_TEST_RESULT)
    assert [(f.data[0], f.data[1]) for f in results] == [(w, 0) for w in range(4)], results
    # Each tested drive's own encoder turned forward by about 0.5 s x 3 rad/s.
    angles = [int.from_bytes(f.data[2:4], "little", signed=True) / 1000 for f in results]
    assert all(0.8 < a < 1.7 for a in angles), angles
