"""A CANopen CiA 402 profile-velocity drive on a real SocketCAN bus, for the tests marked `vcan`.

`Cia402Peer` is the drive docs/protocol.md ("CANopen CiA 402") configures: python canopen's
`LocalNode` (its SDO server and object dictionary, from dbc/cia402_drive.eds or
cia402_drive_single.eds) plus what `LocalNode` lacks: boot-up, NMT commands, the heartbeat
producer (0x1017) and consumer (0x1016:01), PDOs (canopen hands received RPDOs only to
callbacks, issue #558), the CiA 402 state machine and a first-order motor per axis.

Choices, as a real drive makes them: the statusword carries bit 9 (remote) always and bit 4
(voltage enabled) in ready to switch on, switched on, operation enabled and quick stop active
(0x0231, 0x0233, 0x0237, 0x0217; switch on disabled 0x0240, fault 0x0208), so a master must
mask (0x6F). Quick stop behaves as option code 2: the motor slows with the model's time
constant and the drive goes to switch on disabled once stopped. Enabling is refused unless
0x6060 == 3. A silent heartbeat producer (monitored from its first heartbeat after 0x1016:01
is written) sends EMCY 0x8130 and faults the drive; a bus-off (`enter_bus_off`) faults it too.
Both are communication errors, and with CiA 301's default error behaviour (0x1029 = 0) they
take an operational node to pre-operational; only NMT start (or a reset) brings it back. Each
change of the NMT state goes out in a heartbeat at once (as CANopenNode does and hostsim's
drives do). PDO parameters are checked when written
(CiA 301 order disable, map, enable; aborts 0x08000022, 0x06040041-43, 0x06090030); TPDO
types 1-240 (every n-th SYNC) and RPDO types 0-240 (applied at the next SYNC), 0xFE and 0xFF
(on receipt). SDO and PDOs stop in NMT stopped. Frames are received by a python-can listener
on the canopen Network's notifier thread; one more thread times heartbeats and the quick stop.
"""

from __future__ import annotations

import enum
import math
import pathlib
import struct
import threading
import time
from types import TracebackType
from typing import NamedTuple

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

ROOT = pathlib.Path(__file__).resolve().parent.parent
DUAL_EDS = ROOT / "dbc" / "cia402_drive.eds"
SINGLE_EDS = ROOT / "dbc" / "cia402_drive_single.eds"

# NMT states as the heartbeat carries them, and NMT command specifiers (CiA 301).
BOOTUP, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x01, 0x02, 0x80, 0x81, 0x82

PROFILE_VELOCITY = 3
REMOTE = 0x0200  # statusword bit 9
FAULT_RESET = 0x80  # controlword bit 7
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat error
EMCY_BUS_OFF_RECOVERED = 0x8140  # recovered from bus off
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
DEFAULT_FAULT = 0x2310  # continuous over current (device output side)
# SDO abort codes (CiA 301) the peer answers PDO parameter writes with.
ABORT_GENERAL = 0x08000000
ABORT_DEVICE_STATE = 0x08000022
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_INCOMPATIBLE = 0x06040043
ABORT_VALUE_RANGE = 0x06090030
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
COB_INVALID = 1 << 31
_QUICK_STOP_DONE = 0.5  # |velocity| (raw) below which quick stop counts as stopped
_COMM_AREA = range(0x1000, 0x2000)


class State(enum.IntEnum):
    """CiA 402 drive states, each valued by its statusword without bit 9 (bit 4 as chosen)."""

    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0031
    SWITCHED_ON = 0x0033
    OPERATION_ENABLED = 0x0037
    QUICK_STOP_ACTIVE = 0x0017
    FAULT = 0x0008


class Transition(NamedTuple):
    """One trace entry: monotonic time (s), the controlword received (None: an event inside
    the drive, a fault, a reset or the end of a quick stop) and the statusword after it."""

    t: float
    controlword: int | None
    statusword: int


class _Pdo(NamedTuple):
    """One valid PDO as configured: COB-ID, transmission type, mapped (index, sub, bytes)."""

    cob_id: int
    transmission: int
    entries: tuple[tuple[int, int, int], ...]


