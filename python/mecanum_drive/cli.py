"""`mecanum-drive`: the robot from a shell. `mecanum-drive --help` lists the commands."""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import sys
import time
from collections.abc import Sequence
from typing import Any

import can

from . import params, protocol, ros2, sweep
from .robot import NotResponding, Robot, RobotError

#: Teleop: a key held down repeats (the terminal's auto-repeat); when no key has come for
#: this long, every key is taken as released and the setpoint goes to zero.
TELEOP_RELEASE_S = 0.3

#: Teleop keys: key -> (vx, vy, wz) direction; speeds are the --speed and --turn options.
TELEOP_KEYS = {
    "w": (1, 0, 0),
    "s": (-1, 0, 0),
    "a": (0, 1, 0),
    "d": (0, -1, 0),
    "q": (0, 0, 1),
    "e": (0, 0, -1),
}

TELEOP_HELP = """mecanum-drive teleop: hold a key to drive, release it to stop
  w / s  forward / back      a / d  strafe left / right      q / e  turn left / right
  space  stop                x      E-STOP (latches; `r` resets)   r  reset and enable
  Ctrl-C or Esc  quit (the robot is stopped and disabled)"""


#: --channel and --interface when not given (None in the namespace: `ros2` tells given from not).
DEFAULT_CHANNEL = "can0"
DEFAULT_INTERFACE = "socketcan"


def _robot(args: argparse.Namespace) -> Robot:
    kwargs: dict[str, object] = {"rate_hz": args.rate}
    if args.bitrate is not None:
        kwargs["bitrate"] = args.bitrate
    channel = args.channel or DEFAULT_CHANNEL
    interface = args.interface or DEFAULT_INTERFACE
    try:
        return Robot.open(channel=channel, interface=interface, **kwargs)
    except (can.CanError, OSError, ValueError) as err:
        raise SystemExit(f"mecanum-drive: cannot open {interface} channel {channel}: {err}") from err


def cmd_param(args: argparse.Namespace) -> int:
    """`param list|get|set|save|restore|dump`: the robot's parameters over its SDO service
    (docs/protocol.md, "Parameters")."""
    known = params.table()
    if args.action in ("save", "restore", "dump") and args.names:
        raise ValueError(f"{args.action} takes no names: param {args.action}"
                         + (" [--output FILE]" if args.action == "dump" else ""))
    if args.output is not None and args.action != "dump":
        raise ValueError("--output is for dump: param dump --output robot.toml")
    names = args.names if args.action != "set" else [args.names[0]] if args.names else []
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"no parameter {unknown[0]!r} (`mecanum-drive param list` lists them)")
    if args.action == "list":
        for p in known.values():
            high = "" if p.high == math.inf else f"{p.high:g}"
            print(f"{p.name:32} {p.change:8} {p.low:g}..{high}  {p.doc}")
        return 0
    value = math.nan
    if args.action == "set":
        if len(args.names) != 2:
            raise ValueError("set takes a name and a value: param set gains.kp 1.5")
        try:
            value = float(args.names[1])
        except ValueError:
            raise ValueError(f"{args.names[0]}: {args.names[1]!r} is not a number") from None
        known[args.names[0]].encode(value)  # a value the type cannot hold: refused before the bus
    channel = args.channel or DEFAULT_CHANNEL
    interface = args.interface or DEFAULT_INTERFACE
    node = args.node
    response = [{"can_id": 0x580 + node, "can_mask": 0x7FF, "extended": False}]
    try:
        bus = can.Bus(channel=channel, interface=interface, can_filters=response,
                      **({"bitrate": args.bitrate} if args.bitrate else {}))
    except (can.CanError, OSError, ValueError) as err:
        raise SystemExit(f"mecanum-drive: cannot open {interface} channel {channel}: {err}") from err
    with bus:
        client = params.Client(bus, node=node, timeout=args.timeout)
        if args.action == "set":
            p = known[args.names[0]]
            client.set(p, value)
            print(f"{p.name} = {client.get(p):g}")
            return 0
        if args.action in ("save", "restore"):
            if args.action == "save":
                client.save()
            else:
                client.restore()
            verb = "saved" if args.action == "save" else "restored"
            try:
                info = client.info()
            except params.ParamError as err:  # stored all the same: the robot answered the save
                print(f"{verb}; the ids could not be read after it: {err}")
                return 0
            print(_stored(verb, info))
            return 0
        if args.action == "dump":
            return _dump(client, known, args.output)
        values = {}
        for name in names or known:
            try:
                values[name] = client.get(known[name])
            except params.ParamError as err:
                if names or err.code != params.NOT_IN_CONFIGURATION:
                    raise
        if args.json:
            print(json.dumps(values))
        else:
            for name, value in values.items():
                print(f"{name} = {value:g}")
    return 0


