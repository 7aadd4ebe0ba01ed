"""The native protocol (``imu_gateway.protocol.native``): frames, command table, framer.

Every example frame of the native document (``vectors.NATIVE_VECTORS``) must decode to
the values the document prints and re-encode byte for byte.  Decoded BCD values are
compared with ``==``: a BCD value is an exact count divided by a power of ten, which
Python rounds correctly, so it is the same float as the printed decimal literal.

The framer gets every vector whole, byte by byte, split at every position, behind
garbage, back to back and with a bad checksum; Hypothesis then feeds it arbitrary
streams in arbitrary chunkings.
"""

from __future__ import annotations

import contextlib
import itertools
import random
from collections.abc import Iterable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.vectors import ANSWER, NATIVE_VECTORS, REQUEST, Vector, ids

from imu_gateway.model import Series
from imu_gateway.protocol import bcd, native
from imu_gateway.protocol.errors import (
    BadBcd,
    BadChecksum,
    BadLength,
    FrameError,
    UnknownFrame,
    UsageError,
)
from imu_gateway.protocol.exchanges import NativeAdapter

VECTOR_IDS = ids(NATIVE_VECTORS)
REQUESTS = [v for v in NATIVE_VECTORS if v.direction == REQUEST]
ANSWERS = [v for v in NATIVE_VECTORS if v.direction == ANSWER]
RAWS = [v.raw for v in NATIVE_VECTORS]


def by_section(section: str, direction: str) -> Vector:
    return next(v for v in NATIVE_VECTORS if v.section == section and v.direction == direction)


def feed_all(framer: native.NativeFramer, chunks: Iterable[bytes]) -> list[native.NativeFrame]:
    out: list[native.NativeFrame] = []
    for chunk in chunks:
        out += framer.feed(chunk)
        assert framer.pending <= native.MAX_FRAME
    return out


def split(data: bytes, cuts: Iterable[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points)]


# --------------------------------------------------------------------------- vectors


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_vector_is_well_formed(v: Vector) -> None:
    raw = v.raw
    assert raw[0] == native.SYNC
    assert raw[1] + 1 == len(raw)
    assert native.checksum(raw[1:-1]) == raw[-1]


def direction_of(v: Vector) -> native.Direction:
    return native.Direction.REQUEST if v.direction == REQUEST else native.Direction.ANSWER


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_vector_decodes(v: Vector) -> None:
    for series in {v.series, None}:
        msg = native.decode(v.raw, series, direction_of(v))
        assert msg.name == v.name
        assert msg.address == v.address
        assert dict(msg.values) == v.values
        assert direction_of(v) in msg.shape.direction
        assert msg.shape.section.startswith(v.section.split(".")[0])
        if (v.raw[3], v.raw[1]) not in native.TWO_WAY:  # the same read without a direction
            assert native.decode(v.raw, series) == msg


@pytest.mark.parametrize("v", REQUESTS, ids=ids(tuple(REQUESTS)))
def test_request_reencodes(v: Vector) -> None:
    assert native.encode_request(v.name, v.address, **v.values) == v.raw


@pytest.mark.parametrize("v", ANSWERS, ids=ids(tuple(ANSWERS)))
def test_answer_reencodes(v: Vector) -> None:
    assert v.series is not None
    assert native.encode_answer(v.name, v.series, v.address, **v.values) == v.raw


def test_address_query_is_always_sent_to_zero() -> None:
    assert native.encode_request("read_address", 7) == bytes.fromhex("77 04 00 1F 23")


def test_read_address_answer_encodes() -> None:
    """2.6: the answer carries the current address in ADDR and in its data byte.

    Its one field is named ``address``, the same as encode()'s own address parameter
    (a TypeError until a79bc97 made that parameter positional-only).
    """
    expected = bytes.fromhex("77 05 05 1F 05 2E")
    assert native.decode(expected).values == {"address": 5}
    assert native.encode_answer("read_address", Series.VG, 5, address=5) == expected


def test_read_all_answer_depends_on_series() -> None:
    """2.13-2.15: one request, three answers (0x84/18 bytes, 0x59/43, 0x59/52)."""
    command = native.COMMANDS_BY_NAME["read_all"]
    assert command.answer_for(Series.IMU).key == (0x84, 0x16)  # type: ignore[union-attr]
    assert command.answer_for(Series.VG).key == (0x59, 0x2F)  # type: ignore[union-attr]
    assert command.answer_for(Series.MINS) is command.answer_for(Series.VG)
    assert command.answer_for(Series.AH).key == (0x59, 0x38)  # type: ignore[union-attr]


