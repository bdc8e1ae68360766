"""The ROS 2 bridge: `/cmd_vel` in, `/odom`, `/tf` and `/diagnostics` out, services for the
robot's modes, over the robot protocol.

Start it with `mecanum-drive ros2 --channel can0` (or `python -m mecanum_drive.ros2`); ROS 2
arguments follow `--ros-args` as for any ROS 2 node:

    mecanum-drive ros2 --channel can0 --ros-args -p cmd_vel_timeout:=0.5 -p enable_on_start:=true

It needs ROS 2's Python client (rclpy) and the message packages: `pip install
'./python[ros2]'` installs ROS 2 Jazzy's wheels from PyPI (x86-64 Linux, CPython 3.10-3.13),
or a ROS 2 installation provides them (`source /opt/ros/jazzy/setup.bash`, and the package
installed without the extra where that Python sees it). This module imports none of them
until the bridge starts, so the rest of the package works without them; the node itself is
`mecanum_drive.ros2.bridge`, which documents the topics, services and parameters.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

#: How to get the ROS 2 Python client, for the message when it is missing.
INSTALL_HINT = (
    "install the package with its ros2 extra: pip install './python[ros2]' from the repository "
    "(ROS 2 Jazzy's wheels from PyPI: x86-64 Linux, Python 3.10-3.13), or run it where a ROS 2 "
    "installation is sourced (source /opt/ros/jazzy/setup.bash), with this package installed "
    "for that Python"
)


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Splits a command line at `--ros-args`: (the bridge's own arguments, the ROS 2 arguments
    from `--ros-args` on, which rclpy parses: `-p name:=value`, `--params-file FILE`, `-r`,
    `--log-level`, ...)."""
    argv = list(argv)
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []


def add_arguments(parser: argparse.ArgumentParser, dest_prefix: str = "") -> None:
    """The bridge's own options, stored as `{dest_prefix}channel`, ...: each is also a ROS
    parameter, and the option wins over `-p`."""
    parser.add_argument("--channel", dest=f"{dest_prefix}channel", default=None, metavar="CHANNEL",
                        help="CAN channel (parameter `channel`, default can0)")
    parser.add_argument("--interface", dest=f"{dest_prefix}interface", default=None, metavar="INTERFACE",
                        help="python-can interface (parameter `interface`, default socketcan)")
    parser.add_argument("--bitrate", dest=f"{dest_prefix}bitrate", type=int, default=None, metavar="BITRATE",
                        help="bitrate for adapters that set it (parameter `bitrate`; 0: leave it)")


def run(ros_args: Sequence[str], *, channel: str | None = None, interface: str | None = None,
        bitrate: int | None = None, prog: str = "mecanum-drive ros2") -> int:
    """Runs the bridge until Ctrl-C or SIGTERM, with `ros_args` (from `--ros-args` on) for
    rclpy; `channel`, `interface` and `bitrate`, where given, override those parameters.
    Returns the exit status; prints why to stderr when the ROS 2 client is missing."""
    try:
        from . import bridge
    except ImportError as err:
        print(f"{prog}: the ROS 2 Python client is not importable ({err}); {INSTALL_HINT}.", file=sys.stderr)
        return 1
    overrides: dict[str, str | int] = {}
    if channel is not None:
        overrides["channel"] = channel
    if interface is not None:
        overrides["interface"] = interface
    if bitrate is not None:
        overrides["bitrate"] = bitrate
    return bridge.main(list(ros_args), overrides=overrides, prog=prog)


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m mecanum_drive.ros2 [--channel CAN] [--ros-args ...]`."""
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="python -m mecanum_drive.ros2",
        description="The ROS 2 bridge of the mecanum robot (the same as `mecanum-drive ros2`).",
        epilog="ROS 2 arguments follow --ros-args: -p name:=value, --params-file FILE, -r from:=to.",
    )
    add_arguments(parser)
    args = parser.parse_args(own)
    return run(ros_args, channel=args.channel, interface=args.interface, bitrate=args.bitrate,
               prog="python -m mecanum_drive.ros2")
