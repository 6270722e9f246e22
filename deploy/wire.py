"""Wire format between the controller and robots: fixed little-endian binary structs.

Every message is one 24-byte header followed by a fixed-size body chosen by the message type
(the byte layout, with offsets, is in ``docs/wire-format.md``)::

    header  <2sBBHHIIQ   magic b"FS", version, msg_type, robot_id, flags, epoch, seq, send_time_ns
    STATE   <ddddII      position x, y [m], velocity x, y [m/s] (f64), last_cmd_seq, reserved
    CMD     <ddIHH       acceleration x, y [m/s^2] (f64), state_seq, ttl_ms, reserved
    ESTOP   <II          reason_code, reserved
    SIGHTING <ddddHH     position x, y [m], radius [m], top speed [m/s] (f64), capture_age_ms,
                         fleet robot id (flag ROBOT; else reserved, 0)

``send_time_ns`` is the sender's monotonic clock (``time.monotonic_ns()``, CLOCK_MONOTONIC). It
is comparable with the receiver's clock only when both share it (same host) or the clocks are
synchronised; :class:`deploy.streams.WireDecoder` checks expiry only when given a clock.

``epoch`` (a sender's run) and ``seq`` (1, 2, ... within it) order a stream; the receive-side
checks on them, and on the clock, are :mod:`deploy.streams`.

Decoding never raises on any byte string: :func:`decode` returns a message or a
:class:`Rejection` with a :class:`Reason`.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import ClassVar, NamedTuple

MAGIC = b"FS"
WIRE_VERSION = 2
ACCEPTED_VERSIONS = (1, 2)
"""Version 2 adds the STATE flag LOCKSTEP (same layout); version 1 messages are still decoded."""
ROBOT_ALL = 0xFFFF  # robot_id of fleet-wide messages (ESTOP); never a robot's own id
U32_MAX = 0xFFFF_FFFF
U64_MAX = 0xFFFF_FFFF_FFFF_FFFF
TTL_MS_MAX = 0xFFFF

HEADER = struct.Struct("<2sBBHHIIQ")
STATE_BODY = struct.Struct("<ddddII")
CMD_BODY = struct.Struct("<ddIHH")
ESTOP_BODY = struct.Struct("<II")
SIGHTING_BODY = struct.Struct("<ddddHH")
HEADER_SIZE = HEADER.size  # 24


class MsgType(IntEnum):
    """Byte 3 of every message."""

    STATE = 1  # robot -> controller
    CMD = 2  # controller -> robot
    ESTOP = 3  # controller -> fleet, latched
    SIGHTING = 4  # tracker -> controller: a disc it sees that the controller does not command


MESSAGE_SIZE = {
    MsgType.STATE: HEADER_SIZE + STATE_BODY.size,  # 64
    MsgType.CMD: HEADER_SIZE + CMD_BODY.size,  # 48
    MsgType.ESTOP: HEADER_SIZE + ESTOP_BODY.size,  # 32
    MsgType.SIGHTING: HEADER_SIZE + SIGHTING_BODY.size,  # 60
}


class StateStatus(IntFlag):
    """Header ``flags`` of a STATE message: what the robot is doing on its own."""

    ESTOPPED = 1  # latched e-stop is engaged on the robot
    WATCHDOG_BRAKING = 2  # no fresh command (ttl expired): the robot brakes on its own
    CONTROLLER_LOST = 4  # the controller's liveliness token is gone
    FAULT = 8  # robot-local fault (drives, localisation)
    LOCKSTEP = 16  # version 2: a lock-stepped simulation, it waits for every answer (send lossless)


class CmdFlags(IntFlag):
    """Header ``flags`` of a CMD message."""

    BRAKE = 1  # ignore the acceleration; brake at the robot's maximum deceleration this tick
    STOP = 2  # brake to rest and stay at rest until a command with STOP clear arrives


class EstopFlags(IntFlag):
    """Header ``flags`` of an ESTOP message."""

    ENGAGED = 1  # set: e-stop raised (latched); clear: e-stop released


class SightingFlags(IntFlag):
    """Header ``flags`` of a SIGHTING message."""

    GONE = 1  # the tracker no longer sees this obstacle (left the arena): forget it
    ROBOT = 2  # the disc is one of the fleet's robots: the body's last field is its registry id


ALLOWED_FLAGS = {
    MsgType.STATE: int(StateStatus.ESTOPPED | StateStatus.WATCHDOG_BRAKING
                       | StateStatus.CONTROLLER_LOST | StateStatus.FAULT | StateStatus.LOCKSTEP),
    MsgType.CMD: int(CmdFlags.BRAKE | CmdFlags.STOP),
    MsgType.ESTOP: int(EstopFlags.ENGAGED),
    MsgType.SIGHTING: int(SightingFlags.GONE | SightingFlags.ROBOT),
}


ESTOP_ENGAGED = int(EstopFlags.ENGAGED)
GONE_BIT = int(SightingFlags.GONE)
SEEN_ROBOT_BIT = int(SightingFlags.ROBOT)
# The same bits as plain ints, for hot paths: ``int(flags) & BIT`` costs a tenth of ``flags & FLAG``
# (an IntFlag operation builds a new flag value).
FAULT_BIT = int(StateStatus.FAULT)
LOCKSTEP_BIT = int(StateStatus.LOCKSTEP)
STOP_BIT = int(CmdFlags.STOP)
BRAKE_OR_STOP = int(CmdFlags.BRAKE | CmdFlags.STOP)
# Flag values by their bits, built once: constructing an IntFlag from an int costs about a
# microsecond, and decode builds one per message.
_STATUS_BY_BITS = tuple(StateStatus(bits) for bits in range(ALLOWED_FLAGS[MsgType.STATE] + 1))
_CMD_FLAGS_BY_BITS = tuple(CmdFlags(bits) for bits in range(ALLOWED_FLAGS[MsgType.CMD] + 1))
_TYPE_BY_BYTE = {int(t): t for t in MsgType}


class Reason(IntEnum):
    """Why a message was rejected. The numbers are stable (logs, third-party clients)."""

    BAD_SIZE = 1  # shorter than the header, or not the size of its message type
    BAD_MAGIC = 2  # bytes 0..1 are not b"FS"
    BAD_VERSION = 3  # byte 2 is not one of ACCEPTED_VERSIONS
    UNKNOWN_TYPE = 4  # byte 3 is not a MsgType
    UNEXPECTED_TYPE = 5  # a known type on a key meant for another (e.g. CMD on a state key)
    BAD_SEQUENCE = 6  # epoch or seq is 0
    BAD_FLAGS = 7  # a flag bit not defined for this message type is set
    BAD_RESERVED = 8  # a reserved field is not 0
    BAD_ROBOT_ID = 9  # ROBOT_ALL on a per-robot message, or a robot id on an ESTOP
    NON_FINITE = 10  # NaN or inf in a float field
    BAD_TTL = 11  # ttl_ms is 0
    UNKNOWN_ROBOT = 12  # robot id or key name not in the registry
    ROBOT_MISMATCH = 13  # robot id differs from the robot named by the key
    STALE = 14  # seq not newer than the last accepted in this epoch, or a retired epoch
    EXPIRED = 15  # CMD older than its ttl (receiver clock shared with the sender)
    FROM_FUTURE = 16  # send time ahead of the receiver's clock by more than the tolerance
    BAD_KEY = 17  # key expression does not follow the fleet layout
    STALE_ANSWER = 18  # CMD answering a STATE the robot sent longer ago than it accepts (or never)
    BAD_VALUE = 19  # a SIGHTING's radius is not > 0 or its top speed is negative


class Rejection(NamedTuple):
    """A message that was not accepted, with the reason and a human-readable detail."""

    reason: Reason
    detail: str


_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}")


def check_name(name: object, what: str = "robot id") -> str:
    """Validate a fleet or robot name used as one key-expression chunk; return it.

    Allowed: 1..64 characters from ``[A-Za-z0-9_.-]``, not starting with '.', '-' or '@'
    (Zenoh reserves '@'-chunks). Raises ValueError naming the problem and the fix.
    """
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        raise ValueError(
            f"{what} {name!r} is not allowed: use 1-64 characters from [A-Za-z0-9_.-], "
            "starting with a letter, digit or '_' (never '@', '/', '*', '$', '?', '#' or spaces)")
    return name


class RobotRegistry:
    """Robot names (string ids in key expressions) <-> numeric u16 ids on the wire.

    ``RobotRegistry(["r0", "r1"])`` numbers robots 0, 1, ... in order; a mapping fixes ids
    explicitly. Id 0xFFFF (ROBOT_ALL) is reserved.
    """

    def __init__(self, robots: Iterable[str] | Mapping[str, int]):
        pairs = (list(robots.items()) if isinstance(robots, Mapping)
                 else [(name, i) for i, name in enumerate(robots)])
        self._by_name: dict[str, int] = {}
        self._by_id: dict[int, str] = {}
        for name, rid in pairs:
            check_name(name)
            if not isinstance(rid, int) or isinstance(rid, bool) or not 0 <= rid < ROBOT_ALL:
                raise ValueError(f"robot {name!r}: numeric id {rid!r} must be an int in "
                                 f"[0, {ROBOT_ALL - 1}] (0xFFFF is reserved for ROBOT_ALL)")
            if name in self._by_name or rid in self._by_id:
                raise ValueError(f"robot {name!r} / id {rid}: names and ids must be unique")
            self._by_name[name] = rid
            self._by_id[rid] = name
        if not self._by_name:
            raise ValueError("RobotRegistry needs at least one robot")

    def id_of(self, name: str) -> int | None:
        return self._by_name.get(name)

    def name_of(self, robot_id: int) -> str | None:
        return self._by_id.get(robot_id)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._by_name)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __len__(self) -> int:
        return len(self._by_name)


@dataclass(frozen=True, slots=True)
class StateMsg:
    """Robot -> controller. position [m] and velocity [m/s] are (x, y) in the arena frame."""

    TYPE: ClassVar[MsgType] = MsgType.STATE
    robot_id: int
    epoch: int
    seq: int
    send_time_ns: int
    position: tuple[float, float]
    velocity: tuple[float, float]
    status: StateStatus = StateStatus(0)
    last_cmd_seq: int = 0  # seq of the CMD the robot acted on in the motion this state measures, 0 = none yet

    def __post_init__(self) -> None:
        _normalise_pairs(self, "position", "velocity")


@dataclass(frozen=True, slots=True)
class CmdMsg:
    """Controller -> robot. acceleration [m/s^2] (x, y), valid for ttl_ms after send_time_ns."""

    TYPE: ClassVar[MsgType] = MsgType.CMD
    robot_id: int
    epoch: int
    seq: int
    send_time_ns: int
    acceleration: tuple[float, float]
    ttl_ms: int
    flags: CmdFlags = CmdFlags(0)
    state_seq: int = 0  # seq of the robot STATE this command answers, 0 = none

    def __post_init__(self) -> None:
        _normalise_pairs(self, "acceleration")


@dataclass(frozen=True, slots=True)
class EstopMsg:
    """Controller -> fleet. Latched: robots stay stopped until a newer ESTOP with engaged=False."""

    TYPE: ClassVar[MsgType] = MsgType.ESTOP
    epoch: int
    seq: int
    send_time_ns: int
    engaged: bool
    reason_code: int = 0  # application-defined, 0 = unspecified
    robot_id: int = ROBOT_ALL


@dataclass(frozen=True, slots=True)
class SightingMsg:
    """Tracker -> controller: obstacle ``robot_id`` (the tracker's id for it, 0..0xFFFE; not a
    robot's registry id) was a disc of ``radius`` [m] centred at ``position`` [m]
    ``capture_age_ms`` before ``send_time_ns``, and moves at most ``max_speed`` [m/s]. ``gone``:
    no longer seen, forget it. ``robot``: the registry id of the fleet robot the disc is (flag
    ROBOT; 0..0xFFFE), None: something the controller does not command."""

    TYPE: ClassVar[MsgType] = MsgType.SIGHTING
    robot_id: int
    epoch: int
    seq: int
    send_time_ns: int
    position: tuple[float, float]
    radius: float
    max_speed: float
    capture_age_ms: int = 0
    gone: bool = False
    robot: int | None = None

    def __post_init__(self) -> None:
        _normalise_pairs(self, "position")


Message = StateMsg | CmdMsg | EstopMsg | SightingMsg


def _pair(value: object) -> object:
    """(x, y) as a tuple of Python floats when it converts; otherwise unchanged (encode rejects)."""
    if type(value) is tuple and len(value) == 2 and type(value[0]) is float and type(value[1]) is float:
        return value                    # what decode and most callers hand in: nothing to convert
    try:
        pair = tuple(float(v) for v in value)  # type: ignore[attr-defined]
    except (TypeError, ValueError, OverflowError):
        return value
    return pair if len(pair) == 2 else value


def _normalise_pairs(msg: object, *fields: str) -> None:
    for field in fields:
        object.__setattr__(msg, field, _pair(getattr(msg, field)))


def _check_uint(value: object, bits: int, field: str, lo: int = 0) -> Rejection | None:
    """Range check of an integer field (encode: any of them; decode: only the lower bounds of
    epoch and seq can fail, struct.unpack yields in-range values)."""
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value < (1 << bits):
        return Rejection(Reason.BAD_SEQUENCE if field in ("epoch", "seq") else Reason.BAD_SIZE,
                         f"{field}={value!r} must be an int in [{lo}, {(1 << bits) - 1}]")
    return None


def _check_fields(msg: Message) -> Rejection | None:
    """Every field check of encode: integer ranges, then :func:`_check_meaning`."""
    epoch, seq, send_time, robot_id = msg.epoch, msg.seq, msg.send_time_ns, msg.robot_id
    if not (type(epoch) is int and type(seq) is int and type(send_time) is int
            and type(robot_id) is int and 0 < epoch <= U32_MAX and 0 < seq <= U32_MAX
            and 0 <= send_time <= U64_MAX and 0 <= robot_id <= ROBOT_ALL):
        for field, bits, lo in (("epoch", 32, 1), ("seq", 32, 1), ("send_time_ns", 64, 0),
                                ("robot_id", 16, 0)):
            bad = _check_uint(getattr(msg, field), bits, field, lo)
            if bad:
                return bad
    if isinstance(msg, StateMsg):
        extras: tuple = (("last_cmd_seq", msg.last_cmd_seq, 32),)
    elif isinstance(msg, CmdMsg):
        extras = (("ttl_ms", msg.ttl_ms, 16), ("state_seq", msg.state_seq, 32))
    elif isinstance(msg, SightingMsg):
        extras = (("capture_age_ms", msg.capture_age_ms, 16),)
        if msg.robot is not None:
            extras += (("robot", msg.robot, 16),)
    else:
        extras = (("reason_code", msg.reason_code, 32),)
    for field, value, bits in extras:
        bad = _check_uint(value, bits, field)
        if bad:
            return bad
    return _check_meaning(msg)


def _check_meaning(msg: Message) -> Rejection | None:
    """The checks a well-formed struct can still fail (shared by encode and decode): robot id
    against the type, ttl 0, flag bits, NaN/inf."""
    t = msg.TYPE
    if t is MsgType.ESTOP:
        if msg.robot_id != ROBOT_ALL:
            return Rejection(Reason.BAD_ROBOT_ID,
                             f"ESTOP robot_id={msg.robot_id} must be ROBOT_ALL (0xFFFF)")
    elif msg.robot_id == ROBOT_ALL:
        return Rejection(Reason.BAD_ROBOT_ID,
                         f"{t.name} robot_id=0xFFFF is reserved for fleet-wide messages")
    if t is MsgType.STATE:
        floats: tuple = (("position", msg.position), ("velocity", msg.velocity))
        flags = int(msg.status)
    elif t is MsgType.CMD:
        floats = (("acceleration", msg.acceleration),)
        flags = int(msg.flags)
        if msg.ttl_ms == 0:
            return Rejection(Reason.BAD_TTL, "ttl_ms=0: a command must live 1..65535 ms")
    elif t is MsgType.SIGHTING:
        floats = (("position", msg.position), ("radius, max_speed", (msg.radius, msg.max_speed)))
        flags = _sighting_flags(msg)
        if msg.robot == ROBOT_ALL:
            return Rejection(Reason.BAD_ROBOT_ID, "SIGHTING robot=0xFFFF is reserved for fleet-wide messages")
    else:
        floats = ()
        flags = ESTOP_ENGAGED if msg.engaged else 0
    if flags & ~ALLOWED_FLAGS[t]:
        return Rejection(Reason.BAD_FLAGS, f"{t.name} flags=0x{flags:04x} sets undefined bits "
                         f"(allowed mask 0x{ALLOWED_FLAGS[t]:04x})")
    for field, pair in floats:
        if len(pair) != 2:
            return Rejection(Reason.BAD_SIZE, f"{field} must have 2 components (x, y)")
        if not (math.isfinite(pair[0]) and math.isfinite(pair[1])):
            return Rejection(Reason.NON_FINITE, f"{field}={pair} contains NaN or inf")
    if t is MsgType.SIGHTING and not (msg.radius > 0 and msg.max_speed >= 0):
        return Rejection(Reason.BAD_VALUE, f"SIGHTING radius={msg.radius} must be > 0 m and "
                         f"max_speed={msg.max_speed} >= 0 m/s")
    return None


def _sighting_flags(msg: SightingMsg) -> int:
    return (GONE_BIT if msg.gone else 0) | (SEEN_ROBOT_BIT if msg.robot is not None else 0)


def encode(msg: Message) -> bytes:
    """Pack a message into its fixed-size bytes. Raises ValueError on any invalid field."""
    try:
        bad = _check_fields(msg)
    except TypeError as err:
        raise ValueError(f"{type(msg).__name__}: fields have wrong types ({err})") from None
    if bad:
        raise ValueError(f"cannot encode {type(msg).__name__}: {bad.detail}; "
                         "fix the field before sending")
    t = msg.TYPE
    if isinstance(msg, StateMsg):
        flags, body = int(msg.status), STATE_BODY.pack(*msg.position, *msg.velocity,
                                                       msg.last_cmd_seq, 0)
    elif isinstance(msg, CmdMsg):
        flags, body = int(msg.flags), CMD_BODY.pack(*msg.acceleration, msg.state_seq,
                                                    msg.ttl_ms, 0)
    elif isinstance(msg, SightingMsg):
        flags = _sighting_flags(msg)
        body = SIGHTING_BODY.pack(*msg.position, msg.radius, msg.max_speed, msg.capture_age_ms, msg.robot or 0)
    else:
        flags = ESTOP_ENGAGED if msg.engaged else 0
        body = ESTOP_BODY.pack(msg.reason_code, 0)
    return HEADER.pack(MAGIC, WIRE_VERSION, int(t), msg.robot_id, flags, msg.epoch, msg.seq,
                       msg.send_time_ns) + body


def decode(data: bytes | bytearray | memoryview,
           expect: MsgType | None = None) -> Message | Rejection:
    """Structural decode of one message; never raises on any bytes.

    Checks, in this order: size >= 24, magic, version, type, ``expect`` (UNEXPECTED_TYPE),
    exact size for the type, flags, epoch/seq (BAD_SEQUENCE), robot id, ttl, finite floats,
    a sighting's radius and speed (BAD_VALUE),
    reserved. Context checks (registry, staleness, expiry) are in :class:`WireDecoder`.
    """
    buf = memoryview(data).tobytes()  # TypeError for non-bytes-like input (a caller bug)
    if len(buf) < HEADER_SIZE:
        return Rejection(Reason.BAD_SIZE, f"{len(buf)} bytes is shorter than the "
                         f"{HEADER_SIZE}-byte header")
    magic, version, type_byte, robot_id, flags, epoch, seq, send_time_ns = HEADER.unpack_from(buf)
    if magic != MAGIC:
        return Rejection(Reason.BAD_MAGIC, f"magic {magic!r} is not {MAGIC!r}")
    if version not in ACCEPTED_VERSIONS:
        return Rejection(Reason.BAD_VERSION, f"version {version} is not one of {ACCEPTED_VERSIONS}: "
                         "sender and receiver speak different wire formats")
    t = _TYPE_BY_BYTE.get(type_byte)
    if t is None:
        return Rejection(Reason.UNKNOWN_TYPE, f"message type {type_byte} is not defined")
    if expect is not None and t is not expect:
        return Rejection(Reason.UNEXPECTED_TYPE, f"{t.name} where {expect.name} was expected")
    if len(buf) != MESSAGE_SIZE[t]:
        return Rejection(Reason.BAD_SIZE, f"{t.name} must be {MESSAGE_SIZE[t]} bytes, "
                         f"got {len(buf)}")
    allowed = ALLOWED_FLAGS[t] & ~(int(StateStatus.LOCKSTEP) if version == 1 and t is MsgType.STATE else 0)
    if flags & ~allowed:  # before building IntFlag values from untrusted bits
        return Rejection(Reason.BAD_FLAGS, f"{t.name} flags=0x{flags:04x} sets undefined bits "
                         f"(allowed mask 0x{allowed:04x} in version {version})")
    if epoch == 0 or seq == 0:   # the only range a u32 can fail; the other fields fit by layout
        field, value = ("epoch", epoch) if epoch == 0 else ("seq", seq)
        return Rejection(Reason.BAD_SEQUENCE, f"{field}={value} must be an int in [1, {U32_MAX}]")
    msg: Message
    if t is MsgType.STATE:
        px, py, vx, vy, last_cmd_seq, reserved = STATE_BODY.unpack_from(buf, HEADER_SIZE)
        msg = StateMsg(robot_id, epoch, seq, send_time_ns, (px, py), (vx, vy),
                       _STATUS_BY_BITS[flags], last_cmd_seq)
    elif t is MsgType.CMD:
        ax, ay, state_seq, ttl_ms, reserved = CMD_BODY.unpack_from(buf, HEADER_SIZE)
        msg = CmdMsg(robot_id, epoch, seq, send_time_ns, (ax, ay), ttl_ms, _CMD_FLAGS_BY_BITS[flags],
                     state_seq)
    elif t is MsgType.SIGHTING:
        px, py, radius, max_speed, capture_age_ms, reserved = SIGHTING_BODY.unpack_from(buf, HEADER_SIZE)
        robot = None
        if flags & SEEN_ROBOT_BIT:     # the last field is the robot's id, not reserved
            robot, reserved = reserved, 0
        msg = SightingMsg(robot_id, epoch, seq, send_time_ns, (px, py), radius, max_speed, capture_age_ms,
                          bool(flags & GONE_BIT), robot)
    else:
        reason_code, reserved = ESTOP_BODY.unpack_from(buf, HEADER_SIZE)
        msg = EstopMsg(epoch, seq, send_time_ns, bool(flags & ESTOP_ENGAGED), reason_code,
                       robot_id)
    bad = _check_meaning(msg)
    if bad:
        return bad
    if reserved != 0:
        return Rejection(Reason.BAD_RESERVED, f"{t.name} reserved field is {reserved}, not 0")
    return msg
