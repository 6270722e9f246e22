"""Wire format: exact bytes, round trips, and every kind of corruption rejected for its reason."""

from __future__ import annotations

import dataclasses
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.streams import RejectCounter, Stamper, WireDecoder
from deploy.wire import (
    ACCEPTED_VERSIONS,
    HEADER_SIZE,
    MESSAGE_SIZE,
    ROBOT_ALL,
    U32_MAX,
    CmdFlags,
    CmdMsg,
    EstopMsg,
    MsgType,
    Reason,
    Rejection,
    RobotRegistry,
    SightingMsg,
    StateMsg,
    StateStatus,
    check_name,
    decode,
    encode,
)

finite = st.floats(allow_nan=False, allow_infinity=False)
pairs = st.tuples(finite, finite)
u32_pos = st.integers(1, U32_MAX)
u32 = st.integers(0, U32_MAX)
u64 = st.integers(0, 2**64 - 1)
robot_ids = st.integers(0, ROBOT_ALL - 1)

states = st.builds(StateMsg, robot_ids, u32_pos, u32_pos, u64, pairs, pairs,
                   st.sampled_from(range(16)).map(StateStatus), u32)
cmds = st.builds(CmdMsg, robot_ids, u32_pos, u32_pos, u64, pairs, st.integers(1, 0xFFFF),
                 st.sampled_from(range(4)).map(CmdFlags), u32)
estops = st.builds(EstopMsg, u32_pos, u32_pos, u64, st.booleans(), u32)
sightings = st.builds(SightingMsg, robot_ids, u32_pos, u32_pos, u64, pairs,
                      st.floats(min_value=1e-9, max_value=1e3), st.floats(min_value=0.0, max_value=1e3),
                      st.integers(0, 0xFFFF), st.booleans(), st.one_of(st.none(), robot_ids))
messages = st.one_of(states, cmds, estops, sightings)

# (message type -> byte offsets of its f64 fields, offset and format of its reserved field)
FLOAT_OFFSETS = {MsgType.STATE: (24, 32, 40, 48), MsgType.CMD: (24, 32), MsgType.ESTOP: (),
                 MsgType.SIGHTING: (24, 32, 40, 48)}
RESERVED = {MsgType.STATE: (60, "<I"), MsgType.CMD: (46, "<H"), MsgType.ESTOP: (28, "<I"),
            MsgType.SIGHTING: (58, "<H")}


def patch(data: bytes, offset: int, fmt: str, value) -> bytes:
    buf = bytearray(data)
    struct.pack_into(fmt, buf, offset, value)
    return bytes(buf)


def reason_of(result) -> Reason | None:
    return result.reason if isinstance(result, Rejection) else None


def test_command_bytes_match_the_documented_layout():
    """The example of docs/wire-format.md, worked out by hand from the offset table."""
    msg = CmdMsg(robot_id=2, epoch=0x01020304, seq=5, send_time_ns=1_000_000_000,
                 acceleration=(1.0, -0.5), ttl_ms=100, flags=CmdFlags.BRAKE, state_seq=4)
    expected = bytes.fromhex(
        "4653" "02" "02" "0200" "0100" "04030201" "05000000" "00ca9a3b00000000"
        "000000000000f03f" "000000000000e0bf" "04000000" "6400" "0000")
    assert encode(msg) == expected
    assert decode(expected) == msg


def test_state_and_estop_bytes_match_the_documented_layout():
    state = StateMsg(robot_id=1, epoch=7, seq=1, send_time_ns=123, position=(0.5, 0.25),
                     velocity=(0.0, -1.0), status=StateStatus.ESTOPPED, last_cmd_seq=4)
    assert encode(state) == bytes.fromhex(
        "4653" "02" "01" "0100" "0100" "07000000" "01000000" "7b00000000000000"
        "000000000000e03f" "000000000000d03f" "0000000000000000" "000000000000f0bf"
        "04000000" "00000000")
    estop = EstopMsg(epoch=9, seq=2, send_time_ns=5, engaged=True, reason_code=42)
    assert encode(estop) == bytes.fromhex(
        "4653" "02" "03" "ffff" "0100" "09000000" "02000000" "0500000000000000"
        "2a000000" "00000000")
    assert [MESSAGE_SIZE[t] for t in MsgType] == [64, 48, 32, 60]


