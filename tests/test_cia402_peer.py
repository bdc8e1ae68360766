"""The simulated CiA 402 drive (tests/cia402_peer.py) against python canopen as the master.

The master here does what docs/protocol.md ("CANopen CiA 402") asks of the project's CANopen
master: NMT reset communication, the configuration of each node by expedited SDO in the
order of "Configuration of a node", NMT start, then per cycle SYNC and each node's RPDOs,
its own heartbeat, and the enable sequence 0x06 -> 0x07 -> 0x0F. A recorder (its own
python-can socket) keeps every frame on the bus with the kernel's timestamp; the timings
below are differences of those timestamps, not of the test thread's clock.

The tests marked `vcan` need vcan0 (scripts/vcan.sh runs them natively or in a micro-VM);
the EDS files and the state machine's table are checked without a bus.
"""

from __future__ import annotations

import configparser
import contextlib
import dataclasses
import math
import pathlib
import re
import struct
import threading
import time
import tomllib
from collections.abc import Callable, Iterator

import can
import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from cia402_peer import (
    ABORT_VALUE_RANGE,
    DUAL_EDS,
    EMCY_BUS_OFF_RECOVERED,
    EMCY_HEARTBEAT,
    EMCY_PDO_LENGTH,
    REMOTE,
    SINGLE_EDS,
    Cia402Peer,
    State,
    error_register,
    next_state,
)

DUAL, SINGLE = 1, 3  # the two drives' node ids
MASTER = 127  # drive.master_node's default
HEARTBEAT_MS = 50  # drive.heartbeat_ms's default
HEARTBEAT_TIMEOUT_MS = 150  # drive.heartbeat_timeout_ms's default
CYCLE_S = 0.01
TAU_S = 0.05  # the peer's default motor time constant
COB_INVALID = 0x80000000
SDO_TIMEOUT_S = 2.0
WAIT_S = 5.0  # for a frame that must come (generous: the micro-VM's Python is slow)


# --- without a bus ------------------------------------------------------------------------

def _eds_sections(path: str) -> configparser.RawConfigParser:
    eds = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    eds.optionxform = str  # type: ignore[assignment,method-assign]
    with open(path) as f:
        eds.read_file(f)
    return eds


@pytest.mark.parametrize("path, axes", [(DUAL_EDS, 2), (SINGLE_EDS, 1)])
def test_eds_is_consistent_and_loads_with_canopen(path: str, axes: int) -> None:
    """CiA 306 structure (object lists, SubNumber, sub-index sections) and the objects the
    master relies on, as canopen imports them for node 5."""
    eds = _eds_sections(str(path))
    listed: list[int] = []
    for section in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        count = int(eds.get(section, "SupportedObjects"), 0)
        listed += [int(eds.get(section, str(i)), 0) for i in range(1, count + 1)]
    objects = sorted(int(s, 16) for s in eds.sections() if re.fullmatch(r"[0-9A-F]{4}", s))
    assert sorted(listed) == objects and len(set(listed)) == len(listed)
    for index in objects:
        subs = [s for s in eds.sections() if re.fullmatch(f"{index:04X}sub[0-9A-F]+", s)]
        if int(eds.get(f"{index:04X}", "ObjectType"), 0) == 7:
            assert not subs and eds.has_option(f"{index:04X}", "DataType")
        else:
            assert int(eds.get(f"{index:04X}", "SubNumber"), 0) == len(subs) > 0, f"{index:04X}"
            highest = int(eds.get(f"{index:04X}sub0", "DefaultValue"), 0)
            if index not in range(0x1600, 0x1800) and index not in range(0x1A00, 0x1C00):
                assert highest == max(int(s.split("sub")[1], 16) for s in subs), f"{index:04X}"

    od = canopen.import_od(str(path), 5)

    def var(index: int, sub: int = 0) -> ODVariable:
        obj = od[index]
        if isinstance(obj, (ODArray, ODRecord)):
            obj = obj[sub]
        assert isinstance(obj, ODVariable)
        return obj

    assert var(0x1000).default == 0x00020192 == 0x2 << 16 | 402  # profile 402 in the low 16 bits
    assert (var(0x1017).data_type, var(0x1017).access_type) == (canopen.objectdictionary.UNSIGNED16, "rw")
    assert (var(0x1016, 1).data_type, var(0x1016, 1).access_type) == (canopen.objectdictionary.UNSIGNED32, "rw")
    for k in range(4):
        assert var(0x1400 + k, 1).default == 0x200 + 0x100 * k + 5
        assert var(0x1800 + k, 1).default == 0x180 + 0x100 * k + 5
        for mapping in (0x1600 + k, 0x1A00 + k):
            assert [var(mapping, s).access_type for s in range(9)] == ["rw"] * 9
    assert (var(0x6040).access_type, var(0x6040).pdo_mappable, len(var(0x6040))) == ("rw", True, 16)
    assert (var(0x6041).access_type, var(0x6041).pdo_mappable, len(var(0x6041))) == ("ro", True, 16)
    assert (var(0x6060).data_type, var(0x6061).data_type) == (canopen.objectdictionary.INTEGER8,) * 2
    axis_subs = (1, 2) if axes == 2 else (0,)
    assert isinstance(od[0x60FF], ODArray) == (axes == 2) == isinstance(od[0x606C], ODArray)
    if axes == 2:
        assert var(0x60FF, 0).default == var(0x606C, 0).default == 2
    for s in axis_subs:
        assert (var(0x60FF, s).data_type, var(0x60FF, s).access_type) == (canopen.objectdictionary.INTEGER32, "rw")
        assert (var(0x606C, s).data_type, var(0x606C, s).access_type) == (canopen.objectdictionary.INTEGER32, "ro")
        assert var(0x60FF, s).pdo_mappable and var(0x606C, s).pdo_mappable


