"""SCIP 2.0 codec: known answers from the specification and real captures, every status path."""

from __future__ import annotations

import numpy as np
import pytest

from sensor_agent.scip import (
    ChecksumError,
    CommandError,
    CommandOk,
    CommandRejectedError,
    DeviceStateError,
    Discarded,
    HardwareError,
    LaserOffError,
    MalformedReplyError,
    ParameterError,
    ReplyError,
    ScanData,
    ScanStarted,
    ScipCodec,
    ScipError,
    SensorParameters,
    SensorState,
    StatusError,
    TimeReply,
    TimestampUnwrapper,
    UndefinedCommandError,
    VersionInfo,
    checksum,
    decode_value,
    encode_value,
    status_error,
)
from sensor_agent.scip import commands as c
from sensor_agent.scip.encoding import decode_values, encode_values

# -- independent reference (PROTOCOLS.md A.2), deliberately not the code under test ----------


def ref_checksum(data: bytes) -> bytes:
    return bytes([(sum(data) & 0x3F) + 0x30])


def ref_encode(value: int, n: int) -> bytes:
    return bytes(((value >> (6 * (n - 1 - i))) & 0x3F) + 0x30 for i in range(n))


def ref_scan_reply(echo: bytes, status: bytes, ts_ms: int, values: list[int]) -> bytes:
    ts = ref_encode(ts_ms, 4)
    payload = b"".join(ref_encode(v, 3) for v in values)
    lines = [echo, status + ref_checksum(status), ts + ref_checksum(ts)]
    for i in range(0, len(payload), 64):
        chunk = payload[i : i + 64]
        lines.append(chunk + ref_checksum(chunk))
    return b"\n".join(lines) + b"\n\n"


def ok(echo: bytes) -> bytes:
    return echo + b"\n00P\n\n"


def status_reply(echo: bytes, status: bytes) -> bytes:
    return echo + b"\n" + status + ref_checksum(status) + b"\n\n"


# -- encodings ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "n", "chars"),
    [
        (1234, 2, b"CB"),  # spec worked example, 2-character encoding
        (5432, 3, b"1Dh"),  # spec worked example, 3-character encoding
        (16_000_000, 4, b"m2@0"),  # spec worked example, 4-character encoding
        (0, 3, b"000"),
        (1, 3, b"001"),
        (60_000, 3, b">YP"),
        (0x123456, 4, b"4SAF"),
    ],
)
def test_worked_examples(value: int, n: int, chars: bytes) -> None:
    assert encode_value(value, n) == chars
    assert decode_value(chars) == value
    assert decode_values(chars, n).tolist() == [value]
    assert encode_values([value], n) == chars


def test_checksums_of_status_lines() -> None:
    expected = [
        "00P",
        "01Q",
        "02R",
        "03S",
        "04T",
        "05U",
        "06V",
        "07W",
        "0Cc",
        "0Dd",
        "0Ee",
        "0Ff",
        "0Ll",
        "0Mm",
        "10Q",
        "99b",
    ]
    for line in expected:
        assert bytes([checksum(line[:2].encode())]) == line[2:].encode()
    assert checksum(b"4SAF") == ord(">")


def test_encode_rejects_out_of_range() -> None:
    with pytest.raises(ValueError, match="does not fit"):
        encode_value(4096, 2)
    with pytest.raises(ValueError, match="out of range"):
        encode_values([262_144], 3)


def test_decode_rejects_non_scip_characters() -> None:
    with pytest.raises(MalformedReplyError):
        decode_value(b"0p")
    with pytest.raises(MalformedReplyError):
        decode_values(b"00/", 3)
    with pytest.raises(MalformedReplyError):
        decode_values(b"0000", 3)


# -- commands -------------------------------------------------------------------------------------


