"""The simulator's logs as ROS 2 bags, read by a tool that knows nothing of this project.

rosbags' bag reader (`AnyReader`, with the ROS 2 Humble type store for a bag without
definitions) opens a logged run, builds its decoders from the file's own `ros2msg` schemas
(crates/drivelog/src/lib.rs, "Channels"; crates/drivelog/src/msg.rs) and deserialises every
message of every channel. What it decodes must be the run: the same message counts as the
`mcap` reader and `hostsim summary` find, the odometry and ground truth the summary prints, the
transforms of the odometry, wheel states that are the odometry's own, and CAN frames whose
DBC (cantools) values are the messages' numbers. Two runs: the built-in `circle`, and
scenarios/faults.toml, whose dropped and corrupted frames fill /can/faults (the project's own
type, mecanum_drive_msgs/msg/BusFault).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import pathlib
import re
import subprocess
import tomllib

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

ROOT = pathlib.Path(__file__).resolve().parent.parent

#: Every channel's topic and ROS 2 type (crates/drivelog/src/lib.rs, the channel table).
CHANNEL_TYPES = {
    "/can/rx": "can_msgs/msg/Frame",
    "/can/tx": "can_msgs/msg/Frame",
    "/can/faults": "mecanum_drive_msgs/msg/BusFault",
    "/cmd_vel": "geometry_msgs/msg/TwistStamped",
    "/odom": "nav_msgs/msg/Odometry",
    "/ground_truth/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/joint_states": "sensor_msgs/msg/JointState",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "/rosout": "rcl_interfaces/msg/Log",
    "/firmware/steps": "mecanum_drive_msgs/msg/Step",
    "/firmware/store": "mecanum_drive_msgs/msg/SaveResult",
}

#: The two runs: a built-in, and a scenario file with bus faults.
RUNS = {"circle": "circle", "faults": str(ROOT / "scenarios" / "faults.toml")}

#: A topic line of `hostsim summary`: "  /can/rx      33460 messages".
TOPIC_LINE = re.compile(r"^\s+(/\S+)\s+(\d+) messages$", re.MULTILINE)
NUMBER = r"([+-]\d+\.\d+)"
#: The pose line of `hostsim summary`: x and y to 0.1 mm, heading to 0.01°.
POSE_LINE = re.compile(
    rf"odometry x {NUMBER} y {NUMBER} heading {NUMBER}°; ground truth x {NUMBER} y {NUMBER} heading {NUMBER}°"
)
#: The bus line's frame counts by fate: "frames: 3 corrupted, 31568 delivered, 47 dropped".
FATES_LINE = re.compile(r"frames: ([^\n]*)")

#: rcl_interfaces/msg/Log levels.
INFO, WARN, ERROR = 20, 30, 40

#: DBC resolutions: ODOM_POSITION x, y (m); ODOM_VELOCITY heading (rad), vx, vy, wz (m/s,
#: rad/s); the C620's current (A, 20 A in 16384 counts).
POSITION_RES, HEADING_RES, VELOCITY_RES, CURRENT_RES = 1e-4, 1e-4, 1e-3, 20 / 16384


def ns(stamp) -> int:
    """A builtin_interfaces/msg/Time in nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def yaw(q) -> float:
    """The yaw of a rotation about z."""
    return 2.0 * math.atan2(q.z, q.w)


def angle_diff(a: float, b: float, turn: float = 2 * math.pi) -> float:
    """a - b, wrapped to half a turn either side."""
    return (a - b + turn / 2) % turn - turn / 2


@dataclasses.dataclass
class Log:
    """A logged run, as rosbags and the mcap reader read it, with what hostsim said of it."""

    name: str
    path: pathlib.Path
    run: dict  # `hostsim run --json`
    summary: str  # `hostsim summary`
    config: dict  # the metadata record's drive configuration
    counts: collections.Counter  # messages per topic, rosbags
    connection_types: dict[str, str]  # topic -> message type, rosbags
    messages: dict[str, list]  # topic -> [(log time ns, message)], rosbags
    mcap_counts: collections.Counter  # messages per topic, mcap reader
    statistics: dict[str, int]  # the Statistics record's counts per topic
    tx_publish_ns: dict[int, int]  # /can/tx log time -> publish time (the step that sent it)
    schemas: dict[str, str]  # type -> ros2msg schema text

    def last(self, topic: str):
        return self.messages[topic][-1][1]


