"""The bring-up check: which wheel turns, which way, and the configuration lines that fix it.

A new robot's first hour goes to signs and wheel order. With the robot on blocks,
`mecanum-drive check --config robot.toml` drives each configured wheel in turn through the
firmware's WHEEL_TEST and asks the person watching which wheel turned and which way (no
encoder can tell: the drive that turned reports its own motion with the sign the
configuration gives it). `diagnose` turns the four answers into the fix: configured wheel i
drove the physical wheel p (p is on the id the configuration gives i) in direction d, so
wheel p's id is the configured ids[i], and its motor is mounted as configured for i if d is
forward, the other way if backward.

The simulator computes the same rule (`hostsim check`, the hostsim crate's `bringup`
module); the tests hold the two to the same answers on every miswiring of the examples.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

WHEELS = ("FL", "FR", "RL", "RR")


@dataclasses.dataclass(frozen=True)
class Wiring:
    """How a robot is wired: a drive id per wheel (`esc_ids` for DJI, `node_ids` for ODrive)
    and its mounting (`inverted`), wheel order FL, FR, RL, RR."""

    ids: tuple[int, int, int, int]
    inverted: tuple[bool, bool, bool, bool]
    ids_key: str  # "esc_ids" or "node_ids"

    @classmethod
    def from_config(cls, path: str | pathlib.Path) -> Wiring:
        """The wiring of a firmware configuration file (its [drive] section). Raises ValueError
        naming the file and the key that is missing or wrong."""
        path = pathlib.Path(path)
        try:
            drive = tomllib.loads(path.read_text())["drive"]
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise ValueError(f"{path}: {err}") from err
        except KeyError as err:
            raise ValueError(f"{path}: no [drive] section") from err
        key = {"dji": "esc_ids", "odrive": "node_ids"}.get(drive.get("protocol"))
        if key is None:
            raise ValueError(f"{path}: drive.protocol = {drive.get('protocol')!r}: expected \"dji\" or \"odrive\"")
        ids, inverted = drive.get(key), drive.get("inverted", [False] * 4)
        if not (isinstance(ids, list) and len(ids) == 4 and all(isinstance(i, int) for i in ids)):
            raise ValueError(f"{path}: drive.{key} = {ids!r}: expected four ids")
        if not (isinstance(inverted, list) and len(inverted) == 4 and all(isinstance(i, bool) for i in inverted)):
            raise ValueError(f"{path}: drive.inverted = {inverted!r}: expected four booleans")
        return cls(tuple(ids), tuple(inverted), key)


@dataclasses.dataclass(frozen=True)
class Seen:
    """What the person watching saw when one configured wheel was tested."""

    wheel: int  # the wheel that turned, 0-3
    forward: bool  # it turned so as to roll the robot forward


def parse_seen(text: str) -> Seen | None:
    """An answer: a wheel (FL, FR, RL, RR, any case) and a direction (f/forward, b/backward),
    as "RL b", "rl backward" or "RL-" / "RL+"; "none" or "-" when no wheel turned. Raises
    ValueError naming the answer."""
    t = text.strip().lower()
    if t in ("none", "-", "n", "no"):
        return None
    m = re.fullmatch(r"(fl|fr|rl|rr)\s*(\+|-|f|forward|b|back|backward|backwards)", t)
    if not m:
        raise ValueError(f"{text!r}: expected a wheel and a direction, e.g. 'RL b' or 'FL forward', or 'none'")
    return Seen(WHEELS.index(m.group(1).upper()), m.group(2) in ("+", "f", "forward"))


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """Per configured wheel a verdict; the corrected wiring if the answers determine it
    (every wheel seen turning, each physical wheel once), else why not."""

    verdicts: tuple[str, str, str, str]
    right: bool
    fixed: Wiring | None
    unresolved: str | None

    def fix_lines(self, configured: Wiring) -> list[str]:
        """The [drive] lines that fix the configuration: only the keys that change."""
        if self.fixed is None:
            return []
        lines = []
        if self.fixed.ids != configured.ids:
            lines.append(f"{configured.ids_key} = [{', '.join(str(i) for i in self.fixed.ids)}]")
        if self.fixed.inverted != configured.inverted:
            lines.append(f"inverted = [{', '.join(str(i).lower() for i in self.fixed.inverted)}]")
        return lines


def diagnose(configured: Wiring, seen: list[Seen | None]) -> Diagnosis:
    """The wiring the answers imply (see the module's documentation)."""
    if len(seen) != 4:
        raise ValueError(f"{len(seen)} answers: expected one per wheel (4)")
    verdicts = []
    ids, inverted = list(configured.ids), list(configured.inverted)
    claimed: dict[int, int] = {}
    unresolved = None
    for i, s in enumerate(seen):
        name = WHEELS[i]
        if s is None:
            verdicts.append("no wheel turned")
            unresolved = unresolved or (
                f"no wheel turned when {name} was tested: no drive answers to {configured.ids_key[:-1]} "
                f"{configured.ids[i]}, or it drives no wheel"
            )
            continue
        way = "forward" if s.forward else "backward"
        if s.wheel == i:
            verdicts.append(f"{name} turned forward: right" if s.forward else
                            f"{name} turned backward: its motor is mounted the other way than configured")
        else:
            verdicts.append(f"{WHEELS[s.wheel]} turned {way} instead: wired to the wrong wheel")
        if s.wheel in claimed:
            unresolved = unresolved or (
                f"{WHEELS[s.wheel]} turned when {WHEELS[claimed[s.wheel]]} and when {name} were tested: "
                "one drive answers to two ids?"
            )
            continue
        claimed[s.wheel] = i
        ids[s.wheel] = configured.ids[i]
        inverted[s.wheel] = configured.inverted[i] ^ (not s.forward)
    right = all(s is not None and s.wheel == i and s.forward for i, s in enumerate(seen))
    fixed = None if unresolved else Wiring(tuple(ids), tuple(inverted), configured.ids_key)  # type: ignore[arg-type]
    return Diagnosis(tuple(verdicts), right, fixed, unresolved)  # type: ignore[arg-type]