# ------------------------------------------------------------- (command, LEN) collisions


@pytest.mark.parametrize(
    ("section", "direction", "key", "name", "shape_direction"),
    [
        ("2.3", ANSWER, (0x84, 0x0D), "read_angles", native.Direction.ANSWER),
        ("2.13", ANSWER, (0x84, 0x16), "read_all", native.Direction.ANSWER),
        ("2.20", REQUEST, (0x84, 0x07), "set_relative_heading", native.Direction.ECHO),
        ("2.2", ANSWER, (0x82, 0x07), "read_roll", native.Direction.ANSWER),
        ("2.19", REQUEST, (0x82, 0x04), "clear_heading", native.Direction.ECHO),
    ],
    ids=["84@0D", "84@16", "84@07", "82@07", "82@04"],
)
def test_collision_resolves_by_length(
    section: str, direction: str, key: tuple[int, int], name: str,
    shape_direction: native.Direction,
) -> None:
    v = by_section(section, direction)
    assert (v.raw[3], v.raw[1]) == key
    assert native.SHAPES[key].name == name
    msg = native.decode(v.raw)
    assert msg.name == name
    assert msg.shape.direction == shape_direction
    assert dict(msg.values) == v.values


@pytest.mark.parametrize(
    ("section", "direction", "wrong", "right"),
    [
        ("2.15", ANSWER, Series.VG, Series.AH),
        ("2.15", ANSWER, Series.IMU, Series.AH),
        ("2.14", ANSWER, Series.AH, Series.MINS),
        ("2.13", ANSWER, Series.VG, Series.IMU),
        ("2.19", REQUEST, Series.VG, Series.MINS),
        ("2.20", REQUEST, Series.AH, Series.MINS),
        ("2.23", ANSWER, Series.VG, Series.AH),
        ("2.21", REQUEST, Series.MINS, Series.AH),
    ],
)
def test_interpret_refuses_shape_of_other_series(
    section: str, direction: str, wrong: Series, right: Series
) -> None:
    frame = native.parse_frame(by_section(section, direction).raw)
    with pytest.raises(UnknownFrame):
        native.interpret(frame, series=wrong)
    assert native.interpret(frame, series=right).name == by_section(section, direction).name


# --------------------------------------------------------------------------- bad frames


def _frame(body_hex: str) -> bytes:
    """77 + body + the right checksum."""
    body = bytes.fromhex(body_hex)
    return b"\x77" + body + bytes([native.checksum(body)])


@pytest.mark.parametrize(
    ("raw", "error"),
    [
        (bytes.fromhex("77 04 00 01"), BadLength),
        (bytes.fromhex("78 04 00 01 05"), FrameError),
        (bytes.fromhex("77 05 00 01 05"), BadLength),
        (bytes.fromhex("77 04 00 01 06"), BadChecksum),
        (_frame("04 00 33"), UnknownFrame),  # no command 0x33
        (_frame("05 00 01 00"), UnknownFrame),  # pitch request with a data byte
        (_frame("07 00 81 1A 34 63"), BadBcd),  # digit nibble A
        (_frame("07 00 81 20 34 63"), BadBcd),  # sign nibble 2
        (_frame("05 00 05 07"), FrameError),  # zero type 07 is no documented code
    ],
    ids=["short", "sync", "len", "sum", "unknown-cmd", "unknown-len", "digit", "sign", "choice"],
)
def test_bad_frame_raises_frame_error(raw: bytes, error: type[FrameError]) -> None:
    with pytest.raises(error):
        native.decode(raw)


def test_result_byte_other_than_documented_is_passed_on_as_its_number() -> None:
    """Only 00 (success) and FF (failure) are documented; 2.18 answers 01 for success,
    so an unnamed code is reported as it is rather than guessed to be a failure."""
    assert native.decode(_frame("05 00 8A 00")).values["result"] == "success"
    assert native.decode(_frame("05 00 8A FF")).values["result"] == "failure"
    assert native.decode(_frame("05 00 8A 01")).values["result"] == 1