def _stored(verb: str, info: params.Info) -> str:
    """What a save or restore did, from object 0x2100 read after it."""
    if verb == "restored":
        text = f"restored: the built-in config 0x{info.builtin_id:04x} is in force, saved as record {info.saved_seq}"
    else:
        text = f"saved: config 0x{info.saved_id:04x} as record {info.saved_seq}"
    text += "; a restart runs it"
    if info.running_id != info.saved_id:  # a change since (another client's set)
        text += f" (config 0x{info.running_id:04x} is in force now)"
    return text


def _toml_number(p: params.Param, value: float) -> str:
    """A TOML number: an integer type's as an integer; a REAL32 in the fewest digits that
    read back as the same float32 (`gains.kp` 1.2, not 1.2000000476837158)."""
    if p.data_type != 0x0008:
        return str(int(value))
    if not math.isfinite(value):
        return "nan" if math.isnan(value) else "inf" if value > 0 else "-inf"
    exact = struct.pack("<f", value)
    text = repr(value)  # the float32 widened to a double: exact, if long
    for digits in range(1, 10):  # 9 significant digits always read back as the same float32
        short = f"{value:.{digits}g}"
        try:
            if struct.pack("<f", float(short)) == exact:
                text = short
                break
        except OverflowError:  # rounded up beyond float32's range: more digits
            continue
    return text if any(c in text for c in ".en") else text + ".0"


def _dump(client: params.Client, known: dict[str, params.Param], output: str | None) -> int:
    """`param dump`: every parameter the robot has as TOML, to stdout or to `output`
    (written whole to OUTPUT.tmp, then renamed: a failed dump leaves an old file as it was)."""
    info = client.info()
    lines = []
    for p in known.values():
        try:
            value = client.get(p)
        except params.ParamError as err:
            if err.code != params.NOT_IN_CONFIGURATION:
                raise
            continue
        lines.append(f"{json.dumps(p.name)} = {_toml_number(p, value)}")
    running = client.info().running_id
    if running != info.running_id:
        raise params.ParamError(f"dump: the configuration changed while it was read (0x{info.running_id:04x} -> "
                                f"0x{running:04x}); dump again")
    restart = (f"the saved set 0x{info.saved_id:04x} (record {info.saved_seq})" if info.saved_seq
               else f"the built-in set 0x{info.saved_id:04x} (none saved)")
    text = "\n".join([
        f"# mecanum-drive param dump of node {client.node}: running config 0x{info.running_id:04x}, "
        f"built-in config 0x{info.builtin_id:04x}; a restart runs {restart}.",
        f"# {len(lines)} parameters, each by its name (`mecanum-drive param list`); REAL32 values "
        "in the fewest digits that read back as the same float32.",
        *lines, "",
    ])
    if output is None:
        sys.stdout.write(text)
        return 0
    tmp = f"{output}.tmp"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, output)
    except OSError as err:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise SystemExit(f"mecanum-drive param: cannot write {output}: {err}") from err
    print(f"dumped {len(lines)} parameters of config 0x{info.running_id:04x} to {output}")
    return 0


