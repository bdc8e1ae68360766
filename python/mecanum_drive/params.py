"""The robot's parameters over CAN: the table from its EDS, and an expedited SDO client.

The robot serves its parameters as a CANopen SDO server on its node id N (127, or its CiA
402 drives' master node): requests on 0x600 + N, responses on 0x580 + N
(docs/protocol.md, "Parameters"). The description of every parameter (name, object, type,
limits, when it may change) is `mecanum_robot.eds`, written from the firmware's table and
carried by the package as the DBC is. python-canopen works as well
(`canopen.RemoteNode(N, eds)`); this client is the few lines the CLI needs, on python-can.
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
#: The service's node id unless the robot's drives are CiA 402 nodes.
DEFAULT_NODE = 127
_FORMATS = {0x0001: ("<B", 1), 0x0005: ("<B", 1), 0x0007: ("<I", 4), 0x0008: ("<f", 4)}
_ABORTS = {
    0x0601_0002: "read-only over CAN",
    0x0602_0000: "no such object",
    0x0607_0010: "wrong data length",
    0x0609_0011: "not in this configuration",
    0x0609_0030: "invalid value (NaN, or a rule of the configuration)",
    0x0609_0031: "above its range",
    0x0609_0032: "below its range",
    0x0800_0022: "changes only while disabled",
}


class ParamError(Exception):
    """A refusal or no answer; the message names the parameter and the reason."""


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

    def _transfer(self, p: Param, command: int, data: bytes = b"") -> bytes:
        payload = struct.pack("<BHB", command, p.index, p.sub) + data.ljust(4, b"\0")
        self.bus.send(can.Message(arbitration_id=0x600 + self.node, data=payload, is_extended_id=False))
        deadline = time.monotonic() + self.timeout
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(left)
            if msg is None or msg.arbitration_id != 0x580 + self.node or msg.is_extended_id:
                continue
            cmd, index, sub = struct.unpack_from("<BHB", bytes(msg.data))
            if (index, sub) != (p.index, p.sub):
                continue
            if cmd == 0x80:
                code = struct.unpack_from("<I", bytes(msg.data), 4)[0]
                reason = _ABORTS.get(code, "refused")
                raise ParamError(f"{p.name}: {reason} (SDO abort 0x{code:08X})")
            return bytes(msg.data[4:])
        raise ParamError(f"{p.name}: no answer from node {self.node} within {self.timeout} s")

    def get(self, p: Param) -> float:
        return p.decode(self._transfer(p, 0x40))

    def set(self, p: Param, value: float) -> None:
        data, size = p.encode(value)
        self._transfer(p, 0x23 | ((4 - size) << 2), data)
