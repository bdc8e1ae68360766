"""The robot's parameters over CAN: the table from its EDS, and an expedited SDO client.

The robot serves its parameters as a CANopen SDO server on its node id N (127, or its CiA
402 drives' master node): requests on 0x600 + N, responses on 0x580 + N
(docs/protocol.md, "Parameters"). The description of every parameter (name, object, type,
limits, when it may change) is `mecanum_robot.eds`, written from the firmware's table and
carried by the package as the DBC is. python-canopen works as well
(`canopen.RemoteNode(N, eds)`); this client is the few lines the CLI needs, on python-can:
reads and writes of parameters, the CiA 301 save (0x1010) and restore of the built-in set
(0x1011), and the configurations' ids (0x2100).
"""

from __future__ import annotations

import configparser
import math
import pathlib
import struct
import time
from dataclasses import dataclass

import can

from . import protocol

#: The EDS's name inside the package (and in the repository's `dbc/` directory).
EDS_NAME = "mecanum_robot.eds"
#: The read-only record of the configurations' ids and the saved set (not parameters).
INFO_INDEX = 0x2100
#: CiA 301 Store parameters: writing `SAVE_SIGNATURE` to sub-index 1 saves the set in force.
STORE_INDEX = 0x1010
#: CiA 301 Restore default parameters: `LOAD_SIGNATURE` to sub-index 1 puts the built-in
#: set in force and saves it.
RESTORE_INDEX = 0x1011
SAVE_SIGNATURE = b"save"  # 0x65766173 as the UNSIGNED32 it is
LOAD_SIGNATURE = b"load"  # 0x64616F6C
#: The least time a save or restore is given to answer: the robot answers once the set is
#: stored (about 25 ms on the board; a runner's file and its fsync may take longer).
STORE_TIMEOUT = 1.0
#: The abort of a read of an object this configuration does not have (another drive's).
NOT_IN_CONFIGURATION = 0x0609_0011
#: The service's node id unless the robot's drives are CiA 402 nodes.
DEFAULT_NODE = 127
_FORMATS = {0x0001: ("<B", 1), 0x0005: ("<B", 1), 0x0007: ("<I", 4), 0x0008: ("<f", 4)}
_ABORTS = {
    0x0601_0002: "read-only over CAN",
    0x0602_0000: "no such object",
    0x0606_0000: "the parameter flash failed: not stored, or its read-back differs",
    0x0607_0010: "wrong data length",
    0x0609_0011: "not in this configuration",
    0x0609_0030: "invalid value (NaN, or a rule of the configuration)",
    0x0609_0031: "above its range",
    0x0609_0032: "below its range",
    0x0800_0020: "not stored: wrong signature, or no erased flash slot left "
                 "(reset the board while disabled to compact its parameter flash)",
    0x0800_0022: "changes only while disabled",
}
#: What 0x0800_0022 means for a save and for a restore (the robot's state, not a value's).
_SAVE_ABORTS = {0x0800_0022: "a save is already being stored; try again when it has answered"}
_RESTORE_ABORTS = {0x0800_0022: "refused while the robot is enabled (restore only while disabled), "
                                "or while a save is being stored"}


class ParamError(Exception):
    """A refusal or no answer; the message names the parameter and the reason, `code` is
    the SDO abort code of a refusal (None: no answer)."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Info:
    """Object 0x2100: the configurations' ids (16-bit CRCs, shown as 0x%04x) and the saved set."""

    running_id: int  # the configuration in force (HEARTBEAT.config_id)
    builtin_id: int  # the image's (or the runner's configuration file's) built-in one
    saved_id: int  # the one a restart runs: the saved set, else the built-in one
    saved_seq: int  # that saved record's sequence number; 0: none saved (the built-in set)


@dataclass(frozen=True)
class Param:
    """One parameter as the EDS describes it."""

    name: str
    index: int
    sub: int
    data_type: int
    low: float
    high: float
    change: str  # live, disabled or fixed
    doc: str

    def encode(self, value: float) -> tuple[bytes, int]:
        """The value's bytes and size; ValueError if the type cannot hold it."""
        fmt, size = _FORMATS[self.data_type]
        if fmt != "<f" and not (math.isfinite(value) and value == int(value) and value >= 0):
            raise ValueError(f"{self.name}: {value} is not a whole number >= 0")
        try:
            return struct.pack(fmt, value if fmt == "<f" else int(value)), size
        except struct.error as err:
            raise ValueError(f"{self.name}: {value} does not fit: {err}") from None

    def decode(self, data: bytes) -> float:
        fmt, size = _FORMATS[self.data_type]
        return float(struct.unpack(fmt, data[:size])[0])