@settings(max_examples=300, deadline=None)
@given(messages)
def test_round_trip_is_identity(msg):
    data = encode(msg)
    assert len(data) == MESSAGE_SIZE[msg.TYPE]
    assert decode(data) == msg
    assert decode(data, expect=msg.TYPE) == msg


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=96))
def test_random_bytes_never_raise(data):
    result = decode(data)
    assert isinstance(result, Rejection | StateMsg | CmdMsg | EstopMsg | SightingMsg)
    decoder = WireDecoder(RobotRegistry(["r0", "r1"]), clock_ns=lambda: 10**12)
    decoder.decode(data, MsgType.CMD, robot_id=1)


@settings(max_examples=500, deadline=None)
@given(st.sampled_from(list(MsgType)), st.data())
def test_random_bodies_behind_a_valid_prefix_never_raise_and_accepted_ones_are_canonical(t, data):
    """Valid magic/version/type and the right size, random rest: reaches every field check."""
    body = data.draw(st.binary(min_size=MESSAGE_SIZE[t] - 4, max_size=MESSAGE_SIZE[t] - 4))
    raw = b"FS" + bytes([1, int(t)]) + body
    result = decode(raw)
    if not isinstance(result, Rejection):
        assert encode(result) == raw  # an accepted message has exactly one encoding
        assert all(math.isfinite(v) for pair in _float_pairs(result) for v in pair)


def _float_pairs(msg):
    if isinstance(msg, StateMsg):
        return [msg.position, msg.velocity]
    if isinstance(msg, SightingMsg):
        return [msg.position, (msg.radius, msg.max_speed)]
    return [msg.acceleration] if isinstance(msg, CmdMsg) else []


@settings(max_examples=200, deadline=None)
@given(messages, st.data())
def test_every_header_corruption_is_rejected_for_its_reason(msg, data):
    good = encode(msg)
    t = msg.TYPE
    bad_magic = data.draw(st.binary(min_size=2, max_size=2).filter(lambda m: m != b"FS"))
    assert reason_of(decode(patch(good, 0, "2s", bad_magic))) is Reason.BAD_MAGIC
    version = data.draw(st.integers(0, 255).filter(lambda v: v not in ACCEPTED_VERSIONS))
    assert reason_of(decode(patch(good, 2, "B", version))) is Reason.BAD_VERSION
    unknown = data.draw(st.integers(0, 255).filter(lambda v: v not in (1, 2, 3, 4)))
    assert reason_of(decode(patch(good, 3, "B", unknown))) is Reason.UNKNOWN_TYPE
    other = data.draw(st.sampled_from([m for m in MsgType if m is not t]))
    assert reason_of(decode(patch(good, 3, "B", int(other)), expect=t)) is Reason.UNEXPECTED_TYPE
    assert reason_of(decode(patch(good, 3, "B", int(other)))) is Reason.BAD_SIZE
    cut = data.draw(st.integers(0, len(good) - 1))
    assert reason_of(decode(good[:cut])) is Reason.BAD_SIZE
    extra = data.draw(st.binary(min_size=1, max_size=16))
    assert reason_of(decode(good + extra)) is Reason.BAD_SIZE
    allowed = {MsgType.STATE: 0x1F, MsgType.CMD: 0x3, MsgType.ESTOP: 0x1, MsgType.SIGHTING: 0x3}[t]  # 0x10: LOCKSTEP, v2
    flags = data.draw(st.integers(0, 0xFFFF).filter(lambda f: f & ~allowed))
    assert reason_of(decode(patch(good, 6, "<H", flags))) is Reason.BAD_FLAGS
    assert reason_of(decode(patch(good, 8, "<I", 0))) is Reason.BAD_SEQUENCE  # epoch
    assert reason_of(decode(patch(good, 12, "<I", 0))) is Reason.BAD_SEQUENCE  # seq
    wrong_id = (data.draw(robot_ids) if t is MsgType.ESTOP else ROBOT_ALL)
    assert reason_of(decode(patch(good, 4, "<H", wrong_id))) is Reason.BAD_ROBOT_ID