def test_command_lines() -> None:
    assert c.md(0, 1080).line == b"MD0000108001000"
    assert c.me(540, 541, 1, nscans=1).line == b"ME0540054101001"
    assert c.md(44, 725, 2, interval=1, nscans=99, tag="abc").line == b"MD0044072502199;abc"
    assert c.gd(540, 542).line == b"GD0540054201"
    assert c.tm(1).line == b"TM1"
    assert c.qt().encode() == b"QT\n"  # LF only, like every peer driver
    assert c.md(0, 1080, 3).scan is not None
    assert c.md(0, 1080, 3).scan.value_count == 361
    assert c.md(0, 1080, 0).scan.value_count == 1081  # cluster 0 means 1


@pytest.mark.parametrize(
    "build",
    [
        lambda: c.md(10, 5),
        lambda: c.md(0, 10_000),
        lambda: c.md(0, 10, 100),
        lambda: c.md(0, 10, interval=10),
        lambda: c.md(0, 10, nscans=100),
        lambda: c.tm(3),
        lambda: c.qt("x" * 17),
        lambda: c.vv("no;semicolon"),
    ],
)
def test_bad_commands_raise_command_error(build: object) -> None:
    with pytest.raises(CommandError):
        build()  # type: ignore[operator]


# -- information replies --------------------------------------------------------------------------

# A real UTM-30LX-EW PP reply (PROTOCOLS.md A.5); its sums exclude the ';'.
REAL_PP = (
    b"PP\n00P\nMODL:UTM-30LX-EW;I\nDMIN:23;7\nDMAX:60000;J\nARES:1440;^\n"
    b"AMIN:0;?\nAMAX:1080;Z\nAFRT:540;0\nSCAN:2400;U\n\n"
)


def test_pp_from_a_real_utm30lx_ew() -> None:
    codec = ScipCodec()
    cmd = c.pp()
    codec.send(cmd)
    [ev] = codec.receive(REAL_PP)
    assert isinstance(ev, SensorParameters)
    assert ev.command is cmd
    assert (ev.model, ev.dmin_mm, ev.dmax_mm, ev.ares) == ("UTM-30LX-EW", 23, 60000, 1440)
    assert (ev.amin, ev.amax, ev.afrt, ev.scan_rpm) == (0, 1080, 540, 2400)
    assert codec.pending == ()


def kv(key: str, value: str, include_semicolon: bool = False) -> bytes:
    body = f"{key}:{value}".encode()
    covered = body + b";" if include_semicolon else body
    return body + b";" + ref_checksum(covered)


def test_vv_and_ii_and_the_lenient_semicolon_rule() -> None:
    codec = ScipCodec()
    vv, ii = c.vv(), c.ii()
    codec.send(vv)
    codec.send(ii)
    vv_reply = b"\n".join(
        [
            b"VV",
            b"00P",
            kv("VEND", "Hokuyo Automatic Co.,Ltd."),
            kv("PROD", "SOKUIKI Sensor TOP-URG UTM-30LX"),
            kv("FIRM", "1.16.01(16/Nov./2009)"),
            kv("PROT", "SCIP 2.0"),
            kv("SERI", "H0900000", include_semicolon=True),  # older documents' form
        ]
    )
    ii_reply = b"\n".join(
        [b"II", b"00P", kv("LASR", "ON"), kv("STAT", "Stable 000 no error."), kv("TIME", "0N9")]
    )
    events = codec.receive(vv_reply + b"\n\n" + ii_reply + b"\n\n")
    assert len(events) == 2
    v, s = events
    assert isinstance(v, VersionInfo)
    assert (v.product, v.firmware, v.serial) == (
        "SOKUIKI Sensor TOP-URG UTM-30LX",
        "1.16.01(16/Nov./2009)",
        "H0900000",
    )
    assert isinstance(s, SensorState)
    assert s.laser_on is True
    assert s.status_text == "Stable 000 no error."


def test_info_line_with_bad_checksum_is_a_checksum_error() -> None:
    codec = ScipCodec()
    codec.send(c.pp())
    [ev] = codec.receive(REAL_PP.replace(b"DMIN:23;7", b"DMIN:23;8"))
    assert isinstance(ev, ReplyError)
    assert isinstance(ev.error, ChecksumError)