def test_zero_type_query_reads_ff_and_01_as_relative() -> None:
    assert native.decode(_frame("05 00 8D 00")).values["zero_type"] == "absolute"
    assert native.decode(_frame("05 00 8D FF")).values["zero_type"] == "relative"
    assert native.decode(_frame("05 00 8D 01")).values["zero_type"] == "relative"


def test_output_type_answer_is_a_status_not_an_echo() -> None:
    """2.16 answers 77 05 .. 56 with one byte the document prints as 00 whatever type
    was asked (as 2.17 does): read as a status.  FF is a failure; any other byte (a
    sensor that echoes the type after all) is passed on as its number, not a failure."""
    answer = native.Direction.ANSWER
    assert {(0x56, 0x05)} == native.TWO_WAY
    assert native.decode(_frame("05 00 56 00"), direction=answer).values == {"result": "success"}
    assert native.decode(_frame("05 00 56 FF"), direction=answer).values == {"result": "failure"}
    assert native.decode(_frame("05 00 56 05"), direction=answer).values == {"result": 5}
    # the same bytes heard by a sensor are the request for that type
    asked = native.decode(_frame("05 00 56 05"), direction=native.Direction.REQUEST)
    assert (asked.name, dict(asked.values)) == ("set_output_type", {"output_type": 5})
    assert native.decode(_frame("05 00 56 05")) == asked  # no direction: the request
    for series in Series:
        shape = native.COMMANDS_BY_NAME["set_output_type"].answer_for(series)
        assert shape is not None and shape.direction is native.Direction.ANSWER
        assert native.encode(shape, 0, result="success") == _frame("05 00 56 00")


@pytest.mark.parametrize("series", list(Series), ids=lambda s: s.name)
def test_stream_set_up_takes_an_output_type_answer_of_ff_as_failure(series: Series) -> None:
    """The gateway's auto-output set-up (2.16 then 2.17): 00 goes on, FF is a refusal
    (the set-up is retried later), an echo of the type asked is no refusal."""
    set_type, set_rate = NativeAdapter().stream_start(series, 3, 10)
    assert set_type.label == "set_output_type" and set_rate.label == "set_output_rate"
    code = set_type.request[4]
    assert code == (2 if series is Series.IMU else 5)  # the combined frame (2.13-2.15)
    for byte, ok in ((0x00, True), (0xFF, False), (code, True)):
        frame = native.parse_frame(native.NativeFrame(3, 0x56, bytes([byte])).encode())
        answer = set_type.match(frame)
        assert answer is not None and answer.ok is ok, (byte, answer)
    assert set_type.match(native.parse_frame(native.NativeFrame(4, 0x56, b"\0").encode())) \
        is None  # another sensor's


def test_baud_code_the_table_lacks_is_read_as_its_number_but_never_sent() -> None:
    """2.4: a sensor must be able to hear a code it does not know, to answer it with FF;
    the gateway itself can only ask for a rate the table has."""
    message = native.decode(_frame("05 00 0B 09"))
    assert (message.name, dict(message.values)) == ("set_baudrate", {"baudrate": 9})
    assert native.decode(_frame("05 00 8B FF")).values == {"result": "failure"}
    for not_a_rate in (9, 5, 9601):  # neither a code nor a baud rate is sent as it is
        with pytest.raises(UsageError):
            native.encode_request("set_baudrate", baudrate=not_a_rate)


@pytest.mark.parametrize(("section", "name"), [
    ("2.1", "read_pitch"), ("2.2", "read_roll"), ("2.3", "read_angles"),
    ("2.12", "read_quaternion")])
def test_reads_that_name_no_series_are_any_series(section: str, name: str) -> None:
    """2.1-2.3 and 2.12 mark no series (2.13-2.15 and 2.19-2.26 do): an IMU may ask and
    answer them like any other series."""
    command = native.COMMANDS_BY_NAME[name]
    assert command.request.series == frozenset(Series)
    v = by_section(section, ANSWER)
    for series in Series:
        assert command.answer_for(series) is command.answer_for(Series.VG)
        assert dict(native.decode(v.raw, series).values) == v.values
        assert native.encode_answer(name, series, 0, **v.values) == v.raw


