"""The `.mrec` recording format: round trips, torn tails, corruption."""

from __future__ import annotations

import logging
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from clients.recording import (
    MAGIC,
    MAX_RECORD_BYTES,
    RecordingError,
    RecordingReport,
    RecordingWriter,
    is_recording,
    iter_raw_records,
    read_messages,
    scan_file,
    valid_length,
)
from clients.wire import OdometryPose, Pose, PoseFlag, Scan, encode_pose, encode_scan

HEADER = struct.Struct("<II")


def make_scan(seq: int) -> Scan:
    ranges = np.linspace(0.5, 10.0, 181)
    return Scan(
        robot_id="amr-07",
        seq=seq,
        sensor_stamp_ns=seq * 25_000_000,
        host_stamp_ns=1_700_000_000_000_000_000 + seq * 25_000_000,
        angle_min_rad=-np.pi / 2,
        angle_increment_rad=np.pi / 180,
        range_min_m=0.1,
        range_max_m=30.0,
        ranges_m=np.round(ranges, 3),
        odom=OdometryPose(0.1 * seq, 0.0, 0.0, seq) if seq % 2 else None,
    )


def make_pose(seq: int) -> Pose:
    return Pose("s1", "amr-07", seq, seq * 1000, 0.5 * seq, -1.0, 0.25, 0.9, PoseFlag.AMBIGUOUS_X)


def messages(n: int = 6) -> list[Scan | Pose]:
    out: list[Scan | Pose] = []
    for i in range(n):
        out.append(make_scan(i) if i % 3 else make_pose(i))
    return out


def encode(message: Scan | Pose) -> bytes:
    return encode_scan(message) if isinstance(message, Scan) else encode_pose(message)


def write(path: Path, items: list[Scan | Pose]) -> list[int]:
    """Write a recording; return the byte offset of each record."""
    offsets = []
    with RecordingWriter(path) as writer:
        for m in items:
            offsets.append(path.stat().st_size)
            writer.append(encode(m))
        assert writer.records_written == len(items)
    return offsets


def set_length(path: Path, offset: int, length: int) -> bytes:
    """Overwrite the length field of the record at `offset`; return the file's new bytes."""
    data = bytearray(path.read_bytes())
    data[offset : offset + 4] = struct.pack("<I", length)
    path.write_bytes(bytes(data))
    return bytes(data)


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "run.mrec"
    items = messages()
    offsets = write(path, items)
    assert is_recording(path)
    assert list(read_messages(path)) == items
    raw = list(iter_raw_records(path))
    assert [r.offset for r in raw] == offsets
    assert [r.kind for r in raw] == ["pose" if isinstance(m, Pose) else "scan" for m in items]
    assert valid_length(path) == path.stat().st_size


def test_layout_is_as_documented(tmp_path: Path) -> None:
    path = tmp_path / "one.mrec"
    payload = encode_pose(make_pose(1))
    with RecordingWriter(path) as writer:
        writer.append(payload)
    data = path.read_bytes()
    assert data[:8] == MAGIC == b"MMREC01\n"
    assert HEADER.unpack(data[8:16]) == (len(payload), zlib.crc32(payload))
    assert data[16:] == payload