non_finite_bits = st.one_of(
    st.sampled_from([0x7FF0_0000_0000_0000, 0xFFF0_0000_0000_0000]),  # +inf, -inf
    st.integers(1, 2**52 - 1).flatmap(  # NaNs: exponent all ones, any non-zero mantissa, any sign
        lambda m: st.sampled_from([0x7FF0_0000_0000_0000 | m, 0xFFF0_0000_0000_0000 | m])))


@settings(max_examples=200, deadline=None)
@given(messages, st.data())
def test_every_body_corruption_is_rejected_for_its_reason(msg, data):
    good = encode(msg)
    t = msg.TYPE
    for offset in FLOAT_OFFSETS[t]:
        bits = data.draw(non_finite_bits)
        assert reason_of(decode(patch(good, offset, "<Q", bits))) is Reason.NON_FINITE
    offset, fmt = RESERVED[t]
    junk = data.draw(st.integers(1, 0xFFFF))
    if getattr(msg, "robot", None) is None:
        assert reason_of(decode(patch(good, offset, fmt, junk))) is Reason.BAD_RESERVED
    else:               # flag ROBOT: the field names the robot, 0xFFFF none
        assert reason_of(decode(patch(good, offset, fmt, ROBOT_ALL))) is Reason.BAD_ROBOT_ID
    if t is MsgType.CMD:
        assert reason_of(decode(patch(good, 44, "<H", 0))) is Reason.BAD_TTL
    if t is MsgType.SIGHTING:
        radius = data.draw(st.floats(max_value=0.0, allow_nan=False, allow_infinity=False))
        assert reason_of(decode(patch(good, 40, "<d", radius))) is Reason.BAD_VALUE
        speed = data.draw(st.floats(max_value=-1e-300, allow_nan=False, allow_infinity=False))
        assert reason_of(decode(patch(good, 48, "<d", speed))) is Reason.BAD_VALUE


def test_sighting_bytes_match_the_documented_layout_and_name_an_obstacle_not_a_robot():
    """docs/wire-format.md's SIGHTING example: obstacle 3 at (0.5, 0.25), radius 0.0625 m, at
    most 0.5 m/s, seen 12 ms before sending. The decoder takes it whatever the robot registry
    (its id names an obstacle), and still checks its stream."""
    msg = SightingMsg(robot_id=3, epoch=7, seq=1, send_time_ns=123, position=(0.5, 0.25), radius=0.0625,
                      max_speed=0.5, capture_age_ms=12)
    expected = bytes.fromhex(
        "4653" "02" "04" "0300" "0000" "07000000" "01000000" "7b00000000000000"
        "000000000000e03f" "000000000000d03f" "000000000000b03f" "000000000000e03f" "0c00" "0000")
    assert encode(msg) == expected
    assert encode(dataclasses.replace(msg, gone=True))[6:8] == b"\x01\x00"
    decoder = WireDecoder(RobotRegistry(["r0"]))
    assert decoder.decode(expected, MsgType.SIGHTING) == msg
    assert reason_of(decoder.decode(expected, MsgType.SIGHTING)) is Reason.STALE
    state = encode(StateMsg(3, 7, 1, 123, (0.0, 0.0), (0.0, 0.0)))
    assert reason_of(decoder.decode(state, MsgType.STATE)) is Reason.UNKNOWN_ROBOT