@pytest.mark.parametrize(("fmt", "value", "sent"), [
    (bcd.DECLINATION, 0.25, 0.3), (bcd.DECLINATION, -0.25, -0.3),
    (bcd.DECLINATION, 0.35, 0.4), (bcd.DECLINATION, 1.25, 1.3),
    (bcd.DECLINATION, -1.25, -1.3), (bcd.DECLINATION, 0.24, 0.2),
    (bcd.DECLINATION, 99.90000152587891, 99.9),  # the float32 of 99.9
    (bcd.ANGLE, 1.005, 1.01), (bcd.ANGLE, -1.005, -1.01), (bcd.ANGLE, 2.675, 2.68),
    (bcd.ANGLE, 0.125, 0.13), (bcd.ANGLE, -0.004, 0.0),
])
def test_bcd_rounds_half_away_from_zero(fmt: bcd.BcdFormat, value: float, sent: float) -> None:
    """0.25 at one decimal is sent as 0.3, as the sensor would show it, not 0.2 (round
    half to even); 1.005 (100.49999… once multiplied) as 1.01."""
    assert fmt.decode(fmt.encode(value)) == sent
    assert fmt.rounded(value) == sent


def test_truncated_frame_says_how_much_is_there() -> None:
    pitch = by_section("2.1", ANSWER).raw
    with pytest.raises(BadLength, match="truncated: 6 of 8 bytes"):
        native.parse_frame(pitch[:6])


# --------------------------------------------------------------------------- tables


@pytest.mark.parametrize("command", native.COMMANDS, ids=lambda c: c.name)
def test_command_row_is_complete(command: native.NativeCommand) -> None:
    assert native.REQUEST_SHAPES[command.request.key] == command.request
    assert native.SHAPES[command.request.key] == command.request
    assert native.Direction.REQUEST in command.request.direction
    echo = command.request.direction is native.Direction.ECHO
    for series in command.request.series:
        answer = command.answer_for(series)
        assert answer is not None, f"{command.name}: no answer for {series.name}"
        assert native.ANSWER_SHAPES[answer.key] == answer
        assert series in answer.series
        if echo:
            assert answer is command.request
        else:
            assert answer.direction is native.Direction.ANSWER
    assert set(command.answers) == set(command.request.series)


def test_commands_cover_every_section() -> None:
    sections = {s for c in native.COMMANDS for s in c.section.split("-")}
    assert sections >= {f"2.{n}" for n in range(1, 27)} - {"2.14"}
    assert {v.name for v in NATIVE_VECTORS} == set(native.COMMANDS_BY_NAME)


@pytest.mark.parametrize("series", list(Series), ids=lambda s: s.name)
def test_output_types_map_to_answers_of_that_series(series: Series) -> None:
    for code, name in native.OUTPUT_TYPES[series].items():
        answer = native.COMMANDS_BY_NAME[name].answer_for(series)
        assert answer is not None, f"{series.name} code {code}: {name} has no answer"


def test_output_types_follow_section_2_16() -> None:
    vg = {0: "read_angles", 1: "read_accel", 2: "read_gyro", 3: "read_angles",
          4: "read_quaternion", 5: "read_all"}
    assert dict(native.OUTPUT_TYPES[Series.VG]) == vg
    assert dict(native.OUTPUT_TYPES[Series.MINS]) == vg
    assert dict(native.OUTPUT_TYPES[Series.IMU]) == {0: "read_gyro", 1: "read_accel",
                                                     2: "read_all"}
    assert dict(native.OUTPUT_TYPES[Series.AH]) == vg | {3: "read_mag"}
    ih = native.COMMANDS_BY_NAME["read_all"].answer_for(Series.IMU)
    assert ih is not None and ih.key == (0x84, 0x16)  # IMU code 2 is the 2.13 frame


def test_max_frame_is_the_ah_answer() -> None:
    assert native.MAX_FRAME == len(by_section("2.15", ANSWER).raw) == 57