def test_empty_recording(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "empty.mrec"
    RecordingWriter(path).close()
    assert path.read_bytes() == MAGIC
    assert list(read_messages(path)) == []


def test_reopen_appends(tmp_path: Path) -> None:
    path = tmp_path / "run.mrec"
    items = messages(8)
    write(path, items[:4])
    write(path, items[4:])
    assert list(read_messages(path)) == items


def test_torn_tail_at_every_offset_is_cut_on_reopen(tmp_path: Path) -> None:
    full = tmp_path / "full.mrec"
    items = messages(4)
    offsets = write(full, items)
    data = full.read_bytes()
    last = offsets[-1]
    path = tmp_path / "torn.mrec"
    for cut in range(last + 1, len(data)):
        path.write_bytes(data[:cut])
        # Readers stop before the torn record ...
        assert list(read_messages(path)) == items[:-1], cut
        # ... and a writer reopening the file cuts it off and appends after the good ones.
        with RecordingWriter(path) as writer:
            assert path.stat().st_size == last
            writer.append(encode(items[-1]))
        assert path.read_bytes() == data, cut


def test_torn_header_is_restarted(tmp_path: Path) -> None:
    path = tmp_path / "torn-header.mrec"
    for cut in range(1, len(MAGIC)):
        path.write_bytes(MAGIC[:cut])
        with RecordingWriter(path) as writer:
            writer.append(encode(make_pose(1)))
        assert list(read_messages(path)) == [make_pose(1)]


def test_zero_filled_tail_is_cut(tmp_path: Path) -> None:
    # After a power loss some file systems leave the tail of a file as zero bytes.
    path = tmp_path / "zeros.mrec"
    items = messages(3)
    write(path, items)
    size = path.stat().st_size
    with open(path, "ab") as f:
        f.write(b"\0" * 4096)
    assert list(read_messages(path)) == items
    RecordingWriter(path).close()
    assert path.stat().st_size == size


def test_bad_crc_of_the_last_record_is_a_torn_tail(tmp_path: Path) -> None:
    path = tmp_path / "lastcrc.mrec"
    items = messages(3)
    write(path, items)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    assert list(read_messages(path)) == items[:-1]


def test_corrupt_crc_before_the_last_record_is_skipped_and_reported(tmp_path: Path) -> None:
    """Issue 16: one damaged record used to lose the whole recording (RecordingError)."""
    path = tmp_path / "crc.mrec"
    items = messages(4)
    offsets = write(path, items)
    data = bytearray(path.read_bytes())
    data[offsets[1] + HEADER.size + 3] ^= 0x01  # one bit inside the second payload
    path.write_bytes(bytes(data))
    report = RecordingReport()
    assert [r.offset for r in iter_raw_records(path, report)] == [offsets[0], *offsets[2:]]
    assert list(read_messages(path)) == [items[0], *items[2:]]
    assert report.records == 3
    assert report.records_lost == 1
    assert report.bytes_lost == offsets[2] - offsets[1]
    assert [(d.offset, d.reason) for d in report.damage] == [(offsets[1], "crc")]
    # Appending keeps the damage for fsck and goes on after the last intact record.
    with RecordingWriter(path, report=report) as writer:
        writer.append(encode(make_pose(9)))
    assert list(read_messages(path)) == [items[0], *items[2:], make_pose(9)]
    assert path.read_bytes()[: len(data)] == bytes(data)


@pytest.mark.parametrize("value", [0, 7, MAX_RECORD_BYTES + 1, 0xFFFFFFFF])
def test_damaged_length_is_resynchronised(tmp_path: Path, value: int) -> None:
    path = tmp_path / "len.mrec"
    items = messages(5)
    offsets = write(path, items)
    set_length(path, offsets[1], value)
    report = scan_file(path)
    assert list(read_messages(path)) == [items[0], *items[2:]]
    assert report.records == 4
    assert report.records_lost >= 1
    assert report.damage[0].offset == offsets[1]
    assert report.bytes_lost == offsets[2] - offsets[1]


def test_damage_in_the_last_record_is_reported_not_torn(tmp_path: Path) -> None:
    path = tmp_path / "last.mrec"
    items = messages(3)
    offsets = write(path, items)
    data = bytearray(path.read_bytes())
    data[offsets[2] + HEADER.size + 2] ^= 0x10
    path.write_bytes(bytes(data))
    report = scan_file(path)
    assert (report.records, report.records_lost, report.torn_tail_bytes) == (2, 1, 0)
    with RecordingWriter(path, report=report):
        pass  # truncates the damaged record, after keeping a copy of it
    assert path.stat().st_size == offsets[2]
    (backup,) = tmp_path.glob("last.mrec.tail-*.damaged")
    assert backup.read_bytes() == bytes(data[offsets[2] :])


def test_length_past_the_end_of_the_file_is_a_torn_tail(tmp_path: Path) -> None:
    path = tmp_path / "len.mrec"
    offsets = write(path, messages(3))
    data = set_length(path, offsets[2], 1000)
    report = scan_file(path)
    assert [r.offset for r in iter_raw_records(path)] == offsets[:2]
    assert report.torn_tail_bytes == len(data) - offsets[2]
    assert not report.damaged


def test_an_impossible_length_in_the_last_record_is_damage_not_a_torn_tail(tmp_path: Path) -> None:
    """A length no record can have, with nothing intact after it: damage, counted and kept for
    inspection, not a write cut short by a crash (that one is a plausible length past the end)."""
    path = tmp_path / "len.mrec"
    offsets = write(path, messages(3))
    set_length(path, offsets[2], 0xFFFFFFFF)
    report = scan_file(path)
    assert (report.records, report.records_lost, report.torn_tail_bytes) == (2, 1, 0)
    assert report.damage[0].reason == "length"
    assert report.damage[0].offset == offsets[2]


@pytest.mark.parametrize(
    "content", [b"", b"MMREC02\n", b"not a recording at all", b"\x89PNG\r\n\x1a\n"]
)
def test_bad_magic(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.mrec"
    path.write_bytes(content)
    assert not is_recording(path)
    with pytest.raises(RecordingError, match="magic"):
        list(iter_raw_records(path))
    with pytest.raises(RecordingError):
        list(read_messages(path))
    if content:
        with pytest.raises(RecordingError):
            RecordingWriter(path)


def test_undecodable_records_are_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "mixed.mrec"
    with RecordingWriter(path) as writer:
        writer.append(encode_pose(make_pose(1)))
        writer.append(b"\x93\x01\x02\x03")  # msgpack, but not a message
        writer.append(b"\x82\xa1v\x01\xa4type\xa4scan")  # a scan missing its fields
        writer.append(encode_pose(make_pose(2)))
    with caplog.at_level(logging.WARNING, logger="clients.recording"):
        assert list(read_messages(path)) == [make_pose(1), make_pose(2)]
    assert "unknown kind" in caplog.text
    assert "does not decode" in caplog.text


def test_append_refuses_empty_and_oversized_payloads(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "x.mrec") as writer:
        with pytest.raises(RecordingError):
            writer.append(b"")
        with pytest.raises(RecordingError):
            writer.append(b"\0" * (MAX_RECORD_BYTES + 1))
        assert writer.records_written == 0


def test_fsync_every(tmp_path: Path) -> None:
    path = tmp_path / "sync.mrec"
    with RecordingWriter(path, fsync_every=2) as writer:
        for m in messages(5):
            writer.append(encode(m))
        writer.sync()
    assert list(read_messages(path)) == messages(5)


def test_every_append_reaches_the_kernel_before_it_returns(tmp_path: Path) -> None:
    """What the service's durability rests on: a record is readable by another reader (and so
    survives kill -9 of the writer) as soon as `append` returns, without close or sync."""
    path = tmp_path / "live.mrec"
    items = messages(4)
    with RecordingWriter(path) as writer:
        for n, m in enumerate(items, 1):
            writer.append(encode(m))
            assert list(read_messages(path)) == items[:n]


def test_fsync_every_n_appends_and_on_sync(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real_fsync = os.fsync

    def counting_fsync(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    monkeypatch.setattr("clients.recording.os.fsync", counting_fsync)
    with RecordingWriter(tmp_path / "a.mrec", fsync_every=2) as writer:
        for m in messages(5):
            writer.append(encode(m))
        assert len(synced) == 2  # after appends 2 and 4
        writer.sync()
        assert len(synced) == 3
        writer.append(encode(make_pose(9)))
        writer.append(encode(make_pose(10)))
        assert len(synced) == 4  # counting restarts at the sync
    synced.clear()
    with RecordingWriter(tmp_path / "b.mrec") as writer:  # fsync_every=0: the page cache only
        for m in messages(5):
            writer.append(encode(m))
        assert synced == []


def test_missing_file_is_not_a_recording(tmp_path: Path) -> None:
    assert not is_recording(tmp_path / "nope.mrec")
    with pytest.raises(FileNotFoundError):
        list(iter_raw_records(tmp_path / "nope.mrec"))
