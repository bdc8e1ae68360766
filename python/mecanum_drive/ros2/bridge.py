"""The ROS 2 node `mecanum_drive`: the robot on a CAN bus as the topics and services that
Nav2, teleop_twist_keyboard / teleop_twist_joy and RViz speak.

It drives the robot through the package's `Robot` (the keep-alive stream, the way out) and
needs rclpy and the message packages geometry_msgs, nav_msgs, diagnostic_msgs and std_srvs
(`pip install './python[ros2]'`, or a ROS 2 installation).

| name | type | what |
|---|---|---|
| `cmd_vel` (sub) | `geometry_msgs/msg/Twist` (`TwistStamped` with `use_stamped_vel`) | body-frame setpoint: linear.x, linear.y, angular.z; streamed to the robot at 50 Hz. None for `cmd_vel_timeout` s: zero twist (the robot stays enabled and holds still) |
| `odom` (pub) | `nav_msgs/msg/Odometry` | the robot's odometry: pose in `odom_frame_id`, measured twist in `base_frame_id`, at most `publish_rate` Hz (the robot sends its `timing.odometry_hz`, 100 by default); the pose's covariance grows with the distance driven and the rotation turned, at the odometry source's expected error (below); the twist's is `twist_covariance_diagonal`, constant |
| `/tf` (pub) | `tf2_msgs/msg/TFMessage` | `odom_frame_id` -> `base_frame_id`, with each `odom`, when `enable_odom_tf` and `tf2_msgs` is importable (a ROS 2 installation has it; the PyPI wheels do not: the node says so once at start-up) |
| `/diagnostics` (pub) | `diagnostic_msgs/msg/DiagnosticArray` | state, fault, motors online, heading source (wheels or gyro), odometry source (wheels or tracking pods) and, from a robot with pods, the slip estimate, the robot's counters and the bridge's, at `diagnostics_rate` Hz |
| `~/enable`, `~/disable`, `~/reset`, `~/estop` | `std_srvs/srv/Trigger` | MODE_CMD enable / disable / reset, ESTOP; `success` when the robot reports the state reached (ENABLED, DISABLED, DISABLED, ESTOP) within `service_timeout` s; `message`: its state and fault, or why not |

`/joint_states` is not published: the robot protocol (dbc/mecanum_robot.dbc) carries no wheel
states, only odometry, the slip estimate, status, counters and the heartbeat. (The drives' own frames
are on the bus, but decoding them is the firmware's job, at 4 kHz.)

Twists beyond the robot's limits are **clamped**: the whole twist is scaled by one factor
(direction and curvature kept) so that |(vx, vy)| <= `max_linear_speed` and |wz| <=
`max_angular_speed`, with a warning at most every 5 s. The firmware would otherwise reject
such a twist, and a robot fed only rejected twists stops on its command watchdog. A twist
with a component that is not a finite number is rejected (zero twist sent, warning).

**The pose covariance** of `/odom` is `pose_covariance_diagonal` at the start, and grows as
odometry drifts: the standard deviations of x and y grow by `position_error_wheels` (default
0.06) times each increment of the distance driven while the odometry comes from the wheels
(`Robot.odometry_source` WHEELS: a robot without tracking pods; or WHEELS_PODS_SILENT), by
`position_error_pods` (0.01) while it comes from pods (PODS2_GYRO, PODS3); the heading's by
`heading_error_gyro` (0.01) times each increment of the rotation while the heading comes from
a gyro (STATUS.heading_source GYRO) or from three pods (PODS3), else by `heading_error_wheels`
(0.05). Each variance is its base plus that standard deviation squared (x, y, yaw; z, roll,
pitch stay the base). The increments are those between successive odometry samples (every
one the robot sends, not only those published), and the growth never resets: the drift
accumulates for as long as the bridge runs. The model is `mecanum_drive.ros2.covariance`.
The twist's covariance is `twist_covariance_diagonal`, constant: the measured velocity's
error does not accumulate.

`/diagnostics` carries `odometry_source` (WHEELS from a robot without pods) and, once the
robot has sent ODOM_SLIP (only a robot with pods does), the slip estimate `slip_vx`,
`slip_vy` (m/s), `slip_wz` (rad/s); without ODOM_SLIP there are no slip keys. Pods silent
(WHEELS_PODS_SILENT) is a WARN, "<state>, pods silent: odometry from the wheels", as a
silent gyro is.

The parameters (PARAMETERS below; `ros2 param describe /mecanum_drive NAME`) are read once at
start-up and read-only after. The robot stays disabled until `~/enable`, or enables once it
answers with `enable_on_start`.

**The robot's own parameters** (docs/protocol.md, "Parameters": the firmware's configuration,
served as CiA 301 expedited SDO on node `robot_node`, 127 unless its CiA 402 drives make it
their master's node) are ROS 2 parameters too, `robot.<name>`: the name of the robot's table
with each index `[i]` written `_i`, since ROS 2 names take dots but no brackets
(`robot.gains.kp`, `robot.odometry.pods_1.x` for `odometry.pods[1].x`; `ros_parameter_name`).
At start-up the bridge reads each from the robot and declares those it has (a parameter the
robot answers "not in this configuration", 0x0609_0011, is not declared): a REAL32 as a
double, an UNSIGNED8 or UNSIGNED32 as an integer, a BOOLEAN as a bool, each described by the
robot's EDS (what it is, its object and type, its change class; the EDS carries no unit),
with the EDS's range (none where it has no upper limit) and read-only where its class is
*fixed*. A robot that does not answer leaves them undeclared, with a warning; they are
declared once it answers (tried again on its HEARTBEAT, at most every 5 s). They are the
robot's values: `-p robot.x:=...` and parameter files do not set them.

`ros2 param set /mecanum_drive robot.gains.kp 1.5` (the SetParameters service; a REAL32's
parameter is a double, so `2.0`, not `2`, which ROS 2 refuses as an integer) writes the
value to the robot, waiting at most 0.5 s for its answers, and succeeds only if the robot takes
it; a refusal fails the set with the robot's reason, `timing.status_hz = 20: changes only
while disabled (SDO abort 0x08000022)` (the rules: *live* any time, *disabled* only while the
robot is disabled, the EDS's range), and leaves the parameter as it was. The bridge reads the
value back and the parameter holds the value in force: a REAL32 is the float32 nearest the one
asked (1.3 becomes 1.2999999523162842). A set to a robot that sends no HEARTBEAT fails at
once. A set of several parameters at once (SetParametersAtomically) writes them in order and
stops at the first refusal; those written before it are in force on the robot and show up in
their parameters at the re-read below. When the robot's `HEARTBEAT.config_id` changes (another
client, `mecanum-drive param set` or a restore, changed the configuration; or the robot
restarted on another one) the bridge reads the parameters again and updates the declared
values, without writing them back. The SDO responses (0x580 + `robot_node`) arrive on the
bridge's one CAN bus: its receive path (`_SdoTap`, under the `Robot`'s receiving thread) hands
them to the parameter client and every other frame to the `Robot`.

On Ctrl-C or SIGTERM the bridge stops the stream and sends a zero twist and MODE_CMD disable
(`Robot.close`); killed outright, it stops sending and the robot's own command watchdog
stops it (100 ms by default).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import can
import rclpy.utilities
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.task import Future
from rclpy.time import Time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # type: ignore[import-untyped]
from geometry_msgs.msg import TransformStamped, Twist, TwistStamped  # type: ignore[import-untyped]
from nav_msgs.msg import Odometry as OdometryMsg  # type: ignore[import-untyped]
from rcl_interfaces.msg import ParameterDescriptor  # type: ignore[import-untyped]
from std_srvs.srv import Trigger  # type: ignore[import-untyped]

from .. import params as robot_params
from .. import protocol
from ..robot import Odometry, Robot, RobotError, RobotFault, Status
from .robot_parameters import RobotParameters, _SdoTap
from .covariance import (
    HEADING_ERROR_GYRO,
    HEADING_ERROR_WHEELS,
    POSITION_ERROR_PODS,
    POSITION_ERROR_WHEELS,
    CovarianceGrowth,
    ErrorRates,
)

#: The node's name (services are `/mecanum_drive/enable`, ...; `-r __node:=NAME` renames it).
NODE_NAME = "mecanum_drive"

#: Warnings about /cmd_vel (clamped, rejected, not sent) come at most this often, s.
WARN_EVERY_S = 5.0

#: The clamp aims this far inside a limit (m/s, rad/s): TWIST_CMD carries 0.001 steps, and a
#: speed rounded up past the firmware's limit would be rejected.
LIMIT_MARGIN = 0.002

#: The diagonal of diff_drive_controller's default covariances (x, y, z, roll, pitch, yaw).
DEFAULT_COVARIANCE = [0.001, 0.001, 0.001, 0.001, 0.001, 0.01]

WHEELS = ("FL", "FR", "RL", "RR")

#: Parameters: name -> (default, description). All are read at start-up (read-only after).
PARAMETERS: dict[str, tuple[Any, str]] = {
    "channel": ("can0", "CAN channel (python-can), e.g. can0"),
    "interface": ("socketcan", "python-can interface: socketcan, slcan, pcan, gs_usb, kvaser, ..."),
    "bitrate": (0, "bitrate for adapters that set it (slcan, pcan), bit/s; 0: leave it"),
    "status_rate": (10.0, "Hz, the robot's STATUS and HEARTBEAT rate (its timing.status_hz)"),
    "missed_heartbeats": (3, "HEARTBEAT periods without one after which the robot is not responding"),
    "cmd_vel_timeout": (0.5, "s without /cmd_vel after which the twist becomes zero"),
    "use_stamped_vel": (False, "subscribe geometry_msgs/msg/TwistStamped instead of Twist"),
    "max_linear_speed": (3.0, "m/s, |(vx, vy)| limit (the firmware's limits.max_linear_speed); faster twists are scaled down"),
    "max_angular_speed": (6.0, "rad/s, |wz| limit (the firmware's limits.max_angular_speed); faster twists are scaled down"),
    "publish_rate": (50.0, "Hz, most /odom (and /tf) messages per second"),
    "odom_frame_id": ("odom", "frame of the odometry's pose"),
    "base_frame_id": ("base_link", "the robot's body frame (the odometry's child frame)"),
    "enable_odom_tf": (True, "publish odom_frame_id -> base_frame_id on /tf (needs tf2_msgs)"),
    "pose_covariance_diagonal": (DEFAULT_COVARIANCE, "x, y, z, roll, pitch, yaw variances of the pose at the start "
                                 "(x, y and yaw then grow with the motion: the position_error_* and heading_error_* "
                                 "parameters)"),
    "twist_covariance_diagonal": (DEFAULT_COVARIANCE, "vx, vy, vz, wx, wy, wz variances of the twist (constant)"),
    "position_error_wheels": (POSITION_ERROR_WHEELS, "m per m driven: the /odom x and y standard deviations grow "
                              "by this times the distance driven while the odometry comes from the wheels (no "
                              "pods, or pods silent); 0.06: the largest error along the path on the built-in "
                              "square at speed was 5.9 % of the distance"),
    "position_error_pods": (POSITION_ERROR_PODS, "m per m driven, as position_error_wheels while the odometry comes "
                            "from tracking pods (PODS2_GYRO, PODS3); 0.01: the pods' target"),
    "heading_error_wheels": (HEADING_ERROR_WHEELS, "rad per rad turned: the /odom yaw standard deviation grows by "
                             "this times the rotation while the heading comes from the wheels"),
    "heading_error_gyro": (HEADING_ERROR_GYRO, "rad per rad turned, as heading_error_wheels while the heading comes "
                           "from a gyro (STATUS.heading_source GYRO) or three pods (PODS3)"),
    "diagnostics_rate": (1.0, "Hz, /diagnostics messages per second"),
    "service_timeout": (2.0, "s a service waits for the robot to report the state it asked for"),
    "enable_on_start": (False, "enable the robot once it answers, at start-up"),
    "robot_node": (robot_params.DEFAULT_NODE, "CANopen node id of the robot's parameter service (SDO): 127, or with "
                   "CiA 402 drives their master's node (drive.master_node); its parameters are robot.*"),
}


class ParameterError(ValueError):
    """A parameter with a value the bridge cannot use; the message names both."""

    def __init__(self, name: str, value: object, why: str) -> None:
        super().__init__(f"parameter {name} = {value!r}: {why}")
        self.name = name
        self.value = value


class BusError(RuntimeError):
    """The CAN channel cannot be opened."""


@dataclasses.dataclass(frozen=True)
class Settings:
    """The bridge's parameters, checked (see PARAMETERS)."""

    channel: str
    interface: str
    bitrate: int
    status_rate: float
    missed_heartbeats: int
    cmd_vel_timeout: float
    use_stamped_vel: bool
    max_linear_speed: float
    max_angular_speed: float
    publish_rate: float
    odom_frame_id: str
    base_frame_id: str
    enable_odom_tf: bool
    pose_covariance_diagonal: tuple[float, ...]
    twist_covariance_diagonal: tuple[float, ...]
    position_error_wheels: float
    position_error_pods: float
    heading_error_wheels: float
    heading_error_gyro: float
    diagnostics_rate: float
    service_timeout: float
    enable_on_start: bool
    robot_node: int

    @classmethod
    def from_values(cls, values: Mapping[str, object]) -> Settings:
        """Checks every value (type, range) and raises ParameterError naming the first bad one."""

        def positive(name: str, upper: float = math.inf, unit: str = "") -> float:
            value = values[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ParameterError(name, value, "must be a number")
            if not (math.isfinite(value) and 0 < value <= upper):
                bound = f" at most {upper}{unit}" if math.isfinite(upper) else ""
                raise ParameterError(name, value, f"must be a positive number{bound}")
            return float(value)

        def nonnegative(name: str) -> float:
            value = values[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ParameterError(name, value, "must be a number")
            if not (math.isfinite(value) and value >= 0):
                raise ParameterError(name, value, "must be a finite number >= 0")
            return float(value)

        def text(name: str) -> str:
            value = values[name]
            if not isinstance(value, str) or not value.strip():
                raise ParameterError(name, value, "must be a non-empty string")
            return value

        def flag(name: str) -> bool:
            value = values[name]
            if not isinstance(value, bool):
                raise ParameterError(name, value, "must be true or false")
            return value

        def covariance(name: str) -> tuple[float, ...]:
            value = values[name]
            items = list(value) if isinstance(value, (list, tuple)) else None
            if (items is None or len(items) != 6
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items)
                    or not all(math.isfinite(v) and v >= 0 for v in items)):
                raise ParameterError(name, value, "must be 6 finite numbers >= 0 (x, y, z, roll, pitch, yaw)")
            return tuple(float(v) for v in items)

        missed = values["missed_heartbeats"]
        if isinstance(missed, bool) or not isinstance(missed, int) or missed < 1:
            raise ParameterError("missed_heartbeats", missed, "must be a whole number >= 1")
        bitrate = values["bitrate"]
        if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate < 0:
            raise ParameterError("bitrate", bitrate, "must be an integer >= 0 (0: leave the adapter's)")
        node = values["robot_node"]
        if isinstance(node, bool) or not isinstance(node, int) or not 1 <= node <= 127:
            raise ParameterError("robot_node", node, "must be a CANopen node id, 1..127")
        _, top = protocol.signal_range("TWIST_CMD", "vx")
        return cls(
            channel=text("channel"),
            interface=text("interface"),
            bitrate=bitrate,
            status_rate=positive("status_rate"),
            missed_heartbeats=missed,
            cmd_vel_timeout=positive("cmd_vel_timeout"),
            use_stamped_vel=flag("use_stamped_vel"),
            max_linear_speed=positive("max_linear_speed", top, " m/s (the protocol's range)"),
            max_angular_speed=positive("max_angular_speed", top, " rad/s (the protocol's range)"),
            publish_rate=positive("publish_rate"),
            odom_frame_id=text("odom_frame_id"),
            base_frame_id=text("base_frame_id"),
            enable_odom_tf=flag("enable_odom_tf"),
            pose_covariance_diagonal=covariance("pose_covariance_diagonal"),
            twist_covariance_diagonal=covariance("twist_covariance_diagonal"),
            position_error_wheels=nonnegative("position_error_wheels"),
            position_error_pods=nonnegative("position_error_pods"),
            heading_error_wheels=nonnegative("heading_error_wheels"),
            heading_error_gyro=nonnegative("heading_error_gyro"),
            diagnostics_rate=positive("diagnostics_rate"),
            service_timeout=positive("service_timeout"),
            enable_on_start=flag("enable_on_start"),
            robot_node=node,
        )


def limit_twist(vx: float, vy: float, wz: float, max_linear: float, max_angular: float) -> tuple[tuple[float, float, float], bool]:
    """(the twist scaled by one factor so that |(vx, vy)| and |wz| stay within the limits, less
    LIMIT_MARGIN; whether it exceeded a limit). Direction and curvature are kept."""
    speed = math.hypot(vx, vy)
    over = speed > max_linear or abs(wz) > max_angular
    scale = 1.0
    if speed > max_linear - LIMIT_MARGIN:
        scale = min(scale, max(0.0, max_linear - LIMIT_MARGIN) / speed)
    if abs(wz) > max_angular - LIMIT_MARGIN:
        scale = min(scale, max(0.0, max_angular - LIMIT_MARGIN) / abs(wz))
    return (vx * scale, vy * scale, wz * scale), over


class Decimator:
    """Lets samples through at most `rate_hz` times a second, on a fixed schedule: a sample up
    to 30 % of a period early still counts (the robot's 10 ms samples arrive with jitter, and
    a rate that divides theirs is then kept exactly); after a gap the schedule restarts."""

    def __init__(self, rate_hz: float) -> None:
        self.period = 1.0 / rate_hz
        self._due = -math.inf

    def take(self, t: float) -> bool:
        """Whether the sample at time `t` (s, increasing) goes through."""
        if t < self._due - 0.3 * self.period:
            return False
        self._due = self._due + self.period if t < self._due + self.period else t + self.period
        return True


def _covariance_matrix(diagonal: Sequence[float]) -> list[float]:
    matrix = [0.0] * 36
    for i, value in enumerate(diagonal):
        matrix[i * 7] = value
    return matrix


class Bridge(RobotParameters):
    """The node. `overrides`: parameter values that win over `--ros-args` (the command line's
    `--channel`, `--interface`, `--bitrate`); `context`: rclpy's (default: the global one).
    Raises ParameterError for a bad parameter, BusError when the channel cannot be opened."""

    def __init__(self, overrides: Mapping[str, object] | None = None, *, context: Context | None = None) -> None:
        given = [Parameter(k, value=v) for k, v in (overrides or {}).items()]  # type: ignore[no-untyped-call]
        super().__init__(NODE_NAME, parameter_overrides=given, context=context)
        # rclpy's logger is untyped: one typed handle for the whole node.
        self.log: Any = self.get_logger()  # type: ignore[no-untyped-call]
        values: dict[str, object] = {}
        for name, (default, description) in PARAMETERS.items():
            descriptor = ParameterDescriptor(description=description, read_only=True, dynamic_typing=True)
            values[name] = self.declare_parameter(name, default, descriptor).value
        self.settings = s = Settings.from_values(values)
        log = self.log

        self._lock = threading.Condition()
        # Held for each command the bridge gives the robot, and by close(): once closed, no
        # callback still running (an executor thread, the timeout thread) restarts the stream.
        self._command_lock = threading.Lock()
        self._last_cmd: float | None = None  # time.monotonic() of the last /cmd_vel
        self._timed_out = True
        self._closing = False
        self.cmd_vel_received = 0
        self.cmd_vel_clamped = 0
        self.cmd_vel_rejected = 0
        self.cmd_vel_timeouts = 0
        self._odom_rate = Decimator(s.publish_rate)
        # The /odom pose covariance (mecanum_drive.ros2.covariance), grown with every odometry
        # sample by the robot's receiving thread; read it only for a look (tests, a debugger).
        self.pose_growth = CovarianceGrowth(s.pose_covariance_diagonal, ErrorRates(
            position_wheels=s.position_error_wheels, position_pods=s.position_error_pods,
            heading_wheels=s.heading_error_wheels, heading_gyro=s.heading_error_gyro))
        self._twist_cov = _covariance_matrix(s.twist_covariance_diagonal)

        # The bus as Robot.open makes it, with the robot's SDO responses let through too (the
        # parameter client's: `_SdoTap` hands them to it, the rest to the Robot).
        bus_args: dict[str, Any] = {"can_filters": [
            *Robot.receive_filters(), {"can_id": 0x580 + s.robot_node, "can_mask": 0x7FF, "extended": False}]}
        if s.bitrate:
            bus_args["bitrate"] = s.bitrate
        try:
            tap = _SdoTap(can.Bus(channel=s.channel, interface=s.interface, **bus_args), s.robot_node)
        except (can.CanError, OSError, ValueError) as err:
            raise BusError(f"cannot open {s.interface} channel {s.channel}: {err}") from err
        try:
            self.robot = Robot(tap, owns_bus=True, heartbeat_period_s=1.0 / s.status_rate,
                               missed_heartbeats=s.missed_heartbeats)
        except BaseException as err:
            tap.shutdown()
            if isinstance(err, ValueError):
                raise BusError(f"cannot open {s.interface} channel {s.channel}: {err}") from err
            raise
        self._sdo_port = tap.port

        self._odom_pub = self.create_publisher(OdometryMsg, "odom", 10)
        self._tf_pub = None
        self._tf_type: Any = None
        if s.enable_odom_tf:
            try:
                from tf2_msgs.msg import TFMessage  # type: ignore[import-not-found, import-untyped, unused-ignore]
            except ImportError as err:
                log.warning(
                    f"no {s.odom_frame_id} -> {s.base_frame_id} on /tf: tf2_msgs is not importable ({err}). "
                    "The ROS 2 wheels on PyPI do not include it; a ROS 2 installation does (run the bridge "
                    "with its Python: source /opt/ros/jazzy/setup.bash). /odom carries the same pose."
                )
            else:
                self._tf_type = TFMessage
                self._tf_pub = self.create_publisher(TFMessage, "/tf", 100)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)

        # The services wait for the robot's answer (up to service_timeout) in a thread each,
        # and their callbacks await it, in a reentrant group (a coroutine holds its group until
        # it returns): the executor, one thread, goes on with /cmd_vel, /diagnostics and any
        # other call meanwhile, so an e-stop never waits behind an enable. (rclpy's
        # multi-threaded executor spins hot while a callback group is busy: seen at 36-90 % of
        # a core with /cmd_vel at 20 Hz.)
        services = ReentrantCallbackGroup()
        modes: dict[str, tuple[Callable[[], None], str]] = {
            "enable": (self.robot.enable, "ENABLED"),
            "disable": (self.robot.disable, "DISABLED"),
            "reset": (self.robot.reset, "DISABLED"),
            "estop": (self.robot.estop, "ESTOP"),
        }
        for name, (action, state) in modes.items():
            self.create_service(Trigger, f"~/{name}", self._service(name, action, state), callback_group=services)

        self._cmd_type = TwistStamped if s.use_stamped_vel else Twist
        self.create_subscription(self._cmd_type, "cmd_vel", self._on_cmd_vel, 10)
        self.create_timer(1.0 / s.diagnostics_rate, self._publish_diagnostics)
        self.robot.on_odometry(self._on_odometry)

        self._watchdog = threading.Thread(target=self._cmd_vel_watchdog, name="cmd_vel timeout", daemon=True)
        self._watchdog.start()
        self._start_robot_parameters()
        if s.enable_on_start:
            threading.Thread(target=self._enable_on_start, name="enable on start", daemon=True).start()
        log.info(
            f"robot on {s.interface} channel {s.channel} (protocol version {protocol.protocol_version()}); "
            f"/cmd_vel ({'TwistStamped' if s.use_stamped_vel else 'Twist'}) timeout {s.cmd_vel_timeout} s, "
            f"limits {s.max_linear_speed} m/s, {s.max_angular_speed} rad/s (clamped); "
            + ("enabling once it answers" if s.enable_on_start else "disabled until ~/enable")
        )

    # --- /cmd_vel ----------------------------------------------------------------------------

    def _on_cmd_vel(self, msg: Any) -> None:
        twist = msg.twist if self.settings.use_stamped_vel else msg
        vx, vy, wz = float(twist.linear.x), float(twist.linear.y), float(twist.angular.z)
        log = self.log
        with self._lock:
            self.cmd_vel_received += 1
            self._last_cmd = time.monotonic()
            self._timed_out = False
            self._lock.notify_all()
        if not all(math.isfinite(v) for v in (vx, vy, wz)):
            with self._lock:
                self.cmd_vel_rejected += 1
            self._command(self.robot.stop)
            log.warning(f"/cmd_vel rejected, zero twist sent: not finite (vx {vx}, vy {vy}, wz {wz})",
                        throttle_duration_sec=WARN_EVERY_S)
            return
        s = self.settings
        (cx, cy, cw), over = limit_twist(vx, vy, wz, s.max_linear_speed, s.max_angular_speed)
        if over:
            with self._lock:
                self.cmd_vel_clamped += 1
            log.warning(
                f"/cmd_vel beyond the limits ({s.max_linear_speed} m/s, {s.max_angular_speed} rad/s) clamped: "
                f"({vx:.3f}, {vy:.3f}, {wz:.3f}) -> ({cx:.3f}, {cy:.3f}, {cw:.3f})",
                throttle_duration_sec=WARN_EVERY_S)
        try:
            self._command(lambda: self.robot.drive(cx, cy, cw))
        except (RobotError, ValueError) as err:
            self._command(self.robot.stop)
            log.warning(f"/cmd_vel not sent, zero twist instead: {err}", throttle_duration_sec=WARN_EVERY_S)

    def _command(self, command: Callable[[], None]) -> None:
        """Runs a robot command unless the bridge is closing."""
        with self._command_lock:
            if not self._closing:
                command()

    def _cmd_vel_watchdog(self) -> None:
        """Zero twist once no /cmd_vel came for cmd_vel_timeout s (a thread of its own that
        sleeps until that moment, so the stop is on time whatever the executor is doing)."""
        timeout = self.settings.cmd_vel_timeout
        while True:
            with self._lock:
                if self._closing:
                    return
                if self._timed_out or self._last_cmd is None:
                    self._lock.wait()
                    continue
                left = self._last_cmd + timeout - time.monotonic()
                if left > 0:
                    self._lock.wait(left)
                    continue
                self._timed_out = True
                self.cmd_vel_timeouts += 1
            self._command(self.robot.stop)
            self.log.info(f"no /cmd_vel for {timeout} s: zero twist", throttle_duration_sec=WARN_EVERY_S)

    # --- odometry ----------------------------------------------------------------------------

    def _on_odometry(self, odom: Odometry) -> None:
        """From the robot's receiving thread, on each ODOM_VELOCITY: /odom (and /tf) at most
        publish_rate times a second."""
        if self._closing or not (math.isfinite(odom.x) and math.isfinite(odom.y)):
            return
        # The covariance grows with every sample, published or not; the source is the latest
        # ODOM_SLIP's (sent after the ODOM_VELOCITY of its step: a change counts from the next
        # sample, 10 ms later).
        status = self.robot.status
        self.pose_growth.update(odom.x, odom.y, odom.heading, self.robot.odometry_source,
                                 status.heading_source if status is not None else None)
        # The stamp is when the frame arrived on the bus (its kernel receive time on SocketCAN,
        # `Odometry.age`), not when this process got to it: a busy receiving thread delays the
        # messages, not their stamps. The age is read first, so that a thread switch between
        # the two reads makes the stamp later, never earlier, than the sample.
        age = odom.age()
        if not self._odom_rate.take(time.monotonic() - age):
            return
        s = self.settings
        now = self.get_clock().now()
        stamp = Time(nanoseconds=now.nanoseconds - int(age * 1e9), clock_type=now.clock_type).to_msg()
        qz, qw = math.sin(odom.heading / 2), math.cos(odom.heading / 2)
        msg = OdometryMsg()
        msg.header.stamp = stamp
        msg.header.frame_id = s.odom_frame_id
        msg.child_frame_id = s.base_frame_id
        msg.pose.pose.position.x = odom.x
        msg.pose.pose.position.y = odom.y
        msg.pose.pose.orientation.z = qz
        msg.pose.pose.orientation.w = qw
        msg.pose.covariance = self.pose_growth.pose_covariance()
        msg.twist.twist.linear.x = odom.vx
        msg.twist.twist.linear.y = odom.vy
        msg.twist.twist.angular.z = odom.wz
        msg.twist.covariance = self._twist_cov
        tf = None
        if self._tf_pub is not None:
            tf = TransformStamped()
            tf.header.stamp = stamp
            tf.header.frame_id = s.odom_frame_id
            tf.child_frame_id = s.base_frame_id
            tf.transform.translation.x = odom.x
            tf.transform.translation.y = odom.y
            tf.transform.rotation.z = qz
            tf.transform.rotation.w = qw
        try:
            self._odom_pub.publish(msg)
            if self._tf_pub is not None:
                self._tf_pub.publish(self._tf_type(transforms=[tf]))
        except Exception:  # noqa: BLE001 - rclpy's RCLError once a signal has shut ROS down
            if self.context.ok():
                raise

    # --- services ----------------------------------------------------------------------------

    def _state_text(self) -> str:
        status = self.robot.status
        if status is None:
            return "no STATUS from the robot yet"
        return f"state {status.state}, fault {status.fault}"

    def set_mode(self, action: Callable[[], None], want: str) -> tuple[bool, str]:
        """Runs `action` (a Robot method), asks for a STATUS and waits up to service_timeout
        for `want`: (reached, the robot's state and fault or why not)."""
        try:
            self._command(action)
            self._command(self.robot.request_status)
            status = self.robot.wait_state(want, timeout=self.settings.service_timeout)
        except RobotFault as err:
            return False, f"the robot is in FAULT: {err.fault} (~/reset clears it); {self._state_text()}"
        except (RobotError, TimeoutError, RuntimeError) as err:
            return False, f"{err}; {self._state_text()}"
        return True, f"state {status.state}, fault {status.fault}"

    def _service(self, name: str, action: Callable[[], None], want: str) -> Callable[[Any, Any], Any]:
        async def handle(request: Any, response: Any) -> Any:
            answer: Any = Future(executor=self.executor)  # type: ignore[no-untyped-call]  # rclpy.task is untyped
            # Its completion (from the thread below) wakes the executor, which resumes this.
            answer.add_done_callback(lambda _: None)

            def work() -> None:
                try:
                    answer.set_result(self.set_mode(action, want))
                except BaseException as err:  # noqa: BLE001 - handed to the awaiting callback
                    answer.set_exception(err)

            threading.Thread(target=work, name=f"~/{name}", daemon=True).start()
            response.success, response.message = await answer
            # (rclpy ties a logging call site to one severity: one call per severity.)
            if response.success:
                self.log.info(f"~/{name}: {response.message}")
            else:
                self.log.warning(f"~/{name}: {response.message}")
            return response

        return handle

    def _enable_on_start(self) -> None:
        """enable_on_start, in a thread of its own: waits for the robot's first HEARTBEAT (up
        to service_timeout), then enables it as ~/enable does."""
        deadline = time.monotonic() + self.settings.service_timeout
        while self.robot.heartbeat is None and time.monotonic() < deadline and not self._closing:
            time.sleep(0.02)
        ok, message = self.set_mode(self.robot.enable, "ENABLED")
        if ok:
            self.log.info(f"enable at start-up: {message}")
        else:
            self.log.error(f"enable at start-up: {message}")

    # --- diagnostics -------------------------------------------------------------------------

    def diagnostic_status(self) -> Any:
        """The robot's DiagnosticStatus now: level, message, and the values by key."""
        robot, s = self.robot, self.settings
        status: Status | None = robot.status
        heartbeat, counters = robot.heartbeat, robot.counters
        slip = robot.slip  # ODOM_SLIP: only from a robot with tracking pods
        odometry_source = "WHEELS" if slip is None else slip.source
        problem = None
        try:
            robot.check()
        except RobotFault:
            pass  # STATUS says FAULT: below
        except RobotError as err:  # not responding, another protocol version
            problem = str(err)
        if heartbeat is None and problem is None:
            level, message = DiagnosticStatus.STALE, f"no HEARTBEAT from the robot yet on {s.interface} {s.channel}"
        elif problem is not None:
            level, message = DiagnosticStatus.ERROR, problem
        elif status is None:
            level, message = DiagnosticStatus.STALE, "no STATUS from the robot yet"
        elif status.state == "FAULT":
            level, message = DiagnosticStatus.ERROR, f"FAULT: {status.fault} (~/reset clears it)"
        elif status.state == "ESTOP":
            level, message = DiagnosticStatus.WARN, "ESTOP (latched; ~/reset clears it)"
        elif not all(status.motors_online):
            offline = [w for w, up in zip(WHEELS, status.motors_online) if not up]
            level, message = DiagnosticStatus.WARN, f"{status.state}, motors offline: {' '.join(offline)}"
        elif status.fault != "NONE":
            level, message = DiagnosticStatus.WARN, f"{status.state} after fault {status.fault}"
        elif status.heading_source == "WHEELS_GYRO_SILENT" or odometry_source == "WHEELS_PODS_SILENT":
            silent = [what for what, yes in (
                ("gyro silent: heading from the wheels", status.heading_source == "WHEELS_GYRO_SILENT"),
                ("pods silent: odometry from the wheels", odometry_source == "WHEELS_PODS_SILENT"),
            ) if yes]
            level, message = DiagnosticStatus.WARN, f"{status.state}, {', '.join(silent)}"
        else:
            level, message = DiagnosticStatus.OK, status.state
        with self._lock:
            age = None if self._last_cmd is None else time.monotonic() - self._last_cmd
            bridge = {
                "cmd_vel_received": self.cmd_vel_received,
                "cmd_vel_clamped": self.cmd_vel_clamped,
                "cmd_vel_rejected": self.cmd_vel_rejected,
                "cmd_vel_timeouts": self.cmd_vel_timeouts,
            }
        values: dict[str, object] = {
            "state": status.state if status else "",
            "fault": status.fault if status else "",
            "motors_online": " ".join(w for w, up in zip(WHEELS, status.motors_online) if up) if status else "",
            "heading_source": status.heading_source if status else "",
            "odometry_source": odometry_source,
            **({} if slip is None else {
                "slip_vx": f"{slip.vx:.3f}", "slip_vy": f"{slip.vy:.3f}", "slip_wz": f"{slip.wz:.3f}",
            }),
            "responding": robot.responding,
            "rx_errors": status.rx_errors if status else "",
            "unknown_ids": status.unknown_ids if status else "",
            "repeated_seq": counters.repeated_seq if counters else "",
            "wrong_dlc": counters.wrong_dlc if counters else "",
            "out_of_range": counters.out_of_range if counters else "",
            "non_finite": counters.non_finite if counters else "",
            "protocol_version": heartbeat.protocol_version if heartbeat else "",
            "config_id": f"0x{heartbeat.config_id:04x}" if heartbeat else "",
            "uptime_s": f"{heartbeat.uptime_ms / 1000:.1f}" if heartbeat else "",
            "twists_sent": robot.twists_sent,
            "setpoint": " ".join(f"{v:.3f}" for v in robot.setpoint),
            **bridge,
            "cmd_vel_age_s": "" if age is None else f"{age:.3f}",
        }
        return DiagnosticStatus(
            level=level, name=f"{self.get_name()}: robot", message=message,
            hardware_id=f"{s.interface}:{s.channel}",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostic_status()]
        self._diag_pub.publish(msg)

    # --- the end -----------------------------------------------------------------------------

    def close(self) -> None:
        """Stops the timeout thread and closes the robot: the stream stops, a zero twist and
        MODE_CMD disable go out."""
        with self._command_lock, self._lock:
            self._closing = True
            self._lock.notify_all()
        self._params_stop.set()
        self.robot.close()
        self._watchdog.join(timeout=1.0)
        self._params_thread.join(timeout=1.0)


def make_executor(context: Context | None = None) -> SingleThreadedExecutor:
    """The executor the bridge spins in: one thread (the services wait in threads of their own)."""
    return SingleThreadedExecutor(context=context)


def main(ros_args: list[str], *, overrides: Mapping[str, object] | None = None, prog: str = "mecanum-drive ros2") -> int:
    """Runs the node until Ctrl-C or SIGTERM (rclpy's handlers end the spin); the robot is
    left disabled however it ends. Returns the exit status: 0, 2 for a bad parameter, 1 when
    the CAN channel cannot be opened."""
    rclpy.init(args=[prog, *ros_args])
    bridge: Bridge | None = None
    executor = make_executor()
    try:
        bridge = Bridge(overrides)
        executor.add_node(bridge)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 2
    except BusError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 1
    except Exception:
        # A signal shuts ROS down under the executor's feet: rclpy may then fail to build its
        # next wait set (RCLError) instead of ending the spin. That is the way out too.
        if rclpy.utilities.ok():
            raise
    finally:
        if bridge is not None:
            bridge.close()
        executor.shutdown(timeout_sec=1.0)
        if bridge is not None:
            bridge.destroy_node()  # type: ignore[no-untyped-call]
        rclpy.utilities.try_shutdown()
    return 0