def test_pp_missing_a_key_is_malformed() -> None:
    codec = ScipCodec()
    codec.send(c.pp())
    [ev] = codec.receive(REAL_PP.replace(b"ARES:1440;^\n", b""))
    assert isinstance(ev, ReplyError)
    assert isinstance(ev.error, MalformedReplyError)


def test_tm1_timestamp() -> None:
    codec = ScipCodec()
    codec.send(c.tm(0))
    codec.send(c.tm(1))
    codec.send(c.tm(2))
    events = codec.receive(b"TM0\n00P\n\nTM1\n00P\n0N90W\n\nTM2\n00P\n\n")
    assert isinstance(events[0], CommandOk)
    assert isinstance(events[1], TimeReply)
    assert events[1].timestamp_ms == 123456
    assert isinstance(events[2], CommandOk)


# -- scans ----------------------------------------------------------------------------------------


def test_md_example_from_the_spec() -> None:
    codec = ScipCodec()
    cmd = c.md(540, 542, nscans=1)
    assert codec.send(cmd) == b"MD0540054201001\n"
    events = codec.receive(b"MD0540054201001\n00P\n\nMD0540054201000\n99b\n00?Xg\n0CB1Dh7D`]\n\n")
    assert isinstance(events[0], ScanStarted)
    scan = events[1]
    assert isinstance(scan, ScanData)
    assert scan.remaining == 0
    assert scan.timestamp_raw_ms == 1000
    assert scan.ranges_mm.tolist() == [1234, 5432, 30000]
    assert scan.intensities is None
    assert codec.stream is None  # the finite stream is over


def test_me_example_from_the_spec() -> None:
    codec = ScipCodec()
    codec.send(c.me(540, 541, nscans=1))
    events = codec.receive(
        b"ME0540054101001\n00P\n\nME0540054101000\n99b\n00?Xg\n0CB01T1Dh0O@6\n\n"
    )
    scan = events[1]
    assert isinstance(scan, ScanData)
    assert scan.ranges_mm.tolist() == [1234, 5432]
    assert scan.intensities is not None
    assert scan.intensities.tolist() == [100, 2000]


def test_gd_example_from_the_spec() -> None:
    codec = ScipCodec()
    codec.send(c.gd(540, 542))
    [scan] = codec.receive(b"GD0540054201\n00P\n4SAF>\n0CB1Dh7D`]\n\n")
    assert isinstance(scan, ScanData)
    assert scan.timestamp_raw_ms == 0x123456
    assert scan.ranges_mm.tolist() == [1234, 5432, 30000]


def full_scan_values(seed: int) -> list[int]:
    rng = np.random.default_rng(seed)
    values = rng.integers(23, 60_001, 1081)
    values[::97] = 1  # UTM-30LX error code "no object in range"
    return [int(v) for v in values]


def test_full_md_block_of_a_utm30lx() -> None:
    values = full_scan_values(1)
    reply = ref_scan_reply(b"MD0000108001000", b"99", 123_456, values)
    assert len(reply) == 3372  # PROTOCOLS.md A.2: 51 data lines, 3372 bytes
    data_lines = reply.split(b"\n")[3:-2]
    assert len(data_lines) == 51
    assert len(data_lines[0]) == 65  # a 3-character value straddles this line's end (64 % 3)
    codec = ScipCodec()
    codec.send(c.md(0, 1080))
    # Delivered in awkward pieces, as a serial port would.
    events = []
    for i in range(0, len(reply), 7):
        events += codec.receive(reply[i : i + 7])
    [scan] = events
    assert isinstance(scan, ScanData)
    assert scan.ranges_mm.dtype == np.uint32
    assert scan.ranges_mm.tolist() == values
    assert scan.timestamp_raw_ms == 123_456


