"""`hostsim run --live`: the run served over the Foxglove WebSocket protocol while it goes.

A client that speaks the protocol (tests/foxglove_client.py) against the simulator, with the
run's own MCAP log as the oracle: the handshake on `foxglove.sdk.v1`; every channel of the
log advertised with its schema; after a subscription, the messages equal, byte for byte, the
log's messages of the same channel and log time; a client that stops reading neither slows
the run nor goes unnoticed (its losses are counted, at the end and on /diagnostics); Ctrl-C
ends the run with the log finished and the port closed. docs/live.md is the user's side.

The runs are short (the built-in square, 9.1 s simulated, at 4x real time: 2.3 s) and bind a
free port on 127.0.0.1 only.
"""

from __future__ import annotations

import json
import pathlib
import re
import signal
import socket
import struct
import subprocess
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any
from urllib.parse import urlparse

import pytest
from foxglove_client import SUBPROTOCOL, FoxgloveClient, MessageData, StalledClient
from mcap.reader import make_reader
from mecanum_drive import params as robot_params
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from vcan_robot import binary

ROOT = pathlib.Path(__file__).resolve().parent.parent
LIVE_LINE = re.compile(r"^live: (ws://\S+) \((\S+)\)")
RATE = 4.0


class LiveRun:
    """`hostsim run SCENARIO --live 127.0.0.1:0 --json` in the background, its address read
    from the line it prints on stderr before the run starts."""

    def __init__(self, hostsim_bin: pathlib.Path, out: pathlib.Path, scenario: str, *args: str) -> None:
        self.out = out
        self.proc = subprocess.Popen(
            [str(hostsim_bin), "run", scenario, "--live", "127.0.0.1:0", "--out", str(out), "--no-plot",
             "--json", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stderr is not None
        self.head: list[str] = []
        for line in self.proc.stderr:
            self.head.append(line)
            m = LIVE_LINE.match(line)
            if m:
                self.url, self.subprotocol = m.group(1), m.group(2)
                return
        self.proc.wait(timeout=10)
        pytest.fail(f"no `live:` line; exit {self.proc.returncode}: {''.join(self.head)}")

    def finish(self, timeout: float = 60.0) -> tuple[int, dict[str, Any], str]:
        """Waits for the end: the exit status, the JSON summary, the rest of stderr."""
        out, err = self.proc.communicate(timeout=timeout)
        stderr = "".join(self.head) + err
        assert out.strip(), f"no summary; exit {self.proc.returncode}: {stderr}"
        return self.proc.returncode, json.loads(out), stderr

    @property
    def port(self) -> int:
        port = urlparse(self.url).port
        assert port is not None
        return port


def read_log(path: pathlib.Path) -> tuple[dict[str, Any], dict[tuple[str, int], list[bytes]], dict[str, list[int]]]:
    """The log's channels (topic -> channel and schema), its messages by (topic, log time),
    and each topic's log times in file order."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None, f"{path} has no summary: not finished"
        channels = {c.topic: (c, summary.schemas[c.schema_id]) for c in summary.channels.values()}
        by_key: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        times: dict[str, list[int]] = defaultdict(list)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            by_key[(channel.topic, message.log_time)].append(message.data)
            times[channel.topic].append(message.log_time)
    return channels, by_key, times


def live_status(mcap: pathlib.Path) -> dict[str, str]:
    """The values of the live server's status in the log's last /diagnostics."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    last = None
    with open(mcap, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/diagnostics"]):
            last = message.data
    assert last is not None
    d = store.deserialize_cdr(last, "diagnostic_msgs/msg/DiagnosticArray")
    status = {s.name: s for s in d.status}
    assert "mecanum_drive: firmware" == d.status[0].name
    return {kv.key: kv.value for kv in status["mecanum_drive: live"].values}


@pytest.fixture(scope="module")
def without_client(hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A live run nobody watches: the pace of reference."""
    run = LiveRun(hostsim_bin, tmp_path_factory.mktemp("alone"), "square", "--rate", str(RATE))
    code, summary, stderr = run.finish()
    assert code == 0, stderr
    return summary


def test_a_subscriber_gets_the_logs_channels_and_bytes_at_their_log_times(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path) -> None:
    run = LiveRun(hostsim_bin, tmp_path, "square", "--rate", str(RATE))
    assert run.subprotocol == SUBPROTOCOL
    client = FoxgloveClient(run.url)
    assert client.subprotocol == SUBPROTOCOL
    client.start()
    assert client.server_info["name"] == "hostsim run square"
    topics = ["/odom", "/joint_states", "/diagnostics", "/tf", "/can/rx"]
    client.subscribe(topics)
    received = client.read_until_closed()
    client.close()
    code, summary, stderr = run.finish()
    assert code == 0, stderr
    assert summary["live"]["dropped"] == 0, summary["live"]
    assert summary["live"]["clients"][0]["subprotocol"] == SUBPROTOCOL

    channels, by_key, times = read_log(tmp_path / "square.mcap")
    # Every channel of the log, advertised as the log has it: id, topic, encoding, schema.
    advertised = {c["topic"]: c for c in client.channels.values()}
    assert set(advertised) == set(channels)
    for topic, (channel, schema) in channels.items():
        a = advertised[topic]
        assert a["id"] == channel.id, topic
        assert a["encoding"] == channel.message_encoding == "cdr", topic
        assert a["schemaName"] == schema.name, topic
        assert a["schemaEncoding"] == schema.encoding == "ros2msg", topic
        assert a["schema"] == schema.data.decode(), topic

    # Every message received is the log's, byte for byte, at the same log time.
    got: dict[str, list[MessageData]] = defaultdict(list)
    for topic, m, _ in received:
        assert m.data in by_key[(topic, m.log_time)], f"{topic} at {m.log_time} ns is not the log's"
        got[topic].append(m)
    # From its first message on, each channel but CAN arrives whole and in order (the client
    # connects while the run goes: it misses the start).
    for topic in ["/odom", "/joint_states", "/diagnostics", "/tf"]:
        log_times = [m.log_time for m in got[topic]]
        assert log_times, topic
        expected = [t for t in times[topic] if t >= log_times[0]]
        assert log_times == expected, topic
        assert log_times[0] < 1.5e9 * RATE, f"{topic} from {log_times[0] * 1e-9:.2f} s on"
    # /can/rx is thinned: each CAN id 100 frames a second of log time on average, a frame up to
    # half a period (5 ms) early taken (docs/live.md): in a span, at most 100 a second plus 1.5.
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(channels["/can/rx"][1].data.decode(), "can_msgs/msg/Frame"))
    per_id: dict[int, list[int]] = defaultdict(list)
    for m in got["/can/rx"]:
        per_id[store.deserialize_cdr(m.data, "can_msgs/msg/Frame").id].append(m.log_time)
    assert len(per_id) >= 4, sorted(per_id)
    for can_id, log_times in per_id.items():
        span_s = (log_times[-1] - log_times[0]) * 1e-9
        assert len(log_times) <= 100 * span_s + 1.5, f"{can_id:#x}: {len(log_times)} in {span_s:.2f} s"
    assert len(times["/can/rx"]) > 3 * len(got["/can/rx"]), "the log keeps every frame"
    assert summary["live"]["thinned"] > 0


def test_a_client_sets_a_parameter_and_the_log_has_the_request_at_the_step_it_was_applied(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path, run_codec: Callable[..., list[dict]]) -> None:
    """What Lichtblick's Parameters panel does, against the simulated robot: every parameter
    read; gains.kp set while the square drives, answered with the value in force; a refused
    value answered with the old one and a status naming the parameter, the value and the rule.
    The request is a frame the robot received (/can/rx) and its change a /rosout line at that
    step (docs/live.md, "Parameters")."""
    run = LiveRun(hostsim_bin, tmp_path, "square", "--rate", "1")
    client = FoxgloveClient(run.url)
    client.start()
    assert client.server_info["capabilities"] == ["parameters"], client.server_info
    values, statuses = client.parameters("getParameters", "all", parameterNames=[])
    assert statuses == [] and values["gains.kp"] == 1.2 and values["drive.protocol"] == 0, values
    # Every parameter the square's configuration (the built-in DJI one) has, as the table says.
    table = [p for p in run_codec("params", "--config", str(ROOT / "config" / "dji_m3508.toml"))
             if p["value"] is not None]
    assert list(values) == [p["name"] for p in table]
    for p in table:
        assert values[p["name"]] == pytest.approx(p["value"], rel=1e-7), p
    values, statuses = client.parameters(
        "setParameters", "set", parameters=[{"name": "gains.kp", "value": 1.5}, {"name": "gains.kp", "value": 1000}])
    assert values == {"gains.kp": 1.5}, values
    assert [s["level"] for s in statuses] == [2], statuses
    high = robot_params.table()["gains.kp"].high
    assert statuses[0]["message"] == (
        f"gains.kp = 1000: above {high:g} (SDO abort 0x06090031); the value in force is kept"), statuses
    client.close()
    code, summary, stderr = run.finish()
    assert code == 0, stderr
    assert summary["live"]["clients"][0]["cut_off"] is None, summary["live"]

    rosout, requests = [], []
    with AnyReader([tmp_path / "square.mcap"], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for c, t, raw in reader.messages():
            if c.topic == "/rosout":
                rosout.append((t, reader.deserialize(raw, c.msgtype).msg))
            elif c.topic == "/can/rx":
                f = reader.deserialize(raw, c.msgtype)
                if f.id == 0x67F and bytes(f.data[:4]) == bytes([0x23, 0x02, 0x20, 0x01]):
                    requests.append((t, struct.unpack_from("<f", bytes(f.data), 4)[0]))
    changes = [(t, m) for t, m in rosout if m.startswith("gains.kp ")]
    assert len(changes) == 1 and changes[0][1].startswith("gains.kp 1.2 -> 1.5, config 0x"), rosout
    # Both writes reached the robot; the first changed gains.kp at the step that took it (the
    # request delivered up to a period before).
    assert [v for _, v in requests] == [1.5, 1000.0], requests
    assert 0 <= changes[0][0] - requests[0][0] <= 1_000_000, (changes, requests)


def test_a_client_that_stops_reading_loses_counted_messages_and_slows_nothing(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path, without_client: dict[str, Any]) -> None:
    run = LiveRun(hostsim_bin, tmp_path, "square", "--rate", str(RATE))
    stalled = StalledClient(run.url)
    try:
        code, summary, stderr = run.finish()
    finally:
        stalled.close()
    assert code == 0, stderr
    # The run's own clock: as fast as without a client, on the wall clock at 4x.
    assert summary["wall_s"] <= 1.2 * without_client["wall_s"], (summary["wall_s"], without_client["wall_s"])
    assert summary["live"]["late_p99_s"] < 0.05, summary["live"]
    # Its losses are counted: at the end, and on /diagnostics during the run (in the log).
    client = summary["live"]["clients"][0]
    assert client["dropped"] > 1000, client
    assert client["queued"] == client["sent"] + client["dropped"], client
    assert "dropped for slow clients" in stderr
    status = live_status(tmp_path / "square.mcap")
    assert int(status["dropped"]) > 0, status
    assert status["clients"] == "1", status


def test_ctrl_c_ends_the_run_with_the_log_finished_and_the_port_closed(
        hostsim_bin: pathlib.Path, tmp_path: pathlib.Path) -> None:
    run = LiveRun(hostsim_bin, tmp_path, str(ROOT / "scenarios" / "square_60s.toml"))
    client = FoxgloveClient(run.url)
    client.start()
    client.subscribe(["/odom"])
    # Half a second of the run, watched at real time.
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        m = client.recv(timeout=5)
        if isinstance(m, MessageData) and m.log_time >= 500_000_000:
            break
    run.proc.send_signal(signal.SIGINT)
    code, summary, stderr = run.finish(timeout=10)
    assert code == 130, stderr
    assert summary["interrupted"] is True
    assert summary["duration_s"] < 10, summary["duration_s"]
    assert "INTERRUPTED" in stderr
    # The server closed the connection, and the port.
    client.read_until_closed(timeout=5)
    client.close()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", run.port), timeout=5)
    # The log is finished (its summary written) and holds the run up to the signal.
    _, _, times = read_log(tmp_path / "square-60s.mcap")
    assert 0.5e9 <= times["/odom"][-1] <= summary["duration_s"] * 1e9


def test_the_command_line_refuses_what_cannot_be_served(hostsim_bin: pathlib.Path, tmp_path: pathlib.Path) -> None:
    def refused(*args: str) -> str:
        proc = subprocess.run([str(hostsim_bin), "run", "square", "--out", str(tmp_path), *args],
                              capture_output=True, text=True, timeout=60, check=False)
        assert proc.returncode == 2, proc.stderr
        return proc.stderr

    assert "--live" in refused("--rate", "2")
    assert "--no-log" in refused("--live", "0", "--no-log")
    assert "--rate" in refused("--live", "0", "--rate", "0")
    assert "--rate" in refused("--live", "0", "--rate", "nan")
    assert "--live" in refused("--live", "not-an-address")
    # Without --live nothing changes: no server, no pacing, no `live:` line.
    proc = subprocess.run([str(hostsim_bin), "run", "square", "--out", str(tmp_path), "--no-plot", "--json"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0 and "live" not in proc.stderr and "live" not in json.loads(proc.stdout)


def test_the_plant_and_the_runner_refuse_live_without_a_log(hostsim_bin: pathlib.Path) -> None:
    """--live serves the log as it is written: without --log there is nothing to serve, and
    both programs say so before they touch the interface (exit 2, the startup error)."""
    runner = binary("MECANUM_RUNNER", ROOT / "target" / "release" / "mecanum-runner")
    for cmd in ([str(runner), "--iface", "vcan-none"], [str(hostsim_bin), "plant", "--iface", "vcan-none"]):
        proc = subprocess.run([*cmd, "--live", "0"], capture_output=True, text=True, timeout=60, check=False)
        assert proc.returncode == 2, (cmd, proc.stderr)
        assert "--live" in proc.stderr and "--log FILE" in proc.stderr, proc.stderr
        proc = subprocess.run([*cmd, "--live-can-hz", "10"], capture_output=True, text=True, timeout=60, check=False)
        assert proc.returncode == 2 and "--live" in proc.stderr, (cmd, proc.stderr)
