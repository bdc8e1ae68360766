"""The robot protocol: the DBC file, its ids and value tables, and the version this package speaks.

Every layout comes from `mecanum_robot.dbc`, which the package carries (copied from the
repository's `dbc/` directory when the wheel is built, so there is one source of the layout).
cantools encodes and decodes every frame; this module only names what the rest of the package
needs from the database.
"""

from __future__ import annotations

import functools
import pathlib
import re
from importlib import resources

import cantools
from cantools.database.can import Database

#: The DBC file's name inside the package (and in the repository's `dbc/` directory).
DBC_NAME = "mecanum_robot.dbc"

#: The magic byte of ESTOP (the frame is refused without it).
ESTOP_MAGIC = 0xE5


def data_file(name: str) -> pathlib.Path:
    """A file the package carries from the repository's `dbc/` directory (the DBC, the EDS):
    the package's copy, or the repository's when the package is used from a source checkout
    (not installed)."""
    packaged = resources.files("mecanum_drive") / name
    if packaged.is_file():
        return pathlib.Path(str(packaged))
    source = pathlib.Path(__file__).resolve().parents[2] / "dbc" / name
    if source.is_file():
        return source
    raise FileNotFoundError(
        f"{name} is neither in the installed package nor at {source}: reinstall the package "
        "(pip install ./python from the repository)"
    )


def dbc_path() -> pathlib.Path:
    """The robot DBC."""
    return data_file(DBC_NAME)


@functools.cache
def database() -> Database:
    """The robot protocol's database, loaded strictly (overlapping signals are an error)."""
    db = cantools.database.load_file(str(dbc_path()), strict=True)
    if not isinstance(db, Database):
        raise TypeError(f"{dbc_path()} is not a CAN database")
    return db


@functools.cache
def protocol_version() -> int:
    """The protocol version of the DBC this package carries: the number in the database
    comment's first words, "Mecanum robot CAN protocol, version N"."""
    text = _database_comment()
    match = re.match(r"Mecanum robot CAN protocol, version (\d+)", text)
    if not match:
        raise ValueError(f"{dbc_path()}: its comment does not start with the protocol version: {text[:80]!r}")
    return int(match.group(1))


def _database_comment() -> str:
    """The DBC's database-level comment (its `CM_ "...";` line without an object), which
    cantools does not expose."""
    text = dbc_path().read_text(encoding="utf-8", errors="replace")
    match = re.search(r'^CM_ "((?:[^"\\]|\\.)*)";', text, re.MULTILINE)
    return match.group(1) if match else ""


def frame_id(name: str) -> int:
    """The arbitration id of message `name` (ESTOP, TWIST_CMD, ...)."""
    return database().get_message_by_name(name).frame_id


def choices(message: str, signal: str) -> dict[int, str]:
    """The value table of `message.signal`, raw value to name (STATUS.state: 0 DISABLED...)."""
    sig = database().get_message_by_name(message).get_signal_by_name(signal)
    return {int(k): str(v) for k, v in (sig.choices or {}).items()}


def signal_range(message: str, signal: str) -> tuple[float, float]:
    """The physical range (minimum, maximum) the DBC gives `message.signal`."""
    sig = database().get_message_by_name(message).get_signal_by_name(signal)
    assert sig.minimum is not None and sig.maximum is not None, f"{message}.{signal} has no range"
    return float(sig.minimum), float(sig.maximum)