#: CiA 402's state table, the one hostsim's drive is held to as well (its test
#: `both_drive_models_follow_the_transition_table` reads the same file).
TRANSITIONS = tomllib.loads((pathlib.Path(__file__).resolve().parent / "cia402_transitions.toml").read_text())


@pytest.mark.parametrize("state, controlword, previous, mode, want, transition", TRANSITIONS["table"]["rows"],
                         ids=lambda v: f"{v:#04x}" if isinstance(v, int) and v > 9 else str(v))
def test_state_machine_table(state: str, controlword: int, previous: int, mode: int, want: str,
                             transition: str) -> None:
    """Each row of tests/cia402_transitions.toml: the state the peer goes to, and its
    statusword under 0x6F."""
    got = next_state(State[state], controlword, previous, mode)
    assert got is State[want], f"{state} {controlword:#04x} -> {got.name}, the table says {want} ({transition})"
    assert (got | REMOTE) & 0x6F == TRANSITIONS["statusword"][want]


@pytest.mark.parametrize("code, register", [
    (0x2310, 0x03), (0x3210, 0x05), (0x4210, 0x09), (0x8130, 0x11), (0x8140, 0x11), (0x8210, 0x11),
    (0x8611, 0x01), (0x1000, 0x01), (0x0000, 0x00),
])
def test_error_register_of_an_emcy_code(code: int, register: int) -> None:
    """CiA 301's error register bits (generic, and current, voltage, temperature,
    communication by the code's class), as hostsim's drive sets them."""
    assert error_register(code) == register


# --- on vcan0: the recorder and the master --------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Frame:
    """A frame as the recorder's socket received it: kernel timestamp (s), id, data."""

    t: float
    id: int
    data: bytes