def test_full_me_block_of_a_utm30lx() -> None:
    dist = full_scan_values(2)
    inten = full_scan_values(3)
    inter = [v for pair in zip(dist, inten, strict=True) for v in pair]
    reply = ref_scan_reply(b"ME0000108001000", b"99", 7, inter)
    assert len(reply) == 6717  # PROTOCOLS.md A.2: 102 data lines
    codec = ScipCodec()
    codec.send(c.me(0, 1080))
    [scan] = codec.receive(reply)
    assert isinstance(scan, ScanData)
    assert scan.ranges_mm.tolist() == dist
    assert scan.intensities is not None
    assert scan.intensities.tolist() == inten


def test_finite_stream_counts_down_and_ends() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 542, nscans=3))
    stream = ok(b"MD0540054201003")
    for left in (2, 1, 0):
        stream += ref_scan_reply(f"MD05400542010{left:02d}".encode(), b"99", 25 * left, [1, 2, 3])
    stream += ref_scan_reply(b"MD0540054201000", b"99", 99, [1, 2, 3])  # after the end: stray
    events = codec.receive(stream)
    scans = [e for e in events if isinstance(e, ScanData)]
    assert [s.remaining for s in scans] == [2, 1, 0]
    assert isinstance(events[-1], Discarded)


def test_scan_with_bad_data_checksum_is_an_error_not_a_scan() -> None:
    codec = ScipCodec()
    codec.send(c.md(0, 1080))
    reply = bytearray(ref_scan_reply(b"MD0000108001000", b"99", 5, full_scan_values(4)))
    reply[100] = reply[100] + 1 if reply[100] < 0x6F else reply[100] - 1
    [ev] = codec.receive(bytes(reply))
    assert isinstance(ev, ReplyError)
    assert isinstance(ev.error, ChecksumError)
    # The stream goes on: the next scan decodes.
    [ok_scan] = codec.receive(ref_scan_reply(b"MD0000108001000", b"99", 30, full_scan_values(5)))
    assert isinstance(ok_scan, ScanData)


def with_sum(content: bytes) -> bytes:
    return content + ref_checksum(content)


GOOD_MD = b"MD0540054201000\n99b\n00?Xg\n0CB1Dh7D`]\n\n"


@pytest.mark.parametrize(
    ("old", "new", "error"),
    [
        (b"\n00?Xg\n", b"\n00?Xh\n", ChecksumError),  # timestamp checksum
        (b"\n99b\n", b"\n99c\n", ChecksumError),  # status checksum
        (b"\n99b\n", b"\n99bb\n", MalformedReplyError),  # status line length
        (b"\n00?Xg\n", b"\n" + with_sum(b"00?") + b"\n", MalformedReplyError),  # 3-char stamp
        (b"0CB1Dh7D`]", with_sum(b"0CB1Dh7Dp"), MalformedReplyError),  # 'p' is not SCIP data
        (b"\n0CB1Dh7D`]", b"", MalformedReplyError),  # no data lines
        (b"\n00?Xg\n0CB1Dh7D`]", b"", MalformedReplyError),  # no timestamp either
        (b"\n0CB1Dh7D`]", b"\n]", MalformedReplyError),  # a data line of just a sum
    ],
)
def test_broken_scan_replies(old: bytes, new: bytes, error: type[ScipError]) -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 542))
    assert old in GOOD_MD
    events = codec.receive(GOOD_MD.replace(old, new))
    assert len(events) == 1
    assert isinstance(events[0], ReplyError)
    assert isinstance(events[0].error, error)


def test_wrong_value_count_is_malformed() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 543))  # 4 values asked, 3 sent
    [ev] = codec.receive(b"MD0540054301000\n99b\n00?Xg\n0CB1Dh7D`]\n\n")
    assert isinstance(ev, ReplyError)
    assert isinstance(ev.error, MalformedReplyError)


# -- timestamps -----------------------------------------------------------------------------------


def test_timestamp_unwrapping_across_the_24_bit_wrap() -> None:
    u = TimestampUnwrapper()
    top = (1 << 24) - 30
    raw = [top, top + 25, (top + 50) % (1 << 24), (top + 75) % (1 << 24)]
    assert [u.unwrap(r) for r in raw] == [top, top + 25, top + 50, top + 75]
    u.reset()
    assert u.unwrap(7) == 7