def test_a_sighting_of_a_robot_carries_its_registry_id_under_flag_robot():
    """docs/wire-format.md: the same sighting as the example, of robot id 2 (r2): flag ROBOT
    (0x0002) and the body's last field 2. The decoder checks that robot against the registry."""
    msg = SightingMsg(robot_id=3, epoch=7, seq=1, send_time_ns=123, position=(0.5, 0.25), radius=0.0625,
                      max_speed=0.5, capture_age_ms=12, robot=2)
    raw = encode(msg)
    assert raw[6:8] == b"\x02\x00" and raw[58:60] == b"\x02\x00"
    assert encode(dataclasses.replace(msg, gone=True))[6:8] == b"\x03\x00"
    assert decode(raw) == msg
    assert WireDecoder(RobotRegistry({"r0": 0, "r1": 1, "r2": 2})).decode(raw, MsgType.SIGHTING) == msg
    assert reason_of(WireDecoder(RobotRegistry(["r0"])).decode(raw, MsgType.SIGHTING)) is Reason.UNKNOWN_ROBOT
    with pytest.raises(ValueError, match="robot=0xFFFF"):
        encode(dataclasses.replace(msg, robot=ROBOT_ALL))
    with pytest.raises(ValueError, match="radius=0.0 must be > 0"):
        encode(dataclasses.replace(msg, radius=0.0))


def test_decoder_context_checks_and_counts():
    registry = RobotRegistry({"r0": 0, "r7": 7})
    now = 50_000_000_000
    decoder = WireDecoder(registry, clock_ns=lambda: now, max_future_ms=100)

    def cmd(robot_id=7, epoch=11, seq=1, sent=now, ttl_ms=100):
        return encode(CmdMsg(robot_id, epoch, seq, sent, (0.0, 0.0), ttl_ms))

    assert isinstance(decoder.decode(cmd(seq=1), MsgType.CMD, 7), CmdMsg)
    assert reason_of(decoder.decode(cmd(robot_id=3), MsgType.CMD)) is Reason.UNKNOWN_ROBOT
    assert reason_of(decoder.decode(cmd(seq=2), MsgType.CMD, robot_id=0)) is Reason.ROBOT_MISMATCH
    assert reason_of(decoder.decode(cmd(seq=1), MsgType.CMD, 7)) is Reason.STALE  # repeat
    # 100 ms ttl: sent 100.001 ms ago is expired, sent exactly 100 ms ago is not
    old = cmd(seq=3, sent=now - 100_001_000)
    assert reason_of(decoder.decode(old, MsgType.CMD, 7)) is Reason.EXPIRED
    assert isinstance(decoder.decode(cmd(seq=4, sent=now - 100_000_000), MsgType.CMD, 7), CmdMsg)
    ahead = cmd(seq=5, sent=now + 100_000_001)
    assert reason_of(decoder.decode(ahead, MsgType.CMD, 7)) is Reason.FROM_FUTURE
    # rejected messages did not move the stream: seq 5 is still fresh
    assert isinstance(decoder.decode(cmd(seq=5), MsgType.CMD, 7), CmdMsg)
    assert reason_of(decoder.decode(cmd(seq=3), MsgType.CMD, 7)) is Reason.STALE
    assert decoder.rejects.snapshot() == {"UNKNOWN_ROBOT": 1, "ROBOT_MISMATCH": 1, "STALE": 2,
                                          "EXPIRED": 1, "FROM_FUTURE": 1}
    assert decoder.rejects.total == 6


def test_sender_restart_is_accepted_and_a_retired_epoch_is_stale():
    decoder = WireDecoder()

    def state(epoch, seq):
        return encode(StateMsg(0, epoch, seq, 0, (0.0, 0.0), (0.0, 0.0)))

    assert isinstance(decoder.decode(state(epoch=10, seq=500)), StateMsg)
    assert isinstance(decoder.decode(state(epoch=20, seq=1)), StateMsg)  # restarted sender
    assert reason_of(decoder.decode(state(epoch=10, seq=501))) is Reason.STALE  # late packet
    assert isinstance(decoder.decode(state(epoch=20, seq=2)), StateMsg)
    # streams are per (type, robot id): robot 1 starts fresh
    other = encode(StateMsg(1, 10, 1, 0, (0.0, 0.0), (0.0, 0.0)))
    assert isinstance(decoder.decode(other), StateMsg)


