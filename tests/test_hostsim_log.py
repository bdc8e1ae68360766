"""The simulator's MCAP logs, read with the format's own Python reader, and its CLI.

The logs are ROS 2 bags (crates/drivelog/src/lib.rs, "Channels"): profile `ros2`, schemas
`ros2msg` (the `.msg` text with its dependencies, as rosbag2 writes them), messages in CDR.
Here the `mcap` package reads the records and `rosbags` decodes the CDR, with the ROS 2 Humble
definitions of the standard types and the file's own schema text for the rest
(can_msgs/msg/Frame, mecanum_drive_msgs/msg/BusFault), as a tool that knows neither would.
tests/test_ros2_logs.py reads whole logs with rosbags' own bag reader.
"""

from __future__ import annotations

import json
import math
import pathlib
import subprocess

import cantools
import pytest
from mcap.reader import make_reader
from mcap.records import Message, Statistics
from mcap.stream_reader import StreamReader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from test_ros2_logs import CHANNEL_TYPES

ROOT = pathlib.Path(__file__).resolve().parent.parent


def typestore_for(schemas):
    """The ROS 2 Humble type store, plus the types of `schemas` (the summary's Schema records)
    that it lacks, parsed from their `ros2msg` text: the dependency sections included, so
    can_msgs/msg/Frame comes with the file."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    for schema in schemas:
        types = get_types_from_msg(schema.data.decode(), schema.name)
        store.register({name: fields for name, fields in types.items() if name not in store.fielddefs})
    return store


def run_hostsim(binary: pathlib.Path, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(binary), *args], input=stdin, capture_output=True, text=True, timeout=600, check=False
    )


@pytest.fixture(scope="module")
def circle_run(hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, dict]:
    out = tmp_path_factory.mktemp("circle")
    proc = run_hostsim(hostsim_bin, "run", "circle", "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr
    return out, json.loads(proc.stdout)


def test_every_message_reads_back_with_the_python_mcap_reader(circle_run, dbs) -> None:
    out, summary = circle_run
    counts: dict[str, int] = {}
    tx_ids: set[int] = set()
    joint_states = []
    with open(out / "circle.mcap", "rb") as f:
        # Every chunk's CRC checked; messages found through the summary's chunk indexes.
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        file_summary = reader.get_summary()
        stats = file_summary.statistics
        channel_topics = {c.id: c.topic for c in file_summary.channels.values()}
        store = typestore_for(file_summary.schemas.values())
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            decoded = store.deserialize_cdr(message.data, schema.name)
            if channel.topic in ("/can/rx", "/can/tx"):
                assert 0 <= decoded.dlc <= 8 and len(decoded.data) == 8, decoded
                assert not (decoded.is_rtr or decoded.is_extended or decoded.is_error), decoded
                # The stamp: when the frame completed on the wire. The firmware takes a
                # received frame then or later (a delay fault); a sent frame is logged then,
                # after the control step that sent it (its publish time).
                stamp = decoded.header.stamp.sec * 1_000_000_000 + decoded.header.stamp.nanosec
                assert stamp <= message.log_time, (stamp, message)
                if channel.topic == "/can/tx":
                    assert stamp == message.log_time and message.publish_time <= stamp, (stamp, message)
                    tx_ids.add(decoded.id)
            if channel.topic == "/joint_states":
                joint_states.append(decoded)
    # The ROS 2 bag conventions: rosbag2's profile, .msg schemas, CDR messages.
    assert header.profile == "ros2"
    assert {
        c.topic: (file_summary.schemas[c.schema_id].name, file_summary.schemas[c.schema_id].encoding)
        for c in file_summary.channels.values()
    } == {topic: (name, "ros2msg") for topic, name in CHANNEL_TYPES.items()}
    assert {c.message_encoding for c in file_summary.channels.values()} == {"cdr"}
    # The Statistics record agrees with what is in the file.
    assert stats.message_count == sum(counts.values())
    assert {channel_topics[i]: n for i, n in stats.channel_message_counts.items() if n} == counts
    assert stats.chunk_count >= 1 and stats.metadata_count == 1
    # Counts agree with what the simulator reports.
    assert counts["/can/tx"] == summary["tx_frames"]
    assert counts["/can/rx"] == summary["rx_frames"]
    for topic in ("/joint_states", "/diagnostics", "/odom", "/ground_truth/odom"):
        assert counts[topic] == (summary["steps"] + 9) // 10, topic  # every 10th step
    assert counts["/tf"] == 2 * counts["/odom"]  # odometry and ground truth
    # The configuration travels with the log.
    assert "config" in meta["mecanum_drive"] and meta["mecanum_drive"]["scenario"] == "circle"
    # The firmware sent DJI current commands and the robot's telemetry, all in the DBC files.
    assert {0x200, 0x310, 0x311, 0x312, 0x31F} <= tx_ids
    known = {m.frame_id for db in dbs.values() for m in db.messages}
    assert tx_ids <= known
    # The wheels (what /motors/feedback used to carry): four named joints, finite numbers,
    # and a circle's worth of turning by the end (6.3 m of travel on 76 mm wheels is 83 rad
    # on average; 1 rad is a wheel that certainly turned).
    for state in joint_states:
        assert list(state.name) == ["fl", "fr", "rl", "rr"], state
        for values in (state.position, state.velocity, state.effort):
            assert len(values) == 4 and all(math.isfinite(v) for v in values), state
    assert all(abs(p) > 1.0 for p in joint_states[-1].position), joint_states[-1]


def test_messages_are_in_time_order_in_the_file(circle_run) -> None:
    """A streaming reader (file order, no index) sees log time never step back. The circle
    changes its twist between control steps (at 12.666371 s), the case that used to; and
    /can/tx is logged at the end of each frame on the wire, up to 2 ms after the control
    step that sent it, which the writer must not let fall behind the later steps' messages."""
    out, summary = circle_run
    back, last, count, stats = 0, 0, 0, None
    with open(out / "circle.mcap", "rb") as f:
        for record in StreamReader(f, skip_magic=False, emit_chunks=False).records:
            if isinstance(record, Message):
                count += 1
                back += record.log_time < last
                last = max(last, record.log_time)
            elif isinstance(record, Statistics):
                stats = record
    # Every message was seen (the frames alone are over 70,000), and the last one is the end
    # of the run: the last frames of its last step completing on the wire.
    assert stats is not None and count == stats.message_count
    assert count > summary["tx_frames"] + summary["rx_frames"] > 70_000
    assert last == pytest.approx(summary["duration_s"] * 1e9, abs=2e6)
    assert back == 0, f"{back} messages earlier than one before them in the file"