def _wait_first_status(robot: Robot, timeout: float) -> None:
    robot.request_status()
    deadline = time.monotonic() + timeout
    while robot.status is None or robot.heartbeat is None:
        if time.monotonic() > deadline:
            robot.check()  # names what is wrong: ProtocolMismatch, a fault
            raise NotResponding(
                f"no HEARTBEAT and STATUS from the robot within {timeout} s on {robot.bus.channel_info}: "
                "is it powered, on this bus, at the same bitrate?"
            )
        time.sleep(0.01)


def _status_dict(robot: Robot) -> dict[str, Any]:
    s, o, h, c, slip = robot.status, robot.odometry, robot.heartbeat, robot.counters, robot.slip
    return {
        "state": s.state if s else None,
        "fault": s.fault if s else None,
        "motors_online": list(s.motors_online) if s else None,
        "heading_source": s.heading_source if s else None,
        # ODOM_SLIP (protocol version 7), from a robot with tracking pods only: without it the
        # source is WHEELS and the slip null.
        "odometry_source": "WHEELS" if slip is None else slip.source,
        "slip": None if slip is None else {"vx": slip.vx, "vy": slip.vy, "wz": slip.wz},
        "rx_errors": s.rx_errors if s else None,
        "unknown_ids": s.unknown_ids if s else None,
        "counters": None if c is None else {
            "repeated_seq": c.repeated_seq, "wrong_dlc": c.wrong_dlc,
            "out_of_range": c.out_of_range, "non_finite": c.non_finite,
        },
        "odometry": None if o is None else {"x": o.x, "y": o.y, "heading": o.heading, "vx": o.vx, "vy": o.vy, "wz": o.wz},
        "uptime_s": h.uptime_ms / 1000 if h else None,
        "protocol_version": h.protocol_version if h else None,
        "config_id": f"0x{h.config_id:04x}" if h else None,
        "responding": robot.responding,
    }


def _status_text(robot: Robot) -> str:
    d = _status_dict(robot)
    wheels = "  ".join(f"{n} {'on' if up else 'OFF'}" for n, up in zip(("FL", "FR", "RL", "RR"), d["motors_online"] or []))
    o = d["odometry"]
    lines = [
        f"state     {d['state']}   fault {d['fault']}   {'responding' if d['responding'] else 'NOT RESPONDING'}",
        f"motors    {wheels}",
        f"odometry  x {o['x']:+.4f} m  y {o['y']:+.4f} m  heading {math.degrees(o['heading']):+.2f}°" if o else "odometry  (none yet)",
        f"velocity  vx {o['vx']:+.3f} m/s  vy {o['vy']:+.3f} m/s  wz {o['wz']:+.3f} rad/s" if o else "",
        f"heading   from {d['heading_source']}" if d["heading_source"] not in (None, "WHEELS") else "",
        # Only from a robot with tracking pods (it sends ODOM_SLIP).
        "" if d["slip"] is None else "slip      vx {vx:+.3f} m/s  vy {vy:+.3f} m/s  wz {wz:+.3f} rad/s".format(**d["slip"])
        + f"   odometry from {d['odometry_source']}",
        f"counters  rejected frames {d['rx_errors']}   unknown ids {d['unknown_ids']}",
        "" if d["counters"] is None else "          repeated twists {repeated_seq}   wrong DLC {wrong_dlc}   "
        "out of range {out_of_range}   not finite {non_finite}".format(**d["counters"]),
        f"robot     up {d['uptime_s']:.1f} s, protocol version {d['protocol_version']}, "
        f"configuration id {d['config_id']}" if d["uptime_s"] is not None else "",
    ]
    return "\n".join(line for line in lines if line)