@pytest.fixture(scope="module", params=list(RUNS))
def log(request, hostsim_bin: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> Log:
    """One of RUNS, run and summarised by hostsim, then read whole, once for the module's
    tests: every message deserialised by rosbags, and the file read again by the `mcap`
    reader (every chunk's CRC checked) for its counts, schemas, metadata and the publish times
    rosbags does not give. (A run killed mid-way, read with the `mcap` reader:
    tests/test_crash_safety.py. rosbags needs the summary a killed run never wrote.)"""
    name = request.param
    out = tmp_path_factory.mktemp(name)
    proc = subprocess.run(
        [str(hostsim_bin), "run", RUNS[name], "--out", str(out), "--json", "--no-plot"],
        capture_output=True, text=True, timeout=600, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    run = json.loads(proc.stdout)
    path = out / f"{name}.mcap"
    summary = subprocess.run(
        [str(hostsim_bin), "summary", str(path)], capture_output=True, text=True, timeout=120, check=False
    )
    assert summary.returncode == 0, summary.stderr

    counts: collections.Counter = collections.Counter()
    messages: dict[str, list] = collections.defaultdict(list)
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        connection_types = {c.topic: c.msgtype for c in reader.connections}
        for connection, log_ns, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            counts[connection.topic] += 1
            messages[connection.topic].append((log_ns, message))

    mcap_counts: collections.Counter = collections.Counter()
    tx_publish_ns: dict[int, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        file_summary = reader.get_summary()
        topics = {c.id: c.topic for c in file_summary.channels.values()}
        statistics = {topics[i]: n for i, n in file_summary.statistics.channel_message_counts.items() if n}
        schemas = {s.name: s.data.decode() for s in file_summary.schemas.values()}
        (config,) = [tomllib.loads(m.metadata["config"]) for m in reader.iter_metadata() if m.name == "mecanum_drive"]
        for _, channel, message in reader.iter_messages():
            mcap_counts[channel.topic] += 1
            if channel.topic == "/can/tx":
                tx_publish_ns[message.log_time] = message.publish_time
    # Two frames cannot complete on one bus at once: a sent frame's log time names it.
    assert len(tx_publish_ns) == mcap_counts["/can/tx"]
    return Log(
        name, path, run, summary.stdout, config, counts, connection_types, messages,
        mcap_counts, statistics, tx_publish_ns, schemas,
    )


def test_rosbags_deserialises_every_message_of_every_channel(log: Log) -> None:
    """Every message decodes (the fixture deserialised them all), on every channel with its
    type, and none is missing: rosbags counts what the `mcap` reader, the file's Statistics
    record and `hostsim summary` count, topic by topic, and the frames the run reported."""
    assert log.connection_types == CHANNEL_TYPES
    assert log.counts == log.mcap_counts
    assert dict(log.counts) == log.statistics
    assert {topic: int(n) for topic, n in TOPIC_LINE.findall(log.summary)} == dict(log.counts)
    assert log.counts["/can/tx"] == log.run["tx_frames"]
    assert log.counts["/can/rx"] == log.run["rx_frames"]
    # Ten-step snapshots, odometry and ground truth, each pose once more on /tf.
    every_tenth = (log.run["steps"] + 9) // 10
    for topic in ("/odom", "/ground_truth/odom", "/joint_states", "/diagnostics"):
        assert log.counts[topic] == every_tenth, topic
    assert log.counts["/tf"] == 2 * every_tenth
    # The faults scenario's bus faults, the circle's none: /can/faults is deserialised too.
    assert log.counts["/can/faults"] == log.run["dropped"] + log.run["corrupted"]
    assert (log.counts["/can/faults"] > 0) == (log.name == "faults")


def test_the_standard_types_are_ros2_humbles(log: Log) -> None:
    """A reader that decodes with its own ROS 2 definitions (a `ros 2 bag play` with the
    packages installed) rather than the file's gets the same fields: every standard type in
    the schemas, dependencies included, is field for field the Humble type store's. Only the
    three types Humble lacks come from the file alone."""
    humble = get_typestore(Stores.ROS2_HUMBLE)
    seen, own = set(), set()
    for name, text in log.schemas.items():
        for typename, fields in get_types_from_msg(text, name).items():
            if typename in humble.fielddefs:
                assert fields == humble.fielddefs[typename], typename
                seen.add(typename)
            else:
                own.add(typename)
    assert own == {"can_msgs/msg/Frame", "mecanum_drive_msgs/msg/BusFault", "mecanum_drive_msgs/msg/Step",
                   "mecanum_drive_msgs/msg/SaveResult"}
    assert seen == {
        "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "rcl_interfaces/msg/Log",
        "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion",
        "geometry_msgs/msg/Pose", "geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Twist",
        "geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/TwistWithCovariance",
        "geometry_msgs/msg/Transform", "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry",
        "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/JointState", "diagnostic_msgs/msg/KeyValue",
        "diagnostic_msgs/msg/DiagnosticStatus", "diagnostic_msgs/msg/DiagnosticArray",
    }


def test_final_odometry_and_ground_truth_are_what_the_summary_prints(log: Log) -> None:
    """The last /odom and /ground_truth/odom poses, decoded by rosbags, against `hostsim
    summary`'s line (x and y to 0.1 mm, the heading to 0.01°: the tolerances are what it
    prints), and against the run's own final report (`hostsim run --json`), which is up to
    9 ms later than the last tenth step: within what the logged twist moves the robot in
    that time, plus 1 µm, and in heading plus 1 µrad and one encoder count of one wheel. The
    faults run ends on a tenth step: there the two are the same numbers, to the bit."""
    match = POSE_LINE.search(log.summary)
    assert match, log.summary
    ox, oy, oh, gx, gy, gh = map(float, match.groups())
    for topic, (x, y, heading) in (("/odom", (ox, oy, oh)), ("/ground_truth/odom", (gx, gy, gh))):
        pose = log.last(topic).pose.pose
        assert pose.position.x == pytest.approx(x, abs=1e-4), topic
        assert pose.position.y == pytest.approx(y, abs=1e-4), topic
        assert abs(angle_diff(math.degrees(yaw(pose.orientation)), heading, 360.0)) <= 0.01, topic
        assert pose.position.z == 0.0 and pose.orientation.x == 0.0 and pose.orientation.y == 0.0
    # The odometry moves in encoder counts: a wheel that stands at the edge of a count can tick
    # once in those 9 ms while the logged twist says 0. One count of one wheel (8192 per rotor
    # turn) turns the heading by its travel over 4 (lx + ly), 2.0 µrad on the example chassis
    # (it moves the position by a quarter of its travel, 0.76 µm, within the 1 µm).
    geometry, drive = log.config["geometry"], log.config["drive"]
    assert drive["protocol"] == "dji", drive
    count_m = geometry["wheel_radius"] * 2 * math.pi / (8192 * drive["gear_ratio"])
    # The odometry reports yaw_effectiveness (default 1, left out of the TOML at 1) times it.
    count_rad = geometry.get("yaw_effectiveness", 1.0) * count_m / (4 * (geometry["lx"] + geometry["ly"]))
    for topic, final in (("/odom", log.run["odometry"]), ("/ground_truth/odom", log.run["truth"])):
        last = log.last(topic)
        dt = log.run["duration_s"] - ns(last.header.stamp) * 1e-9
        assert 0.0 <= dt < 0.01, (topic, dt)
        twist, pose = last.twist.twist, last.pose.pose
        moved = math.hypot(twist.linear.x, twist.linear.y) * dt + 1e-6
        turned = abs(twist.angular.z) * dt + 1e-6 + (count_rad if topic == "/odom" else 0.0)
        assert math.hypot(pose.position.x - final[0], pose.position.y - final[1]) <= moved, (topic, final)
        assert abs(angle_diff(yaw(pose.orientation), final[2])) <= turned, (topic, final)
        if log.name == "faults":
            assert (pose.position.x, pose.position.y) == (final[0], final[1]), topic


def test_odometry_frames_agree_with_odom_through_the_dbc(log: Log, dbs) -> None:
    """Every ODOM_POSITION (0x310) and ODOM_VELOCITY (0x311) frame on /can/tx, decoded with
    cantools, is the /odom message of the control step that sent it (its publish time)
    within the frame's resolution: 0.1 mm, 0.1 mrad, 1 mm/s. The last ones are the final
    odometry."""
    db = dbs["robot"]
    odom = {ns(m.header.stamp): m for _, m in log.messages["/odom"]}
    steps: dict[int, list[int]] = {0x310: [], 0x311: []}
    for log_ns, frame in log.messages["/can/tx"]:
        if frame.id not in (0x310, 0x311):
            continue
        step = log.tx_publish_ns[log_ns]
        assert ns(frame.header.stamp) == log_ns and step <= log_ns < step + 2_000_000
        values = db.decode_message(frame.id, bytes(frame.data[: frame.dlc]))
        o = odom[step]
        if frame.id == 0x310:
            assert values["x"] == pytest.approx(o.pose.pose.position.x, abs=POSITION_RES), (step, values)
            assert values["y"] == pytest.approx(o.pose.pose.position.y, abs=POSITION_RES), (step, values)
        else:
            assert abs(angle_diff(values["heading"], yaw(o.pose.pose.orientation))) <= HEADING_RES, (step, values)
            twist = o.twist.twist
            for key, value in (("vx", twist.linear.x), ("vy", twist.linear.y), ("wz", twist.angular.z)):
                assert values[key] == pytest.approx(value, abs=VELOCITY_RES), (step, key, values)
        steps[frame.id].append(step)
    # One of each per /odom message, at its step (odometry at 100 Hz), the last at the last.
    assert steps[0x310] == steps[0x311] == sorted(odom), {i: len(s) for i, s in steps.items()}


def test_tf_is_the_odometry_and_the_ground_truth(log: Log) -> None:
    """/tf holds odom -> base_link (the firmware's odometry) and odom -> base_link_truth (the
    plant's), one transform a message, each the pose of /odom or /ground_truth/odom at the
    same stamp, to the bit."""
    poses = {
        ("base_link", ns(m.header.stamp)): m for _, m in log.messages["/odom"]
    } | {
        ("base_link_truth", ns(m.header.stamp)): m for _, m in log.messages["/ground_truth/odom"]
    }
    assert all(m.header.frame_id == "odom" for (_, m) in log.messages["/odom"] + log.messages["/ground_truth/odom"])
    assert {m.child_frame_id for _, m in log.messages["/odom"]} == {"base_link"}
    assert {m.child_frame_id for _, m in log.messages["/ground_truth/odom"]} == {"base_link_truth"}
    seen = set()
    for log_ns, message in log.messages["/tf"]:
        (t,) = message.transforms
        key = (t.child_frame_id, ns(t.header.stamp))
        assert t.header.frame_id == "odom" and key[1] == log_ns, t
        pose = poses[key].pose.pose
        tr, rot = t.transform.translation, t.transform.rotation
        assert (tr.x, tr.y, tr.z) == (pose.position.x, pose.position.y, pose.position.z), key
        assert (rot.x, rot.y, rot.z, rot.w) == (
            pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w
        ), key
        seen.add(key)
    assert seen == set(poses)


def test_wheel_states_are_the_odometry_and_the_dbc_frames(log: Log, dbs) -> None:
    """/joint_states: the wheels fl, fr, rl, rr. Their speeds, through the configuration's
    forward kinematics (standard layout), are /odom's twist at the same step; their angles
    turned the robot by what the odometry's heading says; each speed is the last DJI feedback
    frame's rotor speed (cantools) through the gear ratio, mirrored motors negated, to the
    float; each effort the current of the step's CURRENT_CMD frame (0x200), within its
    resolution. The forward kinematics include the configuration's effectiveness factors
    (each 1 unless the TOML has the key): the odometry reports them times the wheels' twist."""
    geometry, drive = log.config["geometry"], log.config["drive"]
    r, k = geometry["wheel_radius"], geometry["lx"] + geometry["ly"]
    kx, ky, kw = (geometry.get(f"{axis}_effectiveness", 1.0) for axis in ("forward", "lateral", "yaw"))
    assert geometry["layout"] == "standard" and drive["protocol"] == "dji"
    sign = [-1.0 if inverted else 1.0 for inverted in drive["inverted"]]
    rpm_to_wheel = 2 * math.pi / 60 / drive["gear_ratio"]
    odom = {ns(m.header.stamp): m for _, m in log.messages["/odom"]}
    dji = dbs["dji"]

    # The firmware's last feedback of each wheel, and each step's current command.
    feedback: dict[int, list] = {w: [] for w in range(4)}
    for log_ns, frame in log.messages["/can/rx"]:
        esc = frame.id - 0x200
        if 1 <= esc <= 4:
            feedback[drive["esc_ids"].index(esc)].append(
                (log_ns, dji.decode_message(frame.id, bytes(frame.data[: frame.dlc]))["rotor_speed"])
            )
    commands = {
        log.tx_publish_ns[log_ns]: dji.decode_message(0x200, bytes(frame.data[: frame.dlc]))
        for log_ns, frame in log.messages["/can/tx"]
        if frame.id == 0x200
    }
    cursor = [0, 0, 0, 0]
    first = log.messages["/joint_states"][0][1]
    heading, last_yaw = 0.0, yaw(odom[ns(first.header.stamp)].pose.pose.orientation)
    checked = 0
    for log_ns, state in log.messages["/joint_states"]:
        step = ns(state.header.stamp)
        assert step == log_ns and list(state.name) == ["fl", "fr", "rl", "rr"], state
        assert all(len(v) == 4 and all(map(math.isfinite, v)) for v in (state.position, state.velocity, state.effort))
        fl, fr, rl, rr = state.velocity
        twist = odom[step].twist.twist
        assert kx * r / 4 * (fl + fr + rl + rr) == pytest.approx(twist.linear.x, abs=1e-5), step
        assert ky * r / 4 * (-fl + fr + rl - rr) == pytest.approx(twist.linear.y, abs=1e-5), step
        assert kw * r / (4 * k) * (-fl + fr - rl + rr) == pytest.approx(twist.angular.z, abs=1e-5), step
        for w in range(4):
            fb = feedback[w]
            while cursor[w] < len(fb) and fb[cursor[w]][0] <= step:
                cursor[w] += 1
            if cursor[w]:
                rpm = fb[cursor[w] - 1][1]
                assert state.velocity[w] == pytest.approx(sign[w] * rpm * rpm_to_wheel, rel=1e-5, abs=1e-6), (step, w)
        if step in commands:
            current = [sign[w] * commands[step][f"current_{drive['esc_ids'][w]}"] for w in range(4)]
            assert state.effort == pytest.approx(current, abs=CURRENT_RES), step
            checked += 1
        y = yaw(odom[step].pose.pose.orientation)
        heading += angle_diff(y, last_yaw)
        last_yaw = y
    assert checked == len(log.messages["/joint_states"])
    # The turn the wheel angles make is the odometry's heading, unwrapped (the circle: one
    # turn, 2 pi rad), to a milliradian.
    p0, p1 = first.position, log.last("/joint_states").position
    fl, fr, rl, rr = (b - a for a, b in zip(p0, p1))
    assert kw * r / (4 * k) * (-fl + fr - rl + rr) == pytest.approx(heading, abs=1e-3)
    if log.name == "circle":
        assert heading == pytest.approx(2 * math.pi, abs=0.01)
        # A 1 m radius circle: 2 pi m of travel, as the wheels count it.
        assert r / 4 * (fl + fr + rl + rr) == pytest.approx(2 * math.pi, rel=0.01)
    assert all(abs(p) > 1.0 for p in p1), p1


def test_diagnostics_and_rosout_follow_the_runs_state_changes(log: Log) -> None:
    """/diagnostics' one status carries the state the run reported (its transitions, from
    `hostsim run --json`) at each tenth step: Disabled, then Enabled from 51 ms (the whole
    circle), with the level ERROR in Fault; its `steps` count the control steps. /rosout
    says each state change once, at its time, ERROR for a Fault (WARN for an e-stop)."""
    transitions = [(round(t * 1e9), state, fault) for t, state, fault in log.run["transitions"]]
    states = collections.Counter()
    for log_ns, message in log.messages["/diagnostics"]:
        (status,) = message.status
        values = {kv.key: kv.value for kv in status.values}
        step = ns(message.header.stamp)
        assert step == log_ns
        current = [(state, fault) for t, state, fault in transitions if t <= step]
        state, fault = current[-1] if current else ("DISABLED", "NONE")
        assert (values["state"], values["fault"]) == (state, fault), (step, values)
        assert int(values["steps"]) == step // 1_000_000 + 1, (step, values)
        assert status.level == (2 if state == "FAULT" else 0), (step, status)
        assert status.name == "mecanum_drive: firmware"
        states[state] += 1
    if log.name == "circle":
        assert states["ENABLED"] == log.counts["/diagnostics"] - 6, states  # 0 to 50 ms Disabled
        last = {kv.key: kv.value for kv in log.last("/diagnostics").status[0].values}
        assert last["motors_online"] == "0b1111" and last["fault"] == "NONE", last
    else:
        assert set(states) == {"DISABLED", "ENABLED", "FAULT"}, states
    rosout = [(ns(m.stamp), m.level, m.msg) for _, m in log.messages["/rosout"]]
    assert rosout == [
        (t, {"FAULT": ERROR, "ESTOP": WARN}.get(state, INFO), f"state {state}, fault {fault}")
        for t, state, fault in transitions
    ]


def test_bus_faults_are_the_injectors_dropped_and_corrupted_frames(log: Log) -> None:
    """/can/faults (mecanum_drive_msgs/msg/BusFault) holds one message a frame the fault
    injector dropped or corrupted: as many of each as the run and the summary count. A
    corrupted frame reached the firmware with the faulty data (/can/rx, same stamp, the
    `received` bytes); a dropped one never did."""
    faults = [m for _, m in log.messages["/can/faults"]]
    fates = collections.Counter(f.fate for f in faults)
    assert fates == {
        fate: n for fate, n in (("dropped", log.run["dropped"]), ("corrupted", log.run["corrupted"])) if n
    }
    match = FATES_LINE.search(log.summary)
    assert match, log.summary
    printed = {fate: int(n) for n, fate in re.findall(r"(\d+) (\w+)", match.group(1))}
    assert {fate: n for fate, n in printed.items() if fate != "delivered"} == dict(fates)
    # Every frame on the bus is on /can/rx or /can/tx (a corrupted one as received, one the
    # firmware sent even if dropped), except those dropped on their way to the firmware,
    # which only /can/faults holds.
    lost = sum(f.sender != "controller" and f.fate == "dropped" for f in faults)
    assert sum(printed.values()) == log.counts["/can/rx"] + log.counts["/can/tx"] + lost
    if log.name == "circle":
        assert not faults
        return
    # The scenario: 1 % of the drives' feedback dropped for a second, a tenth of the host's
    # commands corrupted for half a second, and all of them lost for 150 ms (8 frames at 50 Hz).
    assert {f.sender for f in faults} <= {"controller", "drives", "host"}
    assert {(f.sender, f.fate) for f in faults} == {("drives", "dropped"), ("host", "corrupted"), ("host", "dropped")}
    assert sum(f.sender == "host" and f.fate == "dropped" for f in faults) == 8
    received = collections.defaultdict(list)
    for log_ns, frame in log.messages["/can/rx"]:
        received[ns(frame.header.stamp)].append((frame.id, bytes(frame.data)))
    for f in faults:
        stamp = ns(f.header.stamp)
        assert ns(f.frame.header.stamp) == stamp
        if f.fate == "corrupted":
            assert bytes(f.received) != bytes(f.frame.data), f
            assert received[stamp] == [(f.frame.id, bytes(f.received))], f
        else:
            assert bytes(f.received) == bytes(f.frame.data), f
            assert (f.frame.id, bytes(f.frame.data)) not in received[stamp], f
            if f.sender == "drives":
                assert 1.0 <= stamp * 1e-9 < 2.0 and 0x201 <= f.frame.id <= 0x204, f
            else:
                assert 4.0 <= stamp * 1e-9 < 4.15 and f.frame.id == 0x301, f