def test_the_plot_is_a_png(circle_run) -> None:
    out, _ = circle_run
    data = (out / "circle.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert (width, height) == (1200, 600)


def test_circle_closes(circle_run) -> None:
    _, summary = circle_run
    # One full turn of a 1 m radius circle (0.5 m/s, 0.5 rad/s), then a stop: back near the
    # start. Turning spins the rollers, so the wheels slip a little: odometry stays within
    # 2 % of the 6.3 m travelled.
    x, y, _ = summary["truth"]
    assert (x**2 + y**2) ** 0.5 < 0.1, summary["truth"]
    assert summary["final_position_error"] < 0.12, summary


def test_odometry_frames_decode_with_the_dbc(circle_run, dbs) -> None:
    out, summary = circle_run
    db = dbs["robot"]
    last = {}
    headings = []
    with open(out / "circle.mcap", "rb") as f:
        reader = make_reader(f)
        store = typestore_for(reader.get_summary().schemas.values())
        for _, _, message in reader.iter_messages(topics=["/can/tx"]):
            frame = store.deserialize_cdr(message.data, "can_msgs/msg/Frame")
            if frame.id in (0x310, 0x311):
                msg = db.get_message_by_frame_id(frame.id)
                last[frame.id] = msg.decode(bytes(frame.data[: frame.dlc]))
                if frame.id == 0x311:
                    headings.append(last[0x311]["heading"])
    x, y, heading = summary["odometry"]
    assert last[0x310]["x"] == pytest.approx(x, abs=2e-3)
    assert last[0x310]["y"] == pytest.approx(y, abs=2e-3)
    # The heading field: 0.1 mrad resolution, wrapped to +-pi.
    assert last[0x311]["heading"] == pytest.approx(heading, abs=2e-4)
    # One turn counter-clockwise (yaw positive): the unwrapped heading rises by 2 pi, less a
    # little roller slip, and never falls by more than the resolution from frame to frame.
    steps = [(b - a + math.pi) % (2 * math.pi) - math.pi for a, b in zip(headings, headings[1:])]
    assert min(steps) > -2e-4, min(steps)
    assert sum(steps) == pytest.approx(2 * math.pi, abs=0.15), sum(steps)


def test_replay_of_the_log_is_bit_identical(hostsim_bin, circle_run) -> None:
    out, _ = circle_run
    proc = run_hostsim(hostsim_bin, "replay", str(out / "circle.mcap"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "bit-identical" in proc.stdout


def test_kin_calculator_answers_each_line(hostsim_bin) -> None:
    lines = [
        {"op": "inverse", "lx": 0.1, "ly": 0.075, "r": 0.03, "vx": 0.22, "vy": 0.11, "wz": 0},
        # With rotation, k = lx + ly: FL (vx - vy - k wz) / r, FR (vx + vy + k wz) / r,
        # RL (vx + vy - k wz) / r, RR (vx - vy + k wz) / r.
        {"op": "inverse", "lx": 0.1, "ly": 0.075, "r": 0.03, "vx": 0.22, "vy": 0.11, "wz": 0.4},
        "garbage",
        {"op": "forward", "lx": 0.2, "ly": 0.15, "r": 0.05, "fl": 20, "fr": 20, "rl": 20, "rr": 20},
    ]
    stdin = "".join((json.dumps(x) if isinstance(x, dict) else x) + "\n" for x in lines)
    proc = run_hostsim(hostsim_bin, "kin", stdin=stdin)
    assert proc.returncode == 0, proc.stderr
    out = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(out) == 4
    # The documentation page's worked example (crates/kinematics/README.md, References).
    assert out[0] == pytest.approx({"fl": 11 / 3, "fr": 11.0, "rl": 11.0, "rr": 11 / 3}, abs=1e-9)
    assert out[1] == pytest.approx({"fl": 4 / 3, "fr": 40 / 3, "rl": 26 / 3, "rr": 6.0}, abs=1e-9)
    assert "error" in out[2]
    assert out[3] == pytest.approx({"vx": 1.0, "vy": 0.0, "wz": 0.0}, abs=1e-12)


def test_bad_inputs_give_clear_errors(hostsim_bin, tmp_path) -> None:
    proc = run_hostsim(hostsim_bin, "run", "no-such-builtin")
    assert proc.returncode == 2 and "square" in proc.stderr, proc.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("duration_s = 1.0\n[[faults]]\nkind = \"drop\"\nfrom_s = 0.0\nuntil_s = 1.0\n")
    proc = run_hostsim(hostsim_bin, "run", str(bad), "--out", str(tmp_path))
    assert proc.returncode == 2 and "rate" in proc.stderr and "bad.toml" in proc.stderr, proc.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    proc = run_hostsim(hostsim_bin, "replay", str(junk))
    assert proc.returncode == 2 and "junk.mcap" in proc.stderr, proc.stderr