class Recorder(can.Listener):
    """Every frame on the bus, from its own socket (so the master's frames too)."""

    def __init__(self, channel: str) -> None:
        self.frames: list[Frame] = []
        self._cond = threading.Condition()
        self.bus = can.Bus(interface="socketcan", channel=channel)
        self.notifier = can.Notifier(self.bus, [self])

    def on_message_received(self, msg: can.Message) -> None:
        with self._cond:
            self.frames.append(Frame(msg.timestamp, msg.arbitration_id, bytes(msg.data)))
            self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.frames)

    def since(self, mark: int, can_id: int | None = None) -> list[Frame]:
        with self._cond:
            return [f for f in self.frames[mark:] if can_id is None or f.id == can_id]

    def wait(self, mark: int, can_id: int, match: Callable[[Frame], bool] = lambda f: True,
             timeout: float = WAIT_S) -> Frame:
        """The first frame with `can_id` (and `match`) at or after `mark`."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                for frame in self.frames[mark:]:
                    if frame.id == can_id and match(frame):
                        return frame
                left = end - time.monotonic()
                assert left > 0, f"no frame 0x{can_id:03X} within {timeout} s"
                self._cond.wait(left)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


@dataclasses.dataclass(frozen=True)
class Layout:
    """The PDOs docs/protocol.md has the master use on a node: (comm index, COB-ID,
    entries, transmission type), and the comm indices it disables."""

    used: tuple[tuple[int, int, tuple[int, ...], int], ...]
    unused: tuple[int, ...]


def layout(node: int, dual: bool) -> Layout:
    used: tuple[tuple[int, int, tuple[int, ...], int], ...]
    if dual:
        used = ((0x1400, 0x200 + node, (0x60400010, 0x60FF0120), 0xFF), (0x1402, 0x400 + node, (0x60FF0220,), 0xFF),
                (0x1800, 0x180 + node, (0x60410010, 0x606C0120), 1), (0x1801, 0x280 + node, (0x606C0220,), 1))
    else:
        used = ((0x1400, 0x200 + node, (0x60400010, 0x60FF0020), 0xFF),
                (0x1800, 0x180 + node, (0x60410010, 0x606C0020), 1))
    comms = {c for c, _, _, _ in used}
    return Layout(used, tuple(c for c in (*range(0x1400, 0x1404), *range(0x1800, 0x1804)) if c not in comms))


def default_cob(comm: int, node: int) -> int:
    return (0x200 if comm < 0x1800 else 0x180) + 0x100 * (comm & 0xFF) + node


class Master:
    """python canopen as the CANopen master of docs/protocol.md, one RemoteNode per drive."""

    def __init__(self, channel: str, nodes: dict[int, bool]) -> None:
        self.network = canopen.Network()
        self.network.connect(interface="socketcan", channel=channel)
        self.dual = nodes
        self.nodes = {n: self.network.add_node(n, str(DUAL_EDS if dual else SINGLE_EDS)) for n, dual in nodes.items()}
        for node in self.nodes.values():
            node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        self.sdo_log: list[tuple[int, int, int, int]] = []  # (node, index, sub, value)
        self._heartbeat: canopen.network.PeriodicMessageTask | None = None

    def write(self, node: int, index: int, sub: int, value: int) -> None:
        """Expedited SDO download, sized by the EDS."""
        obj = self.nodes[node].object_dictionary[index]
        var = obj[sub] if isinstance(obj, (ODArray, ODRecord)) else obj
        assert isinstance(var, ODVariable)
        self.nodes[node].sdo.download(index, sub, var.encode_raw(value))
        self.sdo_log.append((node, index, sub, value))

    def read(self, node: int, index: int, sub: int = 0) -> int:
        obj = self.nodes[node].object_dictionary[index]
        var = obj[sub] if isinstance(obj, (ODArray, ODRecord)) else obj
        assert isinstance(var, ODVariable)
        return int(var.decode_raw(self.nodes[node].sdo.upload(index, sub)))

    def nmt(self, command: int, node: int) -> None:
        self.network.send_message(0x000, bytes([command, node]))

    def configure(self, node: int, mode: int = 3) -> None:
        """docs/protocol.md, "Configuration of a node", steps 1-5 (6, NMT start, is the caller's)."""
        assert self.read(node, 0x1000) & 0xFFFF == 402
        self.write(node, 0x6060, 0, mode)
        self.write(node, 0x1017, 0, HEARTBEAT_MS)
        self.write(node, 0x1016, 1, MASTER << 16 | HEARTBEAT_TIMEOUT_MS)
        plan = layout(node, self.dual[node])
        for comm, cob_id, entries, transmission in plan.used:
            self.write(node, comm, 1, cob_id | COB_INVALID)
            self.write(node, comm + 0x200, 0, 0)
            for sub, entry in enumerate(entries, 1):
                self.write(node, comm + 0x200, sub, entry)
            self.write(node, comm + 0x200, 0, len(entries))
            self.write(node, comm, 2, transmission)
            self.write(node, comm, 1, cob_id)
        for comm in plan.unused:
            self.write(node, comm, 1, default_cob(comm, node) | COB_INVALID)

    def start_heartbeat(self) -> None:
        self._heartbeat = self.network.send_periodic(0x700 + MASTER, bytes([0x05]), HEARTBEAT_MS / 1000)

    def stop_heartbeat(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.stop()  # type: ignore[no-untyped-call]
            self._heartbeat = None

    def cycle(self, controlword: int, targets: dict[int, tuple[int, ...]]) -> None:
        """One cycle: SYNC, then each node's RPDOs."""
        self.network.send_message(0x080, b"")
        for node, dual in self.dual.items():
            v = targets.get(node, (0, 0) if dual else (0,))
            self.network.send_message(0x200 + node, struct.pack("<Hi", controlword, v[0]))
            if dual:
                self.network.send_message(0x400 + node, struct.pack("<i", v[1]))

    def close(self) -> None:
        self.stop_heartbeat()
        self.network.disconnect()


@dataclasses.dataclass
class Bench:
    recorder: Recorder
    master: Master
    peers: dict[int, Cia402Peer]

    def boot(self) -> None:
        """The master's first step: NMT reset communication to every node, configuration of
        each as its boot-up arrives, NMT start."""
        mark = self.recorder.mark()
        for node in self.peers:
            self.master.nmt(0x82, node)
        for node in self.peers:
            self.recorder.wait(mark, 0x700 + node, lambda f: f.data == b"\x00")
            self.master.configure(node)
            started = self.recorder.mark()
            self.master.nmt(0x01, node)
            # Operational when its heartbeat says so: a change of state goes out at once (0x1017
            # is set), from the peer's own thread, after the command has reached it.
            self.recorder.wait(started, 0x700 + node, lambda f: f.data == b"\x05")

    def statuswords(self, node: int, mark: int) -> list[int]:
        return [struct.unpack_from("<H", f.data)[0] for f in self.recorder.since(mark, 0x180 + node)]

    def run(self, controlword: int, cycles: int, targets: dict[int, tuple[int, ...]] | None = None) -> None:
        for _ in range(cycles):
            self.master.cycle(controlword, targets or {})
            time.sleep(CYCLE_S)

    def until(self, controlword: int, want: int, mask: int = 0x6F,
              targets: dict[int, tuple[int, ...]] | None = None, max_cycles: int = 10) -> int:
        """Cycles with `controlword` (to every node, as the master does) until each node's
        TPDO1 statusword & mask == want: the number of cycles."""
        for n in range(1, max_cycles + 1):
            mark = self.recorder.mark()
            self.master.cycle(controlword, targets or {})
            words = {node: struct.unpack_from("<H", self.recorder.wait(mark, 0x180 + node).data)[0]
                     for node in self.peers}
            if all(w & mask == want for w in words.values()):
                return n
            time.sleep(CYCLE_S)
        raise AssertionError(f"statusword & 0x{mask:02X} != 0x{want:02X} after {max_cycles} cycles of "
                             f"controlword 0x{controlword:02X}: {({n: hex(w) for n, w in words.items()})}")

    def enable(self) -> None:
        for controlword, want in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
            self.until(controlword, want)

    def start(self) -> None:
        """The master's heartbeat on, then `boot` and `enable`: every node operation enabled."""
        self.master.start_heartbeat()
        self.boot()
        self.enable()


@contextlib.contextmanager
def bench(channel: str, nodes: dict[int, bool]) -> Iterator[Bench]:
    with contextlib.ExitStack() as stack:
        recorder = Recorder(channel)
        stack.callback(recorder.close)
        peers = {}
        for node, dual in nodes.items():
            peers[node] = Cia402Peer(channel, node, DUAL_EDS if dual else SINGLE_EDS)
            stack.callback(peers[node].close)
        master = Master(channel, nodes)
        stack.callback(master.close)
        yield Bench(recorder, master, peers)
        for node, peer in peers.items():
            assert peer.errors == [], f"peer {node}: {peer.errors}"


def emcy(frame: Frame) -> tuple[int, int]:
    code, register = struct.unpack_from("<HB", frame.data)
    return code, register


# --- on vcan0: the tests -----------------------------------------------------------------

@pytest.mark.vcan
def test_configuration_enable_and_velocity(vcan: str) -> None:
    """Two drives (dual-axis node 1, single-axis node 3) configured as docs/protocol.md says,
    enabled 0x06 -> 0x07 -> 0x0F (statusword 0x21, 0x23, 0x27 under 0x6F), then each wheel's
    velocity follows its target as a first-order lag of 50 ms, at the SYNC's time."""
    with bench(vcan, {DUAL: True, SINGLE: False}) as b:
        b.master.start_heartbeat()
        boot_mark = b.recorder.mark()
        b.boot()
        # Every download was answered (an abort raises); each node is operational and the
        # PDO tables are what the master wrote, read back.
        # 3 objects, 5 + n downloads per used PDO (n entries), 1 per unused one.
        assert len([s for s in b.master.sdo_log if s[0] == DUAL]) == 3 + (7 + 6 + 7 + 6) + 4
        assert len([s for s in b.master.sdo_log if s[0] == SINGLE]) == 3 + (7 + 7) + 6
        for node, peer in b.peers.items():
            assert peer.nmt_state == 0x05
            assert b.master.read(node, 0x1600, 2) == (0x60FF0120 if node == DUAL else 0x60FF0020)
            assert b.master.read(node, 0x1401, 1) == 0x300 + node | COB_INVALID  # RPDO2 off
        # Boot-ups answered the reset communication, once per node.
        for node in b.peers:
            assert [f.data for f in b.recorder.since(boot_mark, 0x700 + node)][:1] == [b"\x00"]

        # The enable sequence, one controlword per state; each answered at the next SYNC.
        enable_mark = b.recorder.mark()
        for controlword, want in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
            assert b.until(controlword, want) <= 2
        for node, peer in b.peers.items():
            steps = [(e.controlword, e.statusword) for e in peer.trace if e.controlword is not None]
            assert [(c, s & 0x6F) for c, s in steps] == [(0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)]
            assert [s for _, s in steps] == [0x0231, 0x0233, 0x0237]  # bits 4 and 9 as chosen
            assert b.statuswords(node, enable_mark)[0] == 0x0240  # switch on disabled
        # A frame on RPDO2's id (the robot protocol's block) is not taken for a PDO.
        b.master.network.send_message(0x300 + DUAL, struct.pack("<HB", 0x0000, 0x01))
        time.sleep(0.02)
        assert b.peers[DUAL].state is State.OPERATION_ENABLED

        # Targets once every node is enabled; velocity actual from the TPDOs.
        targets = {DUAL: (1200, -700), SINGLE: (900,)}
        start = b.recorder.mark()
        b.run(0x0F, round(8 * TAU_S / CYCLE_S), targets)
        time.sleep(0.05)
        # When each target changed: the first RPDO that carries it.
        t0 = {(DUAL, 0): b.recorder.wait(start, 0x200 + DUAL).t, (DUAL, 1): b.recorder.wait(start, 0x400 + DUAL).t,
              (SINGLE, 0): b.recorder.wait(start, 0x200 + SINGLE).t}
        syncs = [f.t for f in b.recorder.since(start, 0x080)]
        series = {
            (DUAL, 0): [struct.unpack_from("<i", f.data, 2)[0] for f in b.recorder.since(start, 0x180 + DUAL)],
            (DUAL, 1): [struct.unpack_from("<i", f.data)[0] for f in b.recorder.since(start, 0x280 + DUAL)],
            (SINGLE, 0): [struct.unpack_from("<i", f.data, 2)[0] for f in b.recorder.since(start, 0x180 + SINGLE)],
        }
        assert all(len(v) == len(syncs) for v in series.values()), (len(syncs), {k: len(v) for k, v in series.items()})
        slack = 0.005  # frame timestamps vs when the peer acted on the frames
        worst = 0.0
        for (node, axis), values in series.items():
            goal = targets[node][axis]
            for t_sync, v in zip(syncs, values):
                dt = t_sync - t0[node, axis]
                lo = goal * (1 - math.exp(-max(0.0, dt - slack) / TAU_S))
                hi = goal * (1 - math.exp(-max(0.0, dt + slack) / TAU_S))
                lo, hi = min(lo, hi) - 1, max(lo, hi) + 1
                assert lo <= v <= hi, f"node {node} axis {axis}: {v} at {dt:.4f} s, model [{lo:.0f}, {hi:.0f}]"
                worst = max(worst, abs(v - goal * (1 - math.exp(-max(0.0, dt) / TAU_S))))
            assert abs(values[-1] - goal) <= 0.005 * abs(goal), (node, axis, values[-1])
        for node, peer in b.peers.items():
            assert peer.state is State.OPERATION_ENABLED
            assert peer.target_velocity() == targets[node]
        print(f"\nvelocity over {len(syncs)} SYNCs: worst deviation from the 50 ms model {worst:.1f} raw units")


@pytest.mark.vcan
def test_enable_refused_outside_profile_velocity(vcan: str) -> None:
    with bench(vcan, {DUAL: True}) as b:
        b.master.start_heartbeat()
        mark = b.recorder.mark()
        b.master.nmt(0x82, DUAL)
        b.recorder.wait(mark, 0x700 + DUAL, lambda f: f.data == b"\x00")
        b.master.configure(DUAL, mode=1)
        b.master.nmt(0x01, DUAL)
        b.until(0x06, 0x21)
        b.until(0x07, 0x23)
        mark = b.recorder.mark()
        b.run(0x0F, 10)
        assert {s & 0x6F for s in b.statuswords(DUAL, mark)} == {0x23}
        assert b.peers[DUAL].trace[-1][1:] == (0x0F, 0x0233)  # received, refused
        b.master.write(DUAL, 0x6060, 0, 3)
        assert b.master.read(DUAL, 0x6061) == 3
        b.until(0x07, 0x23)
        assert b.until(0x0F, 0x27) <= 2


@pytest.mark.vcan
def test_quick_stop_slows_down_then_switch_on_disabled(vcan: str) -> None:
    with bench(vcan, {SINGLE: False}) as b:
        b.start()
        b.run(0x0F, 30, {SINGLE: (2000,)})
        mark = b.recorder.mark()
        b.until(0x02, 0x07, targets={SINGLE: (2000,)})
        b.until(0x02, 0x40, mask=0x4F, max_cycles=200)
        frames = b.recorder.since(mark, 0x180 + SINGLE)
        velocities = [struct.unpack_from("<i", f.data, 2)[0] for f in frames]
        words = [struct.unpack_from("<H", f.data)[0] for f in frames]
        assert velocities[0] > 1900 and velocities[-1] == 0
        assert all(a >= b for a, b in zip(velocities, velocities[1:])), velocities
        quick = [f.t for f, w in zip(frames, words) if w & 0x6F == 0x07]
        # From ~2000 to below 0.5 at 50 ms: ln(4000) * 0.05 = 0.41 s.
        assert 0.3 < quick[-1] - quick[0] < 0.6, quick[-1] - quick[0]
        assert [e.statusword for e in b.peers[SINGLE].trace[-2:]] == [0x0217, 0x0240]


@pytest.mark.vcan
def test_shutdown_with_option_code_1_slows_down_before_the_drive_function_goes(vcan: str) -> None:
    """0x605B = 1, as the robot's master writes it: a shutdown from operation enabled keeps the
    statusword at operation enabled while the axis slows down, then ready to switch on; the
    default 0 shuts down at once (hostsim's drives do the same)."""
    with bench(vcan, {SINGLE: False}) as b:
        b.master.start_heartbeat()
        b.boot()
        # Only 0 and 1 (the EDS's limits; hostsim's drives refuse the same).
        for bad in (2, -1):
            with pytest.raises(canopen.SdoAbortedError) as aborted:
                b.master.write(SINGLE, 0x605B, 0, bad)
            assert aborted.value.code == ABORT_VALUE_RANGE, (bad, hex(aborted.value.code))
        b.master.write(SINGLE, 0x605B, 0, 1)
        b.enable()
        b.run(0x0F, 30, {SINGLE: (2000,)})
        mark = b.recorder.mark()
        cycles = b.until(0x06, 0x21, max_cycles=200)
        frames = b.recorder.since(mark, 0x180 + SINGLE)
        velocities = [struct.unpack_from("<i", f.data, 2)[0] for f in frames]
        words = [struct.unpack_from("<H", f.data)[0] & 0x6F for f in frames]
        assert velocities[0] > 1900 and abs(velocities[-1]) < 1, velocities
        assert set(words[:-1]) == {0x27} and words[-1] == 0x21, words
        slowing = [f.t for f, w in zip(frames, words) if w == 0x27]
        # From ~2000 to below 0.5 at 50 ms: ln(4000) * 0.05 = 0.41 s, as the quick stop's.
        assert 0.3 < slowing[-1] - slowing[0] < 0.6 and cycles > 10, (slowing[-1] - slowing[0], cycles)
        # The shutdown taken in operation enabled, ready to switch on from inside the drive.
        assert [(e.controlword, e.statusword) for e in b.peers[SINGLE].trace[-2:]] == [
            (0x06, 0x0237), (None, 0x0231)]
        b.master.write(SINGLE, 0x605B, 0, 0)
        b.enable()
        b.run(0x0F, 30, {SINGLE: (2000,)})
        b.until(0x06, 0x21)
        assert [(e.controlword, e.statusword) for e in b.peers[SINGLE].trace[-2:]] == [
            (0x0F, 0x0237), (0x06, 0x0231)]


@pytest.mark.vcan
def test_heartbeat_producer_follows_1017_and_the_hooks(vcan: str) -> None:
    with bench(vcan, {DUAL: True}) as b:
        hb = 0x700 + DUAL
        mark = b.recorder.mark()
        time.sleep(0.3)
        assert b.recorder.since(mark, hb) == []  # 0x1017 = 0 by default: no heartbeat
        b.master.write(DUAL, 0x1017, 0, HEARTBEAT_MS)
        time.sleep(1.0)
        frames = b.recorder.since(mark, hb)
        gaps = [(b2.t - a.t) * 1000 for a, b2 in zip(frames, frames[1:])]
        assert {f.data for f in frames} == {b"\x7f"}  # pre-operational
        assert len(gaps) >= 15 and abs(sum(gaps) / len(gaps) - HEARTBEAT_MS) < 1.0, gaps
        assert HEARTBEAT_MS - 5 < min(gaps) and max(gaps) < HEARTBEAT_MS + 10, gaps
        b.master.nmt(0x01, DUAL)
        b.recorder.wait(b.recorder.mark(), hb, lambda f: f.data == b"\x05")
        b.master.nmt(0x02, DUAL)
        b.recorder.wait(b.recorder.mark(), hb, lambda f: f.data == b"\x04")
        b.master.nmt(0x80, DUAL)
        b.recorder.wait(b.recorder.mark(), hb, lambda f: f.data == b"\x7f")
        # Silent on request, then again at once.
        b.peers[DUAL].stop_heartbeat()
        silent = b.recorder.mark()
        time.sleep(0.4)
        assert b.recorder.since(silent, hb) == []
        b.peers[DUAL].resume_heartbeat()
        b.recorder.wait(silent, hb)
        b.master.write(DUAL, 0x1017, 0, 0)  # off again
        time.sleep(0.1)
        off = b.recorder.mark()
        time.sleep(0.3)
        assert b.recorder.since(off, hb) == []
        print(f"\nheartbeat: {len(gaps)} periods, mean {sum(gaps) / len(gaps):.2f} ms, "
              f"min {min(gaps):.2f}, max {max(gaps):.2f}")


@pytest.mark.vcan
def test_heartbeat_consumer_trips_within_its_time(vcan: str) -> None:
    """0x1016:01 = 127 << 16 | 150: the drive watches the master's heartbeat from the first
    one on; 150 ms of silence (up to one period more) faults it with EMCY 0x8130 and, as
    0x1029 = 0 says, takes it from operational to pre-operational (its heartbeat says so at
    once): no PDOs until the master starts it again."""
    with bench(vcan, {DUAL: True}) as b:
        b.boot()  # without the master's heartbeat: monitoring has not started
        mark = b.recorder.mark()
        time.sleep(3 * HEARTBEAT_TIMEOUT_MS / 1000)
        assert b.recorder.since(mark, 0x80 + DUAL) == []
        b.master.start_heartbeat()
        b.enable()
        b.run(0x0F, round(4 * HEARTBEAT_TIMEOUT_MS / 1000 / CYCLE_S), {DUAL: (500, 500)})
        assert b.recorder.since(mark, 0x80 + DUAL) == [] and b.peers[DUAL].state is State.OPERATION_ENABLED
        stop = b.recorder.mark()
        b.master.stop_heartbeat()
        frame = b.recorder.wait(stop, 0x80 + DUAL)
        last = [f for f in b.recorder.since(mark, 0x700 + MASTER) if f.t < frame.t][-1]
        trip_ms = (frame.t - last.t) * 1000
        assert HEARTBEAT_TIMEOUT_MS <= trip_ms <= HEARTBEAT_TIMEOUT_MS + HEARTBEAT_MS, trip_ms
        assert emcy(frame) == (EMCY_HEARTBEAT, 0x11) and len(frame.data) == 8
        pre_op = b.recorder.wait(stop, 0x700 + DUAL, lambda f: f.data == b"\x7f")
        # The heartbeat right after the EMCY (the same pass of the peer's timing thread).
        assert 0 <= pre_op.t - frame.t < HEARTBEAT_MS / 1000, (pre_op.t - frame.t)
        assert {f.data for f in b.recorder.since(stop, 0x700 + DUAL) if f.t < frame.t} <= {b"\x05"}
        # Pre-operational: SYNC is not answered; the state by SDO.
        unanswered = b.recorder.mark()
        b.run(0x0F, 3)
        assert b.recorder.since(unanswered, 0x180 + DUAL) == []
        assert b.master.read(DUAL, 0x6041) & 0x4F == 0x08 and b.master.read(DUAL, 0x1001) == 0x11
        # Once per silence: no second EMCY while still silent.
        time.sleep(2 * HEARTBEAT_TIMEOUT_MS / 1000)
        assert len(b.recorder.since(stop, 0x80 + DUAL)) == 1
        assert b.peers[DUAL].nmt_state == 0x7F
        # NMT start brings it back: operational, in fault until a fault reset.
        b.master.nmt(0x01, DUAL)
        assert b.until(0x0F, 0x08, mask=0x4F) <= 2
        print(f"\nheartbeat consumer: tripped {trip_ms:.1f} ms after the master's last heartbeat "
              f"(limit {HEARTBEAT_TIMEOUT_MS} + {HEARTBEAT_MS} ms); heartbeat 0x7F "
              f"{(pre_op.t - frame.t) * 1e3:.2f} ms after the EMCY")


@pytest.mark.vcan
def test_bus_off_faults_and_leaves_operational_until_started(vcan: str) -> None:
    """A bus-off while operation enabled: nothing from the drive while off; it faults (abort
    connection) and, 0x1029 = 0, goes pre-operational. Back on the bus: EMCY 0x8140
    (recovered from bus off, register generic + communication) and a 0x7F heartbeat at once;
    SYNC unanswered until NMT start; then a fault reset (EMCY 0x0000) and it enables again."""
    with bench(vcan, {DUAL: True}) as b:
        b.start()
        b.run(0x0F, 5, {DUAL: (300, 300)})
        peer = b.peers[DUAL]
        off = b.recorder.mark()
        peer.enter_bus_off()
        b.run(0x0F, 10, {DUAL: (300, 300)})
        assert [f for f in b.recorder.since(off) if f.id & 0x7F == DUAL and f.id != 0x200 + DUAL
                and f.id != 0x400 + DUAL] == []  # nothing from node 1 (the master's RPDOs only)
        assert peer.state is State.FAULT and peer.nmt_state == 0x7F
        back = b.recorder.mark()
        peer.leave_bus_off()
        frame = b.recorder.wait(back, 0x80 + DUAL)
        assert emcy(frame) == (EMCY_BUS_OFF_RECOVERED, 0x11)
        beat = b.recorder.wait(back, 0x700 + DUAL)
        assert beat.data == b"\x7f" and 0 <= beat.t - frame.t < HEARTBEAT_MS / 1000
        mark = b.recorder.mark()
        b.run(0x0F, 3)
        assert b.recorder.since(mark, 0x180 + DUAL) == []
        b.master.nmt(0x01, DUAL)
        b.recorder.wait(mark, 0x700 + DUAL, lambda f: f.data == b"\x05")
        assert b.until(0x0F, 0x08, mask=0x4F) <= 2
        reset = b.recorder.mark()
        assert b.until(0x80, 0x40, mask=0x4F) <= 2
        assert emcy(b.recorder.wait(reset, 0x80 + DUAL)) == (0, 0)
        b.enable()


@pytest.mark.vcan
def test_fault_reset_only_on_the_rising_edge_of_bit_7(vcan: str) -> None:
    with bench(vcan, {DUAL: True}) as b:
        b.start()
        peer = b.peers[DUAL]
        mark = b.recorder.mark()
        peer.inject_fault()
        assert emcy(b.recorder.wait(mark, 0x80 + DUAL)) == (0x2310, 0x03)
        assert b.until(0x0F, 0x08, mask=0x4F) <= 2
        b.run(0x06, 5)
        assert peer.state is State.FAULT  # shutdown does not leave fault
        assert b.until(0x80, 0x40, mask=0x4F) <= 2  # 0x06 -> 0x80: an edge
        assert emcy(b.recorder.wait(mark, 0x80 + DUAL, lambda f: emcy(f)[0] == 0)) == (0, 0)
        # A fault while bit 7 is already high: no edge, no reset, however long it is held.
        peer.inject_fault(0x3210)
        mark = b.recorder.mark()
        b.run(0x80, 10)
        assert {s & 0x4F for s in b.statuswords(DUAL, mark)} == {0x08}
        b.run(0x00, 3)
        assert peer.state is State.FAULT
        assert b.until(0x80, 0x40, mask=0x4F) <= 2
        assert b.master.read(DUAL, 0x1001) == 0
        assert b.until(0x06, 0x21) <= 2
        # The trace: power-on, the two faults (no controlword), the resets at the edges.
        assert [e.statusword for e in peer.trace if e.controlword is None] == [0x0240, 0x0208, 0x0208]
        assert [e.statusword for e in peer.trace if e.controlword == 0x80] == [0x0240, 0x0240]


@pytest.mark.vcan
def test_reboot_sends_boot_up_and_resets_the_pdo_configuration(vcan: str) -> None:
    with bench(vcan, {DUAL: True}) as b:
        b.start()
        b.run(0x0F, 20, {DUAL: (800, 800)})
        peer = b.peers[DUAL]
        mark = b.recorder.mark()
        peer.reboot()
        assert b.recorder.wait(mark, 0x700 + DUAL).data == b"\x00"
        assert peer.nmt_state == 0x7F and peer.statusword == 0x0240 and peer.velocity_actual() == (0, 0)
        # The EDS defaults: CiA 402's predefined mappings, all four PDOs valid, no heartbeat.
        m = b.master
        assert [m.read(DUAL, 0x1600, s) for s in range(3)] == [1, 0x60400010, 0]
        assert [m.read(DUAL, 0x1A01, s) for s in range(3)] == [2, 0x60410010, 0x60610008]
        assert [m.read(DUAL, 0x1400 + k, 1) for k in range(4)] == [0x201, 0x301, 0x401, 0x501]
        assert (m.read(DUAL, 0x1017), m.read(DUAL, 0x1016, 1), m.read(DUAL, 0x6060)) == (0, 0, 0)
        time.sleep(0.2)
        assert [f.data for f in b.recorder.since(mark, 0x700 + DUAL)] == [b"\x00"]
        # Started unconfigured, it answers SYNC with the default TPDOs.
        m.nmt(0x01, DUAL)
        time.sleep(0.05)
        sync = b.recorder.mark()
        m.network.send_message(0x080, b"")
        tpdos = {f.id: f.data for f in (b.recorder.wait(sync, 0x180 + 0x100 * k + DUAL) for k in (0, 1, 3))}
        assert tpdos == {0x181: b"\x40\x02", 0x281: b"\x40\x02\x00", 0x481: bytes(8)}
        time.sleep(0.05)
        assert b.recorder.since(sync, 0x381) == []  # TPDO3 maps nothing
        # Configured again, it enables again.
        m.nmt(0x80, DUAL)
        m.configure(DUAL)
        m.nmt(0x01, DUAL)
        b.enable()


@pytest.mark.vcan
def test_nmt_commands(vcan: str) -> None:
    with bench(vcan, {DUAL: True, SINGLE: False}) as b:
        b.master.start_heartbeat()
        b.boot()
        m, peer = b.master, b.peers[DUAL]
        stopped = b.recorder.mark()
        m.nmt(0x02, DUAL)
        m.nmt(0x02, SINGLE + 1)  # another node's: ignored
        # Each peer reads its frames in order, on a thread of its own: DUAL's stop shows in its
        # heartbeat (sent at once on a change), and SINGLE answers an SDO only after it has
        # handled the command to the other node.
        b.recorder.wait(stopped, 0x700 + DUAL, lambda f: f.data == b"\x04")
        assert m.read(SINGLE, 0x1017) == HEARTBEAT_MS
        assert peer.nmt_state == 0x04 and b.peers[SINGLE].nmt_state == 0x05
        mark = b.recorder.mark()
        b.run(0x06, 5)
        assert b.recorder.since(mark, 0x181) == [] and len(b.recorder.since(mark, 0x183)) == 5
        m.nodes[DUAL].sdo.RESPONSE_TIMEOUT = 0.2
        with pytest.raises(canopen.SdoCommunicationError):
            m.read(DUAL, 0x1000)  # no SDO when stopped
        m.nodes[DUAL].sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        m.nmt(0x80, 0)  # all nodes pre-operational
        time.sleep(0.05)
        mark = b.recorder.mark()
        b.run(0x06, 3)
        assert b.recorder.since(mark, 0x181) == b.recorder.since(mark, 0x183) == []
        assert m.read(DUAL, 0x1000) == 0x00020192
        # Reset communication: boot-up, the 0x1000 area at its defaults, the drive's own kept.
        mark = b.recorder.mark()
        m.nmt(0x82, DUAL)
        b.recorder.wait(mark, 0x701, lambda f: f.data == b"\x00")
        assert (m.read(DUAL, 0x1017), m.read(DUAL, 0x1600, 0), m.read(DUAL, 0x6060)) == (0, 1, 3)
        # Reset node: the application too.
        mark = b.recorder.mark()
        m.nmt(0x81, DUAL)
        b.recorder.wait(mark, 0x701, lambda f: f.data == b"\x00")
        assert m.read(DUAL, 0x6060) == 0
        assert b.peers[SINGLE].nmt_state == 0x7F


@pytest.mark.vcan
def test_sdo_abort_injection_and_pdo_parameter_checks(vcan: str) -> None:
    with bench(vcan, {DUAL: True}) as b:
        m, peer = b.master, b.peers[DUAL]
        mark = b.recorder.mark()
        b.master.nmt(0x82, DUAL)
        b.recorder.wait(mark, 0x701, lambda f: f.data == b"\x00")

        def abort_code(action: Callable[[], object]) -> int:
            with pytest.raises(canopen.SdoAbortedError) as err:
                action()
            return err.value.code

        peer.inject_sdo_abort(0x1016, 1, 0x06090030)
        assert abort_code(lambda: m.write(DUAL, 0x1016, 1, MASTER << 16 | 150)) == 0x06090030
        assert abort_code(lambda: m.read(DUAL, 0x1016, 1)) == 0x06090030
        m.write(DUAL, 0x1017, 0, HEARTBEAT_MS)  # others answer
        peer.clear_sdo_aborts()
        m.write(DUAL, 0x1016, 1, MASTER << 16 | 150)
        # CiA 301's PDO rules.
        assert abort_code(lambda: m.write(DUAL, 0x1600, 0, 0)) == 0x08000022  # PDO valid
        m.write(DUAL, 0x1400, 1, 0x201 | COB_INVALID)
        assert abort_code(lambda: m.write(DUAL, 0x1600, 1, 0x60400010)) == 0x08000022  # count != 0
        m.write(DUAL, 0x1600, 0, 0)
        assert abort_code(lambda: m.write(DUAL, 0x1600, 1, 0x60410010)) == 0x06040041  # read-only
        assert abort_code(lambda: m.write(DUAL, 0x1600, 1, 0x60400008)) == 0x06040043  # wrong size
        assert abort_code(lambda: m.write(DUAL, 0x1600, 1, 0x20000010)) == 0x06020000  # no object
        for sub, entry in enumerate((0x60400010, 0x60FF0120, 0x60FF0220), 1):
            m.write(DUAL, 0x1600, sub, entry)
        assert abort_code(lambda: m.write(DUAL, 0x1600, 0, 3)) == 0x06040042  # 10 bytes
        m.write(DUAL, 0x1600, 0, 2)
        assert abort_code(lambda: m.write(DUAL, 0x1800, 2, 0xFF)) == 0x06090030  # event-driven TPDO
        assert abort_code(lambda: m.write(DUAL, 0x1400, 1, 0x701)) == 0x06090030  # restricted id
        m.write(DUAL, 0x1400, 1, 0x201)
        assert abort_code(lambda: m.write(DUAL, 0x1400, 1, 0x211)) == 0x06090030  # valid: id fixed
        assert abort_code(lambda: m.write(DUAL, 0x6041, 0, 0)) == 0x06010002  # canopen's own
        # A short RPDO is refused with EMCY 0x8210.
        m.nmt(0x01, DUAL)
        time.sleep(0.05)
        mark = b.recorder.mark()
        m.network.send_message(0x201, b"\x06\x00")
        assert emcy(b.recorder.wait(mark, 0x81)) == (EMCY_PDO_LENGTH, 0x11)
        assert peer.state is State.SWITCH_ON_DISABLED