def cmd_status(args: argparse.Namespace) -> int:
    with _robot(args) as robot:
        _wait_first_status(robot, args.timeout)
        if args.once or args.json:
            time.sleep(0.05)  # one odometry period
            print(json.dumps(_status_dict(robot)) if args.json else _status_text(robot))
            return 0
        try:
            while True:
                sys.stdout.write("\x1b[H\x1b[2J" + _status_text(robot) + "\n\n(Ctrl-C to quit)\n")
                sys.stdout.flush()
                time.sleep(0.2)
        except KeyboardInterrupt:
            return 0


def cmd_drive(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise SystemExit(f"mecanum-drive: --duration {args.duration}: must be a positive number of seconds")
    with _robot(args) as robot:
        _wait_first_status(robot, args.timeout)
        robot.enable()
        robot.wait_state("ENABLED", timeout=args.timeout)
        robot.drive(args.vx, args.vy, args.wz)
        end = time.monotonic() + args.duration
        while time.monotonic() < end:
            robot.check()
            time.sleep(min(0.02, max(0.0, end - time.monotonic())))
        robot.stop()
        time.sleep(0.3)  # let it come to rest before the disable
        print(_status_text(robot))
        # The command ends with the robot disabled, as the robot says (not merely asked).
        robot.disable()
        robot.wait_state("DISABLED", timeout=args.timeout)
        print("disabled: the robot reports DISABLED")
    return 0


def cmd_estop(args: argparse.Namespace) -> int:
    with _robot(args) as robot:
        robot.estop()
        try:
            robot.wait_state("ESTOP", timeout=args.timeout)
        except (TimeoutError, RobotError) as err:
            print(f"mecanum-drive: ESTOP sent; {err}", file=sys.stderr)
            return 1
        print("ESTOP: the robot is stopped and latched (`mecanum-drive reset` clears it)")
    return 0


def cmd_reset(args: argparse.Namespace) -> int:
    with _robot(args) as robot:
        robot.reset()
        robot.wait_state("DISABLED", timeout=args.timeout)
        print("reset: the robot is DISABLED, fault cleared")
    return 0


def cmd_teleop(args: argparse.Namespace) -> int:
    import curses

    with _robot(args) as robot:
        _wait_first_status(robot, args.timeout)

        def loop(screen: curses.window) -> None:
            curses.curs_set(0)
            # Enabled once the terminal is set up: setting it up can hold the interpreter
            # for longer than the robot's command timeout on a slow machine, and the
            # keep-alive thread would miss its frames.
            robot.enable()
            robot.wait_state("ENABLED", timeout=args.timeout)
            # getch waits up to 20 ms for a key: the loop sleeps in it rather than spinning,
            # so the keep-alive and receiving threads keep their time on a slow machine.
            screen.timeout(20)
            last_key, direction, message = 0.0, (0, 0, 0), ""
            twist: tuple[float, float, float] = (0.0, 0.0, 0.0)
            next_draw = 0.0
            while True:
                key = screen.getch()
                now = time.monotonic()
                if key in (27, 3):  # Esc, Ctrl-C in raw mode
                    return
                if key != -1:
                    ch = chr(key) if 0 <= key < 256 else ""
                    if ch in TELEOP_KEYS:
                        direction, last_key = TELEOP_KEYS[ch], now
                    elif ch == " ":
                        direction, last_key = (0, 0, 0), 0.0
                    elif ch == "x":
                        robot.estop()
                        direction, message = (0, 0, 0), "E-STOP sent: `r` resets and enables"
                    elif ch == "r":
                        robot.reset()
                        robot.wait_state("DISABLED", timeout=args.timeout)
                        robot.enable()
                        message = "reset and enabled"
                if now - last_key > TELEOP_RELEASE_S:
                    direction = (0, 0, 0)
                wanted = (direction[0] * args.speed, direction[1] * args.speed, direction[2] * args.turn)
                if wanted != twist or key != -1:
                    twist = wanted
                    try:
                        robot.drive(*twist)
                    except RobotError as err:
                        robot.stop()
                        twist, message = (0.0, 0.0, 0.0), f"robot: {err}"
                if now >= next_draw or key != -1:
                    next_draw = now + 0.1
                    screen.erase()
                    text = "\n".join([
                        TELEOP_HELP,
                        "",
                        f"twist     vx {twist[0]:+.2f} m/s  vy {twist[1]:+.2f} m/s  wz {twist[2]:+.2f} rad/s",
                        _status_text(robot),
                        "",
                        message,
                    ])
                    try:
                        screen.addstr(0, 0, text)
                    except curses.error:
                        pass  # a terminal too small for all of it shows what fits
                    screen.refresh()

        try:
            curses.wrapper(loop)
        except KeyboardInterrupt:
            pass
    print("teleop: stopped, the robot is disabled")
    return 0


CHECK_INTRO = """mecanum-drive check: which wheel turns, and which way
Put the robot on blocks so that no wheel touches the ground, and keep hands clear of the
wheels. Each wheel in turn is driven gently forward (the firmware limits it to a quarter of
its current limit and the time given); watch which wheel turns and which way."""


def cmd_check(args: argparse.Namespace) -> int:
    try:
        return _check(args)
    except (KeyboardInterrupt, EOFError):
        # The robot's context has disabled it already (a wheel test also ends on disable).
        print("\ncheck: stopped; the robot is disabled", file=sys.stderr)
        return 130


def _check(args: argparse.Namespace) -> int:
    from .check import WHEELS, Seen, Wiring, diagnose, parse_seen

    configured = Wiring.from_config(args.config)
    answers: list[str] | None = None
    if args.observed is not None:
        answers = [a for a in args.observed.split(",") if a.strip()]
        if len(answers) != 4:
            raise SystemExit(f"mecanum-drive check: --observed {args.observed!r}: expected four answers, FL's first")
        for a in answers:
            parse_seen(a)  # a bad answer fails before any wheel turns
    print(CHECK_INTRO)
    if answers is None and not args.yes:
        input("Press Enter when the robot is on blocks (Ctrl-C to stop) ")
    seen: list[Seen | None] = []
    with _robot(args) as robot:
        _wait_first_status(robot, args.timeout)
        for i, name in enumerate(WHEELS):
            print(f"\n{name} ({configured.ids_key[:-1]} {configured.ids[i]}): driving it at {args.speed} rad/s "
                  f"for {args.duration} s ...", flush=True)
            result = robot.wheel_test(i, args.speed, args.duration, timeout=args.timeout)
            print(f"  firmware: {result.outcome}, its encoder turned {result.angle:+.2f} rad, "
                  f"peak current {result.peak_current:+.2f} A")
            if result.outcome == "REFUSED":
                raise SystemExit("mecanum-drive check: the robot refused the test: it runs only when DISABLED "
                                 "(`mecanum-drive reset` clears a fault)")
            if result.outcome == "FAULT":
                status = robot.status
                print(f"  the robot faulted ({status.fault if status else 'unknown'}); reset it after the check")
            if answers is not None:
                answer = answers[i]
                print(f"  seen: {answer}")
            else:
                answer = input("  Which wheel turned, and which way? (e.g. 'FL f', 'RR b', 'none') ")
            # --observed answers parsed above; a typed one is asked again until it parses.
            while True:
                try:
                    seen.append(parse_seen(answer))
                    break
                except ValueError as err:
                    answer = input(f"  {err}: ")
            if result.outcome == "FAULT":
                robot.reset()
                robot.wait_state("DISABLED", timeout=args.timeout)
    d = diagnose(configured, seen)
    print()
    for name, verdict in zip(WHEELS, d.verdicts):
        print(f"{name}: {verdict}")
    if d.right:
        print("wiring: as configured")
        return 0
    if d.fixed is None:
        print(f"wiring: cannot be fixed from these answers: {d.unresolved}")
        return 3
    print(f"wiring: wrong; in {args.config}, [drive] section:")
    for line in d.fix_lines(configured):
        print(f"    {line}")
    return 3


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mecanum-drive",
        description=(
            "Drive a mecanum robot running the mecanum-drive firmware over CAN (robot protocol "
            f"version {protocol.protocol_version()}). Every command stops the robot's stream, sends a "
            "zero twist and disables the robot when it ends, however it ends."
        ),
        epilog="Bring a SocketCAN interface up first: sudo ip link set can0 up type can bitrate 1000000",
    )
    parser.add_argument("--channel", default=None, help=f"CAN channel (default {DEFAULT_CHANNEL}; vcan0 for tests)")
    parser.add_argument(
        "--interface", default=None,
        help=f"python-can interface: {DEFAULT_INTERFACE} (default), slcan, pcan, gs_usb, kvaser, virtual, ...",
    )
    parser.add_argument("--bitrate", type=int, default=None, help="bitrate for adapters that set it (slcan, pcan); SocketCAN sets it with ip link")
    parser.add_argument("--rate", type=float, default=50.0, help="keep-alive rate of the twist stream, Hz (default 50)")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the robot's answers (default 2)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("status", help="live view of state, fault, motors, odometry (its source and the slip "
                       "with tracking pods), counters")
    p.add_argument("--once", action="store_true", help="print one view and exit")
    p.add_argument("--json", action="store_true", help="print one view as JSON and exit")
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("drive", help="enable, drive a twist for a time, stop, disable")
    p.add_argument("--vx", type=float, default=0.0, help="forward speed, m/s")
    p.add_argument("--vy", type=float, default=0.0, help="leftward speed, m/s")
    p.add_argument("--wz", type=float, default=0.0, help="yaw rate, rad/s (counter-clockwise)")
    p.add_argument("--duration", type=float, required=True, help="seconds to drive")
    p.set_defaults(func=cmd_drive)

    p = sub.add_parser("estop", help="emergency stop (latched until reset)")
    p.set_defaults(func=cmd_estop)
    p = sub.add_parser("reset", help="clear a fault or the e-stop latch (the robot stays disabled)")
    p.set_defaults(func=cmd_reset)

    p = sub.add_parser("teleop", help="drive with the keyboard in a terminal (keys shown on screen)")
    p.add_argument("--speed", type=float, default=0.3, help="linear speed of a key, m/s (default 0.3)")
    p.add_argument("--turn", type=float, default=0.8, help="yaw rate of a key, rad/s (default 0.8)")
    p.set_defaults(func=cmd_teleop)

    p = sub.add_parser(
        "check", help="bring-up check, robot on blocks: which wheel turns, which way; prints the config fix",
        description=CHECK_INTRO + "\n\nAfter each wheel you say what you saw: a wheel and a direction "
        "(FL/FR/RL/RR, f or b), or none. The check then prints, per wheel, what is wrong and the [drive] "
        "lines (esc_ids or node_ids, inverted) that fix the configuration. Exit status: 0 wired as "
        "configured, 3 miswired (the fix is printed), 1 an error.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", required=True, help="the robot's firmware configuration (TOML, as config/dji_m3508.toml)")
    p.add_argument("--speed", type=float, default=3.0, help="wheel speed of each test, rad/s (default 3, at most 10)")
    p.add_argument("--duration", type=float, default=1.0, help="length of each test, s (default 1, at most 3)")
    p.add_argument("--observed", default=None, metavar="FL,FR,RL,RR",
                   help="the four answers instead of asking, FL's test first, e.g. 'FL f,FR b,RL f,RR f'")
    p.add_argument("--yes", action="store_true", help="do not wait for Enter: the robot is on blocks")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser(
        "param", help="read, set, save, restore and dump the robot's parameters over CAN (gains, limits, timeouts, ...)",
        description="The robot's parameters, read and set over its CANopen SDO service on node --node "
        "(docs/protocol.md, \"Parameters\"). `list` prints every parameter with when it may change "
        "(live: any time; disabled: only while the robot is disabled; fixed: not over CAN) and its range; "
        "`get [NAME ...]` prints values (all the robot has without a name); `set NAME VALUE` sets one and "
        "prints the value then in force (until a restart). `save` saves the configuration in force: a "
        "restart runs it; `restore` puts the built-in configuration in force and saves it (only while "
        "disabled); both print the configuration's id and the saved record. `dump [--output FILE]` "
        "writes every parameter the robot has as TOML (\"gains.kp\" = 1.5), a header naming the node "
        "and the configurations' ids. A refusal names the parameter and the reason (exit status 1).",
    )
    p.add_argument("action", choices=["list", "get", "set", "save", "restore", "dump"],
                   help="list, get, set, save, restore or dump")
    p.add_argument("names", nargs="*", metavar="NAME [VALUE]", help="parameter names; for set, a name and a value")
    p.add_argument("--node", type=int, default=params.DEFAULT_NODE,
                   help=f"the robot's node id (default {params.DEFAULT_NODE}; with CiA 402 drives, drive.master_node)")
    p.add_argument("--json", action="store_true", help="get: print one JSON object")
    p.add_argument("--output", default=None, metavar="FILE",
                   help="dump: write the TOML to FILE (through FILE.tmp: a failed dump leaves FILE as it was)")
    p.set_defaults(func=cmd_param)

    p = sub.add_parser(
        "ros2", help="the ROS 2 bridge: /cmd_vel in; /odom, /tf, /diagnostics out; enable/disable/reset/estop services",
        description="The ROS 2 node mecanum_drive (needs the ros2 extra: pip install './python[ros2]', or a "
        "sourced ROS 2 installation). Runs until Ctrl-C or SIGTERM, then leaves the robot disabled.",
        epilog="ROS 2 arguments follow --ros-args, e.g. --ros-args -p cmd_vel_timeout:=0.5 -p "
        "enable_on_start:=true --params-file bridge.yaml. --channel, --interface and --bitrate here or "
        "before the command set the parameters of those names.",
    )
    ros2.add_arguments(p, dest_prefix="ros2_")
    p.set_defaults(func=cmd_ros2)

    p = sub.add_parser(
        "sweep", help="a hostsim sweep shared out over a Ray cluster (--ray local: this machine's cores)",
        description="Runs `hostsim sweep SCENARIO ...` over a Ray cluster: the local hostsim checks the "
        "sweep and says its runs, each shard of --shard-size runs is a Ray task (hostsim on one CPU of a "
        "node, the binary shipped with the job unless --hostsim-on-nodes), each finished shard is written "
        "to OUT/parts as it comes, and the local hostsim merges them into OUT/sweep.csv, sweep.jsonl and "
        "sweep.png, byte for byte as one hostsim sweep writes them. A shard whose worker died is run "
        "again (--retries); Ctrl-C keeps the finished shards, --resume runs the rest. Needs the ray "
        "extra: pip install './python[ray]'. docs/sweeps-on-ray.md: KubeRay and Slurm.",
    )
    sweep.add_arguments(p)
    p.set_defaults(func=sweep.run)
    return parser


def cmd_ros2(args: argparse.Namespace) -> int:
    """The ROS 2 bridge (mecanum_drive.ros2); its options win over the global ones."""
    def pick(name: str) -> Any:
        own = getattr(args, f"ros2_{name}")
        return own if own is not None else getattr(args, name)

    return ros2.run(args.ros_args, channel=pick("channel"), interface=pick("interface"),
                    bitrate=pick("bitrate"))


def main(argv: Sequence[str] | None = None) -> int:
    own, ros_args = ros2.split_ros_args(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(own)
    if ros_args and args.command != "ros2":
        parser.error(f"--ros-args is for the ros2 command, not {args.command}")
    args.ros_args = ros_args
    try:
        return int(args.func(args))
    except (RobotError, TimeoutError, ValueError, params.ParamError) as err:
        print(f"mecanum-drive {args.command}: {err}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # `| head` closed the output: not an error worth a traceback (nor one at exit).
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