def test_stamper_wraps_to_a_new_epoch_that_receivers_accept():
    stamper = Stamper(clock_ns=lambda: 1, epoch=5)
    stamper.seq = U32_MAX - 1
    decoder = WireDecoder()
    seen = []
    for _ in range(3):
        epoch, seq, sent = stamper.next()
        seen.append((epoch, seq))
        msg = decoder.decode(encode(EstopMsg(epoch, seq, sent, False)))
        assert isinstance(msg, EstopMsg)
    assert seen[0] == (5, U32_MAX)
    assert seen[1][0] != 5 and seen[1][1] == 1 and seen[2] == (seen[1][0], 2)


def test_encode_refuses_invalid_fields_naming_them():
    with pytest.raises(ValueError, match="acceleration.*NaN"):
        encode(CmdMsg(1, 1, 1, 0, (math.nan, 0.0), 100))
    with pytest.raises(ValueError, match="position.*NaN or inf"):
        encode(StateMsg(1, 1, 1, 0, (math.inf, 0.0), (0.0, 0.0)))
    with pytest.raises(ValueError, match="ttl_ms=0"):
        encode(CmdMsg(1, 1, 1, 0, (0.0, 0.0), 0))
    with pytest.raises(ValueError, match="ttl_ms=70000"):
        encode(CmdMsg(1, 1, 1, 0, (0.0, 0.0), 70000))
    with pytest.raises(ValueError, match="seq=0"):
        encode(StateMsg(1, 1, 0, 0, (0.0, 0.0), (0.0, 0.0)))
    with pytest.raises(ValueError, match="reserved for fleet-wide"):
        encode(StateMsg(ROBOT_ALL, 1, 1, 0, (0.0, 0.0), (0.0, 0.0)))
    with pytest.raises(ValueError, match="undefined bits"):
        encode(CmdMsg(1, 1, 1, 0, (0.0, 0.0), 10, flags=8))
    with pytest.raises(ValueError, match="wrong types"):
        encode(CmdMsg(1, 1, 1, 0, ("fast", 0.0), 10))
    with pytest.raises(TypeError):
        decode("FS not bytes")  # a programming error, not wire input


def test_names_and_registry():
    registry = RobotRegistry(["r0", "r1", "arm_2"])
    assert [registry.id_of(n) for n in registry.names] == [0, 1, 2]
    assert registry.name_of(2) == "arm_2" and registry.id_of("zz") is None
    for bad in ["@r0", "", "a/b", "r*", "r 1", "$x", "-r", "x" * 65]:
        with pytest.raises(ValueError, match="not allowed"):
            check_name(bad)
    with pytest.raises(ValueError, match="unique"):
        RobotRegistry({"a": 1, "b": 1})
    with pytest.raises(ValueError, match="reserved"):
        RobotRegistry({"a": ROBOT_ALL})


def test_reject_counter():
    counter = RejectCounter()
    for reason in [Reason.STALE, Reason.BAD_MAGIC, Reason.STALE]:
        counter.add(reason)
    assert counter[Reason.STALE] == 2 and counter[Reason.NON_FINITE] == 0
    assert counter.total == 3
    assert counter.snapshot() == {"BAD_MAGIC": 1, "STALE": 2}
    assert HEADER_SIZE == 24


def test_version_1_is_still_decoded_without_the_lockstep_flag_and_others_are_refused():
    """Version 2 adds the STATE flag LOCKSTEP (0x10) to the same layout: a version-1 message
    decodes as before, a version-1 STATE may not set LOCKSTEP, and version 3 is refused."""
    state = StateMsg(robot_id=1, epoch=7, seq=1, send_time_ns=123, position=(0.5, 0.25),
                     velocity=(0.0, -1.0), status=StateStatus.ESTOPPED, last_cmd_seq=4)
    v2 = encode(state)
    v1 = v2[:2] + b"\x01" + v2[3:]
    assert decode(v1) == state
    lockstep = encode(dataclasses.replace(state, status=StateStatus.LOCKSTEP))
    assert decode(lockstep).status == StateStatus.LOCKSTEP
    assert reason_of(decode(lockstep[:2] + b"\x01" + lockstep[3:])) is Reason.BAD_FLAGS
    assert reason_of(decode(v2[:2] + b"\x03" + v2[3:])) is Reason.BAD_VERSION