def test_small_backwards_jump_stays_small() -> None:
    u = TimestampUnwrapper()
    assert u.unwrap(1000) == 1000
    assert u.unwrap(990) == 990  # not 990 + 2^24


def test_scan_timestamps_unwrap_and_rs_resets_the_counter() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 540))
    top = (1 << 24) - 10
    stamps = []
    for ts in (top, (top + 25) % (1 << 24)):
        [ev] = codec.receive(ref_scan_reply(b"MD0540054001000", b"99", ts, [100]))
        assert isinstance(ev, ScanData)
        stamps.append(ev.timestamp_ms)
    assert stamps == [top, top + 25]
    codec.send(c.rs())
    codec.receive(ok(b"RS"))
    codec.send(c.md(540, 540))
    [ev] = codec.receive(ref_scan_reply(b"MD0540054001000", b"99", 3, [100]))
    assert isinstance(ev, ScanData)
    assert ev.timestamp_ms == 3


# -- status codes ---------------------------------------------------------------------------------

STATUS_TABLE = [
    # (command builder, status, expected error class)
    *[(lambda: c.md(0, 10), s, ParameterError) for s in ("01", "02", "03", "04", "05", "06", "07")],
    *[(lambda: c.gd(0, 10), s, ParameterError) for s in ("01", "02", "03", "04", "05")],
    (lambda: c.gd(0, 10), "10", LaserOffError),
    (lambda: c.md(0, 10), "10", LaserOffError),
    (lambda: c.me(0, 10), "10", LaserOffError),
    (lambda: c.md(0, 10), "98", DeviceStateError),
    (lambda: c.md(0, 10), "21", HardwareError),
    (lambda: c.md(0, 10), "49", HardwareError),
    (lambda: c.md(0, 10), "50", HardwareError),
    (lambda: c.md(0, 10), "97", HardwareError),
    (c.bm, "01", HardwareError),
    (lambda: c.tm(0), "01", ParameterError),
    (lambda: c.tm(0), "02", DeviceStateError),
    (lambda: c.tm(2), "03", DeviceStateError),
    (lambda: c.tm(1), "04", DeviceStateError),
    *[(c.vv, s, CommandRejectedError) for s in ("0A", "0B", "0C", "0D", "0F", "0G", "0H")],
    (lambda: c.raw(b"SCIP2.0"), "0E", UndefinedCommandError),
    (c.pp, "0I", DeviceStateError),
    (c.qt, "0L", DeviceStateError),
    (c.ii, "0M", DeviceStateError),
    (c.rs, "10", DeviceStateError),
    (c.qt, "ZZ", StatusError),
    (c.qt, "99", StatusError),  # "scan data follows" on a reply without scans
]


def test_non_ascii_digit_status_is_an_unknown_status() -> None:
    """Garbage on the line: '¹' passes str.isdigit() but not int() (found by the fuzz test)."""
    cmd = c.qt()
    codec = ScipCodec()
    codec.send(cmd)
    [ev] = codec.receive(status_reply(cmd.line, "¹9".encode("latin-1")))
    assert isinstance(ev, ReplyError)
    assert type(ev.error) is StatusError
    assert ev.error.meaning == "unknown status"


@pytest.mark.parametrize(("build", "status", "cls"), STATUS_TABLE)
def test_every_status_path(build: object, status: str, cls: type[StatusError]) -> None:
    cmd = build()  # type: ignore[operator]
    codec = ScipCodec()
    codec.send(cmd)
    [ev] = codec.receive(status_reply(cmd.line, status.encode()))
    assert isinstance(ev, ReplyError)
    assert type(ev.error) is cls
    assert ev.error.status == status
    assert ev.error.command == cmd.name
    assert ev.command is cmd
    assert codec.pending == ()
    assert status_error(cmd.name, status).meaning in str(ev.error)