def next_state(state: State, controlword: int, previous: int, mode: int) -> State:
    """The state a controlword leads to (CiA 402 device control, quick stop option code 2).
    `previous` is the controlword before it, for the fault reset's rising edge of bit 7."""
    if state is State.FAULT:
        rising = controlword & FAULT_RESET and not previous & FAULT_RESET
        return State.SWITCH_ON_DISABLED if rising else state  # 15
    if controlword & FAULT_RESET:
        return state  # fault reset outside fault: no command
    if not controlword & 0x02:  # disable voltage: 7, 9, 10, 12
        return State.SWITCH_ON_DISABLED
    if not controlword & 0x04:  # quick stop: 11 from operation enabled, 7 and 10
        if state is State.OPERATION_ENABLED:
            return State.QUICK_STOP_ACTIVE
        return State.SWITCH_ON_DISABLED if state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON) else state
    if not controlword & 0x01:  # shutdown: 2, 6, 8
        return State.READY_TO_SWITCH_ON if state is not State.QUICK_STOP_ACTIVE else state
    if state is State.SWITCH_ON_DISABLED or state is State.QUICK_STOP_ACTIVE:
        return state  # switch on needs shutdown first; quick stop ends by itself (option code 2)
    if not controlword & 0x08:  # switch on (3) / disable operation (5)
        return State.SWITCHED_ON
    # enable operation: 4, or 3 + 4 from ready to switch on; refused outside profile velocity
    return State.OPERATION_ENABLED if mode == PROFILE_VELOCITY else State.SWITCHED_ON


def error_register(code: int) -> int:
    """The error register (0x1001) bits of an EMCY error code (CiA 301): bit 0 (generic) with
    any error and the class bit of its code: current (0x2xxx) bit 1, voltage (0x3xxx) bit 2,
    temperature (0x4xxx) bit 3, communication (0x81xx) and protocol (0x82xx) errors bit 4; 0
    for error reset (0x0000). hostsim's drives use the same (canopen_drive::error_register)."""
    if code == 0:
        return 0
    classes = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08}
    return 0x01 | classes.get(code >> 12, 0) | (0x10 if code >> 8 in (0x81, 0x82) else 0)


def _restricted(cob_id: int) -> bool:
    """CiA 301's restricted COB-IDs (NMT, SYNC/EMCY, TIME, SDO, LSS, heartbeat)."""
    return (cob_id <= 0x7F or 0x101 <= cob_id <= 0x180 or 0x581 <= cob_id <= 0x5FF
            or 0x601 <= cob_id <= 0x67F or 0x6E0 <= cob_id <= 0x6FF or cob_id >= 0x701)


class _Listener(can.Listener):
    """Hands every frame the Network's notifier reads to the peer (same thread as SDO)."""

    def __init__(self, peer: Cia402Peer) -> None:
        self._peer = peer

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        try:
            self._peer._on_frame(msg.arbitration_id, bytes(msg.data))
        except Exception as exc:  # kept for the test (`errors`): the notifier must go on
            self._peer._error(exc)