def eds_path() -> pathlib.Path:
    """The robot's EDS."""
    return protocol.data_file(EDS_NAME)


def table(path: pathlib.Path | None = None) -> dict[str, Param]:
    """Every parameter of the EDS, by name, in object order."""
    ini = configparser.ConfigParser(interpolation=None)
    ini.optionxform = str  # type: ignore[assignment, method-assign]
    ini.read_string((path or eds_path()).read_text(encoding="utf-8"))
    params = {}
    for section in ini.sections():
        head, sep, sub = section.partition("sub")
        if not sep or not 0x2000 <= int(head, 16) < INFO_INDEX or int(sub, 16) == 0:
            continue
        e = ini[section]
        doc, _, change = e.get("Denotation", "").rpartition(" (")
        params[e["ParameterName"]] = Param(
            name=e["ParameterName"], index=int(head, 16), sub=int(sub, 16),
            data_type=int(e["DataType"], 0), low=float(e["LowLimit"]),
            high=float(e.get("HighLimit", "inf")), change=change.rstrip(")"), doc=doc,
        )
    return params


class Client:
    """An expedited SDO client of the robot's parameter service on `bus`."""

    def __init__(self, bus: can.BusABC, node: int = DEFAULT_NODE, timeout: float = 0.5) -> None:
        if not 1 <= node <= 127:
            raise ValueError(f"node {node}: a CANopen node id is 1..127")
        self.bus, self.node, self.timeout = bus, node, timeout

    def _transfer(self, what: str, index: int, sub: int, command: int, data: bytes = b"",
                  timeout: float | None = None, aborts: dict[int, str] | None = None) -> bytes:
        """One expedited SDO request to object index:sub and its answer's four data bytes.

        `what` names the object in errors; `aborts` are texts for this object that win over
        `_ABORTS`'s; `timeout` defaults to the client's."""
        timeout = self.timeout if timeout is None else timeout
        payload = struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0")
        self.bus.send(can.Message(arbitration_id=0x600 + self.node, data=payload, is_extended_id=False))
        answer = 0x40 if command == 0x40 else 0x60  # an upload's or a download's response
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(left)
            if msg is None or msg.arbitration_id != 0x580 + self.node or msg.is_extended_id or len(msg.data) < 8:
                continue
            cmd, got_index, got_sub = struct.unpack_from("<BHB", bytes(msg.data))
            if (got_index, got_sub) != (index, sub) or (cmd != 0x80 and cmd & 0xE0 != answer):
                continue
            if cmd == 0x80:
                code = struct.unpack_from("<I", bytes(msg.data), 4)[0]
                reason = (aborts or {}).get(code) or _ABORTS.get(code, "refused")
                raise ParamError(f"{what}: {reason} (SDO abort 0x{code:08X})", code)
            return bytes(msg.data[4:8])
        raise ParamError(f"{what}: no answer from node {self.node} within {timeout:g} s")

    def get(self, p: Param) -> float:
        return p.decode(self._transfer(p.name, p.index, p.sub, 0x40))

    def set(self, p: Param, value: float) -> None:
        data, size = p.encode(value)
        self._transfer(p.name, p.index, p.sub, 0x23 | ((4 - size) << 2), data)

    def _command(self, what: str, index: int, signature: bytes, aborts: dict[int, str]) -> None:
        """Write a CiA 301 signature (4 bytes) to index:1, given at least STORE_TIMEOUT."""
        self._transfer(what, index, 1, 0x23, signature, timeout=max(self.timeout, STORE_TIMEOUT), aborts=aborts)

    def save(self) -> None:
        """Save the configuration in force (0x1010:01 <- "save"); returns once it is stored."""
        self._command("save", STORE_INDEX, SAVE_SIGNATURE, _SAVE_ABORTS)

    def restore(self) -> None:
        """Put the built-in configuration in force and save it (0x1011:01 <- "load"); the
        robot refuses while enabled. Returns once it is stored."""
        self._command("restore", RESTORE_INDEX, LOAD_SIGNATURE, _RESTORE_ABORTS)

    def info(self) -> Info:
        """Object 0x2100: the running, built-in and saved configurations' ids, the saved record."""
        ids = [struct.unpack("<I", self._transfer(f"info 0x{INFO_INDEX:04X}:{sub:02X}", INFO_INDEX, sub, 0x40))[0]
               for sub in range(1, 5)]
        return Info(*ids)