# --------------------------------------------------------------------------- framer


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_whole(v: Vector) -> None:
    framer = native.NativeFramer()
    assert framer.feed(v.raw) == [native.parse_frame(v.raw)]
    assert framer.pending == 0
    assert (framer.stats.frames, framer.stats.garbage_bytes) == (1, 0)


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_byte_by_byte(v: Vector) -> None:
    framer = native.NativeFramer()
    out = feed_all(framer, (v.raw[i : i + 1] for i in range(len(v.raw))))
    assert out == [native.parse_frame(v.raw)]
    assert framer.pending == 0


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_split_anywhere(v: Vector) -> None:
    for cut in range(len(v.raw) + 1):
        framer = native.NativeFramer()
        first = framer.feed(v.raw[:cut])
        assert first == ([native.parse_frame(v.raw)] if cut == len(v.raw) else [])
        assert first + framer.feed(v.raw[cut:]) == [native.parse_frame(v.raw)]
        assert framer.pending == 0


_RNG = random.Random(20261122)
RANDOM_GARBAGE = [bytes(_RNG.choice([b for b in range(256) if b != 0x77]) for _ in range(n))
                  for n in (1, 3, 17, 64, 200)]
# 0x77 followed by LEN bytes some frame has; each is refused by its (command, LEN) pair or
# its checksum before the real frame's bytes run out.
SYNC_GARBAGE = [
    b"\x77", b"\x77\x77", b"\x77\x77\x77", b"\x77\x0d", b"\x77\x38", b"\x77\x38\x00",
    b"\x77\x16\x01\xee", b"\x77\x0d\x00\x33", b"\x77\x04\x00\x01\x00", b"\x77\x05\x77\x05",
    b"\x12\x77\x04\x77\x2f\x77\x38\x00\x00\x42",
]


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_after_random_garbage(v: Vector) -> None:
    for garbage in RANDOM_GARBAGE:
        framer = native.NativeFramer()
        assert framer.feed(garbage + v.raw) == [native.parse_frame(v.raw)]
        assert framer.stats.garbage_bytes == len(garbage)
        assert framer.pending == 0


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_after_garbage_with_sync(v: Vector) -> None:
    for garbage in SYNC_GARBAGE:
        framer = native.NativeFramer()
        assert framer.feed(garbage + v.raw) == [native.parse_frame(v.raw)], garbage.hex(" ")
        assert framer.pending == 0
        # and the same again one byte at a time
        framer = native.NativeFramer()
        data = garbage + v.raw
        assert feed_all(framer, (data[i : i + 1] for i in range(len(data)))) == [
            native.parse_frame(v.raw)
        ], garbage.hex(" ")


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_back_to_back(v: Vector) -> None:
    following = RAWS[(RAWS.index(v.raw) + 1) % len(RAWS)]
    for second in (v.raw, following):
        framer = native.NativeFramer()
        expected = [native.parse_frame(v.raw), native.parse_frame(second)]
        assert framer.feed(v.raw + second) == expected
        assert framer.pending == 0


@pytest.mark.parametrize("v", NATIVE_VECTORS, ids=VECTOR_IDS)
def test_framer_bad_checksum(v: Vector) -> None:
    bad = v.raw[:-1] + bytes([(v.raw[-1] + 1) & 0xFF])
    framer = native.NativeFramer()
    assert framer.feed(bad) == []
    assert framer.stats.bad_checksums == 1
    assert framer.feed(v.raw) == [native.parse_frame(v.raw)]
    assert framer.stats.frames == 1
    # the same in one chunk
    framer = native.NativeFramer()
    assert framer.feed(bad + v.raw) == [native.parse_frame(v.raw)]
    assert framer.stats.bad_checksums == 1


def test_framer_expire_releases_frame_behind_stray_prefix() -> None:
    """A cut-off AH answer header (77 38 00 59) makes the framer wait for 57 bytes; the
    caller's expire() gives up on it and the frame behind comes out."""
    pitch = by_section("2.1", ANSWER).raw
    framer = native.NativeFramer()
    assert framer.feed(bytes.fromhex("77 38 00 59") + pitch) == []
    assert framer.pending == 4 + len(pitch)
    assert framer.expire() == [native.parse_frame(pitch)]
    assert framer.pending == 0
    assert framer.expire() == []


def test_framer_expire_on_empty_and_partial() -> None:
    framer = native.NativeFramer()
    assert framer.expire() == []
    assert framer.feed(b"\x77\x38") == []
    assert framer.pending == 2
    assert framer.expire() == []
    assert framer.pending == 0


@settings(max_examples=200)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 2000), max_size=20))
def test_framer_buffer_is_bounded(garbage: bytes, cuts: list[int]) -> None:
    framer = native.NativeFramer()
    feed_all(framer, split(garbage, cuts))
    assert framer.pending <= native.MAX_FRAME