def test_bm_already_on_is_success() -> None:
    codec = ScipCodec()
    codec.send(c.bm())
    [ev] = codec.receive(status_reply(b"BM", b"02"))
    assert isinstance(ev, CommandOk)
    assert ev.status == "02"


def test_refused_md_ends_the_stream_expectation() -> None:
    codec = ScipCodec()
    codec.send(c.md(0, 10))
    [ev] = codec.receive(status_reply(b"MD0000001001000", b"10"))
    assert isinstance(ev, ReplyError)
    assert codec.stream is None
    [late] = codec.receive(ref_scan_reply(b"MD0000001001000", b"99", 1, [5] * 11))
    assert isinstance(late, Discarded)


# -- framing and resynchronisation ----------------------------------------------------------------


def test_urg_stamped_multiple_responses_vector() -> None:
    """urg_stamped's SCIP2.MultipleResponses: exactly two QT replies come out."""
    codec = ScipCodec()
    codec.send(c.qt())
    codec.send(c.qt())
    events = []
    for chunk in (b"QT\n00P\n\nF", b"OO\nBAR\nQT\n\n", b"QT\n\nQT\n", b"00P\n\n", b"\n\n"):
        events += codec.receive(chunk)
    assert [type(e) for e in events if not isinstance(e, Discarded)] == [CommandOk, CommandOk]
    assert codec.pending == ()


def test_only_what_was_asked_for_comes_out() -> None:
    codec = ScipCodec()
    codec.send(c.qt())
    events = codec.receive(b"QT\n00P\n\n" * 2 + b"VV\n00P\n\n")
    assert isinstance(events[0], CommandOk)
    assert all(isinstance(e, Discarded) for e in events[1:])


def test_garbage_ending_in_a_line_feed_does_not_cost_the_reply() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 542))
    events = codec.receive(b"\x00\xffjunk\n" + b"MD0540054201000\n99b\n00?Xg\n0CB1Dh7D`]\n\n")
    assert isinstance(events[0], Discarded)
    assert events[0].reason == "junk before echo"
    assert isinstance(events[1], ScanData)


def test_garbage_glued_to_the_echo_costs_only_that_reply() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 542))
    good = b"MD0540054201000\n99b\n00?Xg\n0CB1Dh7D`]\n\n"
    events = codec.receive(b"#!" + good + good)
    assert isinstance(events[0], Discarded)
    assert isinstance(events[1], ScanData)


def test_qt_stops_streams_sent_before_it_but_not_after() -> None:
    codec = ScipCodec()
    codec.send(c.md(540, 542))
    codec.send(c.qt())
    md2 = c.md(540, 542)
    codec.send(md2)  # pipelined: QT's reply arrives after the new MD was sent
    codec.receive(ok(b"QT"))
    assert codec.stream is md2


def test_a_frame_without_terminator_is_eventually_discarded() -> None:
    codec = ScipCodec(max_frame_bytes=1000)
    codec.send(c.qt())
    events = codec.receive(b"x" * 600 + b"\n" + b"y" * 600)
    assert any(isinstance(e, Discarded) and e.reason == "no reply terminator" for e in events)
    events = codec.receive(b"\n\nQT\n00P\n\n")
    assert isinstance(events[-1], CommandOk)


def test_clear_pending_makes_late_replies_unexpected() -> None:
    codec = ScipCodec()
    codec.send(c.pp())
    codec.clear_pending()
    [ev] = codec.receive(REAL_PP)
    assert isinstance(ev, Discarded)


def test_echo_with_tag_is_matched() -> None:
    codec = ScipCodec()
    cmd = c.md(540, 542, tag="s1")
    codec.send(cmd)
    events = codec.receive(
        b"MD0540054201000;s1\n00P\n\nMD0540054201000;s1\n99b\n00?Xg\n0CB1Dh7D`]\n\n"
        b"MD0540054201000;s2\n99b\n00?Xg\n0CB1Dh7D`]\n\n"
    )
    assert [type(e) for e in events] == [ScanStarted, ScanData, Discarded]
