"""The pose covariance the bridge publishes on `/odom`: a base that grows with the distance
driven and the rotation turned, at the rate the odometry's source is expected to err.

Odometry drifts: its error is not a constant but grows with the motion. The model is the
simplest one that says so: the standard deviation of x and of y grows by `k_pos` times each
increment of the distance driven, that of the heading by `k_yaw` times each increment of the
rotation, where `k_pos` and `k_yaw` are the expected relative errors of the source that made
that increment:

    sigma_pos = sum(k_pos(source_i) * |(dx_i, dy_i)|)      sigma_yaw = sum(k_yaw(...) * |dheading_i|)
    covariance = base + (sigma_pos^2, sigma_pos^2, 0, 0, 0, sigma_yaw^2)   (x, y, z, roll, pitch, yaw)

The increments are those between successive odometry samples (every ODOM_VELOCITY, 100 Hz by
default, whether or not `/odom` publishes that sample), the heading's wrapped into
[-pi, pi]. The errors are summed, not added in quadrature: odometry's errors are mostly
systematic (a wheel radius, the rollers' slip, a track width), which do not average out. The
growth never resets: the robot protocol has no way to set the odometry's pose, so its drift
only accumulates, for as long as the bridge runs (a bridge started anew starts from the base).
A jump of the pose (a robot that restarted, its odometry back at the origin) counts as motion:
the covariance then over-states the error, never under-states it.

Sources (`Robot.odometry_source`, and STATUS.heading_source for the heading):

| odometry source | position: `k_pos` | heading: `k_yaw` |
|---|---|---|
| WHEELS (no pods), WHEELS_PODS_SILENT | `position_error_wheels` | `heading_error_gyro` with heading_source GYRO, else `heading_error_wheels` |
| PODS2_GYRO | `position_error_pods` | `heading_error_gyro` with heading_source GYRO, else `heading_error_wheels` |
| PODS3 | `position_error_pods` | `heading_error_gyro` |

Any other name (a source this package does not know) counts as the wheels'.

This module needs no ROS: it is the bridge's arithmetic, tested on its own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

#: Default `position_error_wheels`: the largest position error along the path on the
#: simulator's built-in square at speed was 5.9 % of the distance driven, with wheel odometry.
POSITION_ERROR_WHEELS = 0.06
#: Default `position_error_pods`: the tracking pods' target, 1 % of the distance driven.
POSITION_ERROR_PODS = 0.01
#: Default `heading_error_wheels`, rad per rad turned.
HEADING_ERROR_WHEELS = 0.05
#: Default `heading_error_gyro`, rad per rad turned: a gyro (STATUS.heading_source GYRO) or
#: three pods (PODS3).
HEADING_ERROR_GYRO = 0.01

#: Odometry sources whose translation comes from tracking pods.
POD_SOURCES = frozenset({"PODS2_GYRO", "PODS3"})


@dataclasses.dataclass(frozen=True)
class ErrorRates:
    """The expected relative errors of the odometry's sources: m per m driven, rad per rad
    turned (the bridge's parameters of these names, with `position_error_` and
    `heading_error_` before them)."""

    position_wheels: float = POSITION_ERROR_WHEELS
    position_pods: float = POSITION_ERROR_PODS
    heading_wheels: float = HEADING_ERROR_WHEELS
    heading_gyro: float = HEADING_ERROR_GYRO

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{field.name} = {value!r}: must be a finite number >= 0")

    def position(self, source: str) -> float:
        """`k_pos` of odometry source `source` (ODOM_SLIP's, "WHEELS" without pods)."""
        return self.position_pods if source in POD_SOURCES else self.position_wheels

    def heading(self, source: str, heading_source: str | None) -> float:
        """`k_yaw` of odometry source `source` with STATUS.heading_source `heading_source`
        (None before the first STATUS): the gyro's with three pods or a live gyro."""
        if source == "PODS3" or heading_source == "GYRO":
            return self.heading_gyro
        return self.heading_wheels


def _wrap(angle: float) -> float:
    """`angle` in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


class CovarianceGrowth:
    """The pose covariance's growth from the odometry samples (see the module documentation).
    `base`: the diagonal at the start (x, y, z, roll, pitch, yaw variances: the bridge's
    `pose_covariance_diagonal`); `rates`: the sources' expected errors.

    Feed every odometry sample to `update`, in order; `pose_diagonal()` and
    `pose_covariance()` are the covariance now. Not thread-safe: one thread updates and reads
    it (the bridge's: the robot's receiving thread)."""

    def __init__(self, base: Sequence[float], rates: ErrorRates | None = None) -> None:
        if len(base) != 6 or not all(math.isfinite(v) and v >= 0 for v in base):
            raise ValueError(f"base = {list(base)!r}: must be 6 finite numbers >= 0")
        self.base = tuple(float(v) for v in base)
        self.rates = rates if rates is not None else ErrorRates()
        #: The standard deviations' growth so far: of x and y (m), of the heading (rad).
        self.position_stddev = 0.0
        self.heading_stddev = 0.0
        #: The distance driven (m) and the rotation turned (rad) so far, whatever the source.
        self.distance = 0.0
        self.rotation = 0.0
        self._last: tuple[float, float, float] | None = None

    def update(self, x: float, y: float, heading: float, source: str, heading_source: str | None) -> None:
        """One odometry sample: pose (m, m, rad) and the sources it came from (odometry source,
        STATUS.heading_source). The first sample only sets where the motion starts; one with a
        coordinate that is not finite is ignored."""
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(heading)):
            return
        if self._last is not None:
            lx, ly, lh = self._last
            moved = math.hypot(x - lx, y - ly)
            turned = abs(_wrap(heading - lh))
            self.distance += moved
            self.rotation += turned
            self.position_stddev += self.rates.position(source) * moved
            self.heading_stddev += self.rates.heading(source, heading_source) * turned
        self._last = (x, y, heading)

    def pose_diagonal(self) -> tuple[float, float, float, float, float, float]:
        """The variances now: the base plus the growth's squares on x, y and yaw."""
        bx, by, bz, broll, bpitch, byaw = self.base
        p2, h2 = self.position_stddev ** 2, self.heading_stddev ** 2
        return (bx + p2, by + p2, bz, broll, bpitch, byaw + h2)

    def pose_covariance(self) -> list[float]:
        """The 6x6 row-major matrix of `nav_msgs/msg/Odometry`'s pose.covariance: the diagonal
        above, zeros elsewhere."""
        matrix = [0.0] * 36
        for i, value in enumerate(self.pose_diagonal()):
            matrix[i * 7] = value
        return matrix