def test_framer_buffer_bounded_on_sync_flood() -> None:
    framer = native.NativeFramer()
    for _ in range(100):
        framer.feed(bytes.fromhex("77 38 00 59") + b"\x77" * 40)
        assert framer.pending <= native.MAX_FRAME


# --------------------------------------------------------------------------- hypothesis


def _codec_values(codec: native.Codec) -> st.SearchStrategy[Any]:
    if isinstance(codec, native.Bcd):
        fmt = codec.fmt
        return st.integers(-fmt.max_counts, fmt.max_counts).map(lambda c: c / fmt.scale)
    if isinstance(codec, native.Choice):
        return st.sampled_from(list(codec.meanings.values()))
    return st.integers(0, 0xFF)


#: every frame shape of both directions (a TWO_WAY pair has one of each)
ALL_SHAPES = sorted({*native.REQUEST_SHAPES.values(), *native.ANSWER_SHAPES.values()},
                    key=lambda s: (s.command, s.length_byte, s.direction.value))


@st.composite
def messages(draw: st.DrawFn) -> tuple[native.Shape, int, dict[str, Any]]:
    shape = draw(st.sampled_from(ALL_SHAPES))
    values = {f.name: draw(_codec_values(f.codec)) for f in shape.fields}
    return shape, draw(st.integers(0, 0xFF)), values


def _raw_frame(message: tuple[native.Shape, int, dict[str, Any]]) -> bytes:
    # Built from the codecs, not native.encode(), so that the framer tests do not lean on
    # the encoder they would otherwise share a bug with.
    shape, address, values = message
    data = b"".join(f.codec.encode(values[f.name]) for f in shape.fields)
    return native.NativeFrame(address, shape.command, data).encode()


def frames() -> st.SearchStrategy[bytes]:
    return st.one_of(st.sampled_from(RAWS), messages().map(_raw_frame))


TRICKY = [b"\x77", b"\x77\x0d", b"\x77\x38\x00\x59", b"\x77\x04\x00", b"\x77\x16\x00\x84"]
streams = st.lists(
    st.one_of(st.binary(max_size=12), frames(), st.sampled_from(TRICKY)), max_size=12
).map(b"".join)


@settings(max_examples=300)
@given(messages())
def test_any_message_round_trips(message: tuple[native.Shape, int, dict[str, Any]]) -> None:
    shape, address, values = message
    raw = native.encode(shape, address, **values)
    direction = native.Direction.ANSWER if shape.direction is native.Direction.ANSWER \
        else native.Direction.REQUEST
    decoded = native.decode(raw, next(iter(shape.series)), direction)
    assert (decoded.shape, decoded.address, dict(decoded.values)) == (shape, address, values)


@settings(max_examples=300)
@given(streams, st.lists(st.integers(0, 1000), max_size=10))
def test_framer_yields_only_valid_slices(data: bytes, cuts: list[int]) -> None:
    framer = native.NativeFramer()
    position = 0
    for frame in feed_all(framer, split(data, cuts)):
        raw = frame.encode()
        position = data.index(raw, position) + len(raw)  # an in-order slice of the input
        assert native.parse_frame(raw) == frame  # sync, LEN and checksum are right
        for series in (None, *Series):
            with contextlib.suppress(FrameError):
                assert isinstance(native.interpret(frame, series), native.NativeMessage)


@settings(max_examples=300)
@given(
    st.lists(
        st.tuples(st.binary(max_size=20).map(lambda b: b.replace(b"\x77", b"")), frames()),
        min_size=1, max_size=8,
    ),
    st.binary(max_size=20).map(lambda b: b.replace(b"\x77", b"")),
    st.lists(st.integers(0, 1000), max_size=10),
)
def test_framer_recovers_frames_between_garbage(
    pairs: list[tuple[bytes, bytes]], tail: bytes, cuts: list[int]
) -> None:
    data = b"".join(g + f for g, f in pairs) + tail
    framer = native.NativeFramer()
    out = feed_all(framer, split(data, cuts))
    assert [f.encode() for f in out] == [f for _, f in pairs]
    assert framer.pending == 0
    assert framer.stats.bad_checksums == 0