class Cia402Peer:
    """A simulated CiA 402 drive (node `node_id`) on `channel`; boots (sends its boot-up) at
    once. `with Cia402Peer(...) as peer:` or `close()` ends its threads and its bus.

    `actual_per_target`: the velocity actual value's (0x606C) units per target velocity
    (0x60FF) unit; vendors differ, e.g. 10 for a drive taking rpm and reporting 0.1 rpm.
    `own_frames_only`: the socket's acceptance filter passes only what a drive's CAN
    controller would (NMT, SYNC, heartbeats and this node's ids) so the rest of the bus never
    reaches the peer's Python thread."""

    def __init__(self, channel: str, node_id: int, eds: str | pathlib.Path = DUAL_EDS, *,
                 time_constant_s: float = 0.05, interface: str = "socketcan",
                 actual_per_target: float = 1.0, own_frames_only: bool = False) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} is outside 1..127")
        if not (math.isfinite(actual_per_target) and actual_per_target > 0):
            raise ValueError(f"actual_per_target {actual_per_target} is not a positive number")
        self.node_id = node_id
        self.time_constant_s = time_constant_s
        self.actual_per_target = actual_per_target
        self.node = canopen.LocalNode(node_id, canopen.import_od(str(eds), node_id))
        od = self.node.object_dictionary
        self.axes = 2 if isinstance(od[0x60FF], ODArray) else 1
        self._subs = (1, 2) if self.axes == 2 else (0,)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._closing = False
        self._trace: list[Transition] = []
        self._sdo_aborts: dict[tuple[int, int], int] = {}
        self._heartbeat_paused = False
        self._bus_off = False
        self._errors: list[BaseException] = []
        self._nmt = BOOTUP  # until the boot-up is sent: every frame is ignored
        self._heartbeat_next = 0.0
        self._reset_application()
        self._reset_communication()
        # LocalNode's NMT slave answers commands without a boot-up and runs 0x1017 as a
        # kernel-timed task the hooks cannot silence: the peer does both itself.
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.node.add_write_callback(self._on_write)  # type: ignore[no-untyped-call]
        self.node.add_read_callback(self._on_read)  # type: ignore[no-untyped-call]
        self.network = canopen.Network()
        self.network.add_node(self.node)
        self.network.unsubscribe(0, self.node.nmt.on_command)
        self.network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        self.network.subscribe(self.node.sdo.rx_cobid, self._on_sdo)
        self.network.connect(interface=interface, channel=channel)
        if own_frames_only:
            assert self.network.bus is not None
            self.network.bus.set_filters([
                {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},  # NMT
                {"can_id": 0x080, "can_mask": 0x7FF, "extended": False},  # SYNC (0x1005's default)
                {"can_id": 0x700, "can_mask": 0x780, "extended": False},  # heartbeats
                {"can_id": node_id, "can_mask": 0x07F, "extended": False},  # this node's ids
            ])
        assert self.network.notifier is not None
        self.network.notifier.add_listener(_Listener(self))
        with self._lock:
            self._boot()
        self._thread = threading.Thread(target=self._guarded_run, name=f"cia402-peer-{node_id}", daemon=True)
        self._thread.start()

    # --- the test's view and hooks ----------------------------------------------------------

    @property
    def trace(self) -> list[Transition]:
        """A copy of the trace: each controlword that differs from the one before it and each
        state change, in order."""
        with self._lock:
            return list(self._trace)

    @property
    def errors(self) -> list[BaseException]:
        """Exceptions raised while handling frames or timing (a test asserts there are none)."""
        with self._lock:
            return list(self._errors)

    @property
    def state(self) -> State:
        with self._lock:
            return self._state

    @property
    def statusword(self) -> int:
        with self._lock:
            return self._statusword()

    @property
    def nmt_state(self) -> int:
        with self._lock:
            return self._nmt

    def velocity_actual(self) -> tuple[int, ...]:
        """Velocity actual value per axis (0x606C), raw units, now."""
        with self._lock:
            self._advance()
            return tuple(round(v * self.actual_per_target) for v in self._velocity)

    def target_velocity(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(self._target)

    def inject_fault(self, code: int = DEFAULT_FAULT) -> None:
        """A drive fault: state fault, the error register set and an EMCY with `code`."""
        with self._lock:
            self._fault(code)

    def stop_heartbeat(self) -> None:
        """The drive goes silent: no heartbeats (it still works and answers otherwise)."""
        with self._lock:
            self._heartbeat_paused = True

    def resume_heartbeat(self) -> None:
        """Heartbeats again, the first at once."""
        with self._lock:
            self._heartbeat_paused = False
            self._heartbeat_next = time.monotonic()
        self._wake.set()

    def enter_bus_off(self) -> None:
        """The drive's CAN controller goes bus-off: it sends and takes nothing until
        `leave_bus_off`. The drive reacts to the communication error: fault (abort connection;
        the EMCY cannot go out), and pre-operational if it was operational."""
        with self._lock:
            self._bus_off = True
            self._error_register |= error_register(EMCY_BUS_OFF_RECOVERED)
            self._set_state(State.FAULT)
            if self._nmt == OPERATIONAL:
                self._set_nmt(PRE_OPERATIONAL)

    def leave_bus_off(self) -> None:
        """Back on the bus: EMCY 0x8140 (recovered from bus off), then a heartbeat with the
        NMT state it is in."""
        with self._lock:
            self._bus_off = False
            self._emcy(EMCY_BUS_OFF_RECOVERED)
            self._heartbeat_now()
        self._wake.set()

    def reboot(self) -> None:
        """A power cycle: the object dictionary at the EDS defaults (PDOs too), the drive switch
        on disabled and at rest, a boot-up, pre-operational. The test hooks are kept."""
        with self._lock:
            self._reset_application()
            self._reset_communication()
            self._boot()
        self._wake.set()

    def inject_sdo_abort(self, index: int, subindex: int, code: int = ABORT_GENERAL) -> None:
        """Every SDO upload or download of index:subindex is aborted with `code` until cleared."""
        with self._lock:
            self._sdo_aborts[(index, subindex)] = code

    def clear_sdo_aborts(self) -> None:
        with self._lock:
            self._sdo_aborts.clear()

    def close(self) -> None:
        """Stops the peer's thread and the Network (its notifier thread and bus)."""
        with self._lock:
            if self._closing:
                return
            self._closing = True
        self._wake.set()
        self._thread.join(timeout=5.0)
        self.network.disconnect()

    def __enter__(self) -> Cia402Peer:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # --- state, resets ------------------------------------------------------------------------

    def _reset_application(self) -> None:
        """Power-on state of the drive and the 0x6000 area."""
        self.node.data_store = {i: s for i, s in self.node.data_store.items() if i in _COMM_AREA}
        self._state = State.SWITCH_ON_DISABLED
        self._slowing_to: State | None = None
        self._controlword = 0
        self._mode = int(self._default(0x6060, 0))
        self._target = [0] * self.axes
        self._velocity = [0.0] * self.axes
        self._model_t = time.monotonic()
        self._error_register = 0
        self._record(None)

    def _reset_communication(self) -> None:
        """The 0x1000 area at its defaults: no heartbeat, no consumer, the default PDOs."""
        self.node.data_store = {i: s for i, s in self.node.data_store.items() if i not in _COMM_AREA}
        self._heartbeat_ms = int(self._default(0x1017, 0))
        self._consumer: tuple[int, float] | None = None  # (producer node, timeout s)
        self._consumer_deadline: float | None = None
        self._pdo_dirty = True
        self._rpdos: dict[int, _Pdo] = {}
        self._tpdos: list[_Pdo] = []
        self._sync_id = 0x80
        self._sync_count = 0
        self._pending_rpdos: dict[int, bytes] = {}

    def _boot(self) -> None:
        self._send(0x700 + self.node_id, b"\x00")
        self._nmt = PRE_OPERATIONAL
        self._heartbeat_next = time.monotonic() + self._heartbeat_ms / 1000

    def _default(self, index: int, subindex: int) -> int:
        obj = self._od_var(index, subindex)
        return int(obj.default or 0)

    def _od_var(self, index: int, subindex: int) -> ODVariable:
        obj = self.node.object_dictionary[index]
        if isinstance(obj, (ODArray, ODRecord)):
            obj = obj[subindex]
        assert isinstance(obj, ODVariable)
        return obj

    def _value(self, index: int, subindex: int) -> int:
        """An integer object's value as an SDO upload would give it."""
        obj = self._od_var(index, subindex)
        return int(obj.decode_raw(self.node.get_data(index, subindex)))

    def _statusword(self) -> int:
        return int(self._state) | REMOTE

    def _record(self, controlword: int | None) -> None:
        self._trace.append(Transition(time.monotonic(), controlword, self._statusword()))

    def _set_state(self, state: State) -> None:
        """A state change from inside the drive (fault), traced without a controlword."""
        self._advance()
        self._slowing_to = None
        if state is not self._state:
            self._state = state
            self._record(None)

    def _error(self, exc: BaseException) -> None:
        with self._lock:
            self._errors.append(exc)

    def _fault(self, code: int) -> None:
        self._error_register = error_register(code)
        self._set_state(State.FAULT)
        self._emcy(code)

    def _set_nmt(self, state: int) -> None:
        """The NMT state becomes `state`; a change goes out in a heartbeat at once."""
        if state != self._nmt:
            self._nmt = state
            self._heartbeat_now()

    def _heartbeat_now(self) -> None:
        """A heartbeat now (if the producer runs), the next a period later."""
        if self._heartbeat_ms:
            if not self._heartbeat_paused:
                self._send(0x700 + self.node_id, bytes([self._nmt]))
            self._heartbeat_next = time.monotonic() + self._heartbeat_ms / 1000
            self._wake.set()

    def _emcy(self, code: int, register: int = 0) -> None:
        """An EMCY with the error register, or'ed with `register` for a passing error."""
        if self._nmt in (PRE_OPERATIONAL, OPERATIONAL):  # CiA 301: no EMCY when stopped
            self._send(0x80 + self.node_id, struct.pack("<HB5x", code, self._error_register | register))

    def _send(self, can_id: int, data: bytes) -> None:
        if not self._bus_off:
            self.network.send_message(can_id, data)

    # --- the motor ------------------------------------------------------------------------

    def _advance(self) -> None:
        """Each axis's velocity to now: first order towards the target in operation enabled
        (profile velocity), towards 0 otherwise; a finished quick stop ends in switch on disabled,
        a finished slow down (0x605B / 0x605C = 1) in the state it was for."""
        now = time.monotonic()
        decay = math.exp(-(now - self._model_t) / self.time_constant_s)
        self._model_t = now
        driving = (self._state is State.OPERATION_ENABLED and self._mode == PROFILE_VELOCITY
                   and self._slowing_to is None)
        for axis, v in enumerate(self._velocity):
            goal = self._target[axis] if driving else 0
            v = goal + (v - goal) * decay
            self._velocity[axis] = 0.0 if goal == 0 and abs(v) < 1e-3 else v
        at_rest = all(abs(v) < _QUICK_STOP_DONE for v in self._velocity)
        if self._state is State.QUICK_STOP_ACTIVE and at_rest:
            self._state = State.SWITCH_ON_DISABLED
            self._record(None)
        if self._slowing_to is not None and at_rest:
            self._state, self._slowing_to = self._slowing_to, None
            self._record(None)

    # --- objects: SDO and PDO access ------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        with self._lock:
            if index == 0x6041:
                return self._statusword()
            if index == 0x6040:
                return self._controlword
            if index in (0x6060, 0x6061):
                return self._mode
            if index == 0x1001:
                return self._error_register
            if index in (0x606C, 0x60FF) and subindex in self._subs:
                self._advance()
                axis = self._subs.index(subindex)
                if index == 0x606C:
                    return round(self._velocity[axis] * self.actual_per_target)
                return self._target[axis]
            return None

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Every write (SDO download or RPDO) before it is stored; raising aborts it."""
        with self._lock:
            value = int(od.decode_raw(data))
            if (od.min is not None and value < od.min) or (od.max is not None and value > od.max):
                raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)  # the EDS's LowLimit / HighLimit
            if index == 0x6040:
                self._controlword_received(value)
            elif index == 0x60FF and subindex in self._subs:
                self._advance()
                self._target[self._subs.index(subindex)] = value
            elif index == 0x6060:
                self._advance()
                self._mode = value
            elif index == 0x1017:
                self._heartbeat_ms = value
                self._heartbeat_next = time.monotonic() + value / 1000
                self._wake.set()
            elif index == 0x1016 and subindex == 1:
                node, ms = (value >> 16) & 0x7F, value & 0xFFFF
                self._consumer = (node, ms / 1000) if node and ms else None
                self._consumer_deadline = None  # monitoring starts at the first heartbeat
            elif 0x1400 <= index <= 0x1BFF:
                self._check_pdo_write(index, subindex, value)
                self._pdo_dirty = True
            elif index == 0x1005:
                if value & ~0x7FF:
                    raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)  # the peer consumes SYNC only
                self._pdo_dirty = True

    def _controlword_received(self, controlword: int) -> None:
        self._advance()
        previous, self._controlword = self._controlword, controlword
        state = next_state(self._state, controlword, previous, self._mode)
        # Shutdown (8) and disable operation (5) with option code 1 (0x605B, 0x605C): slow
        # down first, still operation enabled, as hostsim's drives do.
        option = {State.READY_TO_SWITCH_ON: 0x605B, State.SWITCHED_ON: 0x605C}.get(state)
        slows = self._state is State.OPERATION_ENABLED and option is not None and self._value(option, 0) == 1
        self._slowing_to = state if slows else None
        if slows:
            state = State.OPERATION_ENABLED
        if state is State.SWITCH_ON_DISABLED and self._state is State.FAULT:
            self._error_register = 0
            self._emcy(0x0000)  # error reset
        if state is not self._state or controlword != previous:
            self._state = state
            self._record(controlword)

    def _check_pdo_write(self, index: int, subindex: int, value: int) -> None:
        """CiA 301's rules for PDO parameters: map only a disabled PDO with its count at 0,
        objects that exist, fit and may go that way; at most 8 bytes."""
        rx = index < 0x1800
        comm = index & ~0x0200  # 0x14xx / 0x18xx
        mapping = index | 0x0200
        if index == comm and subindex == 1:
            old = self._value(index, 1)
            if value & (1 << 29) or (not value & COB_INVALID and _restricted(value & 0x7FF)):
                raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)
            if not value & COB_INVALID and not old & COB_INVALID and (value ^ old) & 0x7FF:
                raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)  # a valid PDO's id cannot change
        elif index == comm and subindex == 2:
            if not (value <= 240 or (rx and value >= 0xFE)) or (not rx and value == 0):
                raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)  # TPDOs: synchronous 1-240 only
        elif index == mapping:
            if not self._value(comm, 1) & COB_INVALID:
                raise canopen.SdoAbortedError(ABORT_DEVICE_STATE)
            if subindex == 0:
                if value > 8:
                    raise canopen.SdoAbortedError(ABORT_VALUE_RANGE)
                total = sum(self._mapped(self._value(index, s), rx)[2] for s in range(1, value + 1))
                if total > 8:
                    raise canopen.SdoAbortedError(ABORT_PDO_LENGTH)
            else:
                if self._value(index, 0) != 0:
                    raise canopen.SdoAbortedError(ABORT_DEVICE_STATE)
                if value:
                    self._mapped(value, rx)

    def _mapped(self, entry: int, rx: bool) -> tuple[int, int, int]:
        """(index, sub, bytes) of a mapping entry, or the abort that refuses it."""
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        od = self.node.object_dictionary
        if index not in od:
            raise canopen.SdoAbortedError(ABORT_NO_OBJECT)
        obj = od[index]
        if isinstance(obj, (ODArray, ODRecord)):
            if subindex not in obj:
                raise canopen.SdoAbortedError(ABORT_NO_SUBINDEX)
            obj = obj[subindex]
        elif subindex != 0:
            raise canopen.SdoAbortedError(ABORT_NO_SUBINDEX)
        assert isinstance(obj, ODVariable)
        if not obj.pdo_mappable or not (obj.writable if rx else obj.readable):
            raise canopen.SdoAbortedError(ABORT_NOT_MAPPABLE)
        if bits != len(obj):
            raise canopen.SdoAbortedError(ABORT_INCOMPATIBLE)
        return index, subindex, bits // 8

    def _pdos(self) -> None:
        """The PDO tables from the object dictionary, when its PDO parameters changed."""
        if not self._pdo_dirty:
            return
        self._pdo_dirty = False
        self._sync_id = self._value(0x1005, 0) & 0x7FF
        self._rpdos, self._tpdos = {}, []
        for k in range(4):
            for comm in (0x1400 + k, 0x1800 + k):
                cob_id, count = self._value(comm, 1), self._value(comm + 0x200, 0)
                if cob_id & COB_INVALID or count == 0:
                    continue
                entries = tuple(self._mapped(self._value(comm + 0x200, s), comm < 0x1800)
                                for s in range(1, count + 1))
                pdo = _Pdo(cob_id & 0x7FF, self._value(comm, 2), entries)
                if comm < 0x1800:
                    self._rpdos[pdo.cob_id] = pdo
                else:
                    self._tpdos.append(pdo)

    # --- frames -----------------------------------------------------------------------------

    def _on_sdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if self._closing or self._bus_off or self._nmt in (BOOTUP, STOPPED):
                return
            if len(data) == 8 and data[0] & 0xE0 in (0x20, 0x40):  # initiate download / upload
                index, subindex = struct.unpack_from("<HB", data, 1)
                code = self._sdo_aborts.get((index, subindex))
                if code is not None:
                    self._send(0x580 + self.node_id, struct.pack("<BHBI", 0x80, index, subindex, code))
                    return
            self.node.sdo.on_request(can_id, data, timestamp)  # type: ignore[no-untyped-call]

    def _on_frame(self, can_id: int, data: bytes) -> None:
        with self._lock:
            if self._closing or self._bus_off or self._nmt == BOOTUP:
                return
            if can_id == 0 and len(data) >= 2:
                self._on_nmt(data[0], data[1])
                return
            if self._consumer is not None and can_id == 0x700 + self._consumer[0] and data:
                self._consumer_deadline = time.monotonic() + self._consumer[1]
                self._wake.set()
                return
            if self._nmt != OPERATIONAL:
                return
            self._pdos()
            if can_id == self._sync_id and len(data) <= 1:
                self._on_sync()
            elif can_id in self._rpdos:
                pdo = self._rpdos[can_id]
                if len(data) < sum(size for _, _, size in pdo.entries):
                    self._emcy(EMCY_PDO_LENGTH, 0x11)  # generic + communication; no fault
                elif pdo.transmission <= 240:
                    self._pending_rpdos[can_id] = data
                else:
                    self._apply_rpdo(pdo, data)

    def _on_nmt(self, command: int, node: int) -> None:
        if node not in (0, self.node_id):
            return
        if command == NMT_START:
            self._pdos()
            self._sync_count = 0
            self._pending_rpdos.clear()
            self._set_nmt(OPERATIONAL)
        elif command == NMT_STOP:
            self._set_nmt(STOPPED)
        elif command == NMT_PRE_OPERATIONAL:
            self._set_nmt(PRE_OPERATIONAL)
        elif command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            if command == NMT_RESET_NODE:
                self._reset_application()
            self._reset_communication()
            self._boot()
            self._wake.set()

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        offset = 0
        for index, subindex, size in pdo.entries:
            self.node.set_data(index, subindex, data[offset:offset + size])
            offset += size

    def _on_sync(self) -> None:
        for cob_id, data in sorted(self._pending_rpdos.items()):
            self._apply_rpdo(self._rpdos[cob_id], data)
        self._pending_rpdos.clear()
        self._sync_count += 1
        self._advance()
        for pdo in self._tpdos:
            if self._sync_count % pdo.transmission == 0:
                payload = b"".join(self.node.get_data(i, s)[:size] for i, s, size in pdo.entries)
                self._send(pdo.cob_id, payload)

    # --- the timing thread: heartbeat producer and consumer, quick stop ----------------------

    def _guarded_run(self) -> None:
        try:
            self._run()
        except Exception as exc:
            self._error(exc)

    def _run(self) -> None:
        while True:
            with self._lock:
                if self._closing:
                    return
                now = time.monotonic()
                if self._heartbeat_ms and now >= self._heartbeat_next:
                    if not self._heartbeat_paused:
                        self._send(0x700 + self.node_id, bytes([self._nmt]))
                    period = self._heartbeat_ms / 1000
                    self._heartbeat_next += period
                    if self._heartbeat_next <= now:  # late by a period or more: no burst
                        self._heartbeat_next = now + period
                if self._consumer_deadline is not None and now >= self._consumer_deadline:
                    self._consumer_deadline = None  # once, until the producer is heard again
                    if self._state is not State.FAULT:
                        self._fault(EMCY_HEARTBEAT)
                    if self._nmt == OPERATIONAL:  # 0x1029:01 = 0
                        self._set_nmt(PRE_OPERATIONAL)
                if self._state is State.QUICK_STOP_ACTIVE:
                    self._advance()
                deadlines = [now + (0.005 if self._state is State.QUICK_STOP_ACTIVE else 0.1)]
                if self._heartbeat_ms:
                    deadlines.append(self._heartbeat_next)
                if self._consumer_deadline is not None:
                    deadlines.append(self._consumer_deadline)
                self._wake.clear()
            self._wake.wait(max(0.0, min(deadlines) - time.monotonic()))
