"""`mapping-service fsck DATA_DIR [--repair]`: check a data directory; repair what is provable.

Per session folder it checks `session.json`, every recording segment (damaged records, torn
tails), every checkpoint (checksum, format) and the array pack the checkpoints refer to (each
entry's checksum). `--repair` only does what needs no guess:

- a recording segment with damaged records is rewritten with exactly its intact records, in
  order (the original is kept beside it as `<file>.bak-<unix time>`);
- a checkpoint that fails its checksum is moved aside as `<file>.rejected` (the service would
  ignore it anyway and replay from the recording).

A `session.json` that cannot be read is reported and left alone: its resolution and odometry
setting cannot be proven from the recording. A torn tail is reported as information: the service
cuts it when it appends again, as after any crash.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Final, TextIO

from clients.recording import (
    RecordingError,
    RecordingReport,
    RecordingWriter,
    iter_raw_records,
    scan_file,
)
from service.app import checkpoint as ckpt
from service.app import statecodec
from service.app.errors import StoreError
from service.app.store import (
    FSCK_REPAIRS,
    LEGACY_CHECKPOINT,
    RecordingRepair,
    parse_checkpoint,
    parse_pack,
    parse_segment,
    read_meta,
    read_repairs,
    record_repair,
)

log = logging.getLogger(__name__)

EXIT_CLEAN: Final = 0
EXIT_DAMAGED: Final = 1
EXIT_USAGE: Final = 2
EXIT_REPAIRED: Final = 3


@dataclass
class Finding:
    file: str
    problem: str
    repairable: bool
    repaired: bool = False


@dataclass
class SessionReport:
    session_id: str
    findings: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # not damage: torn tails, stale files
    records: int = 0


def check_session(directory: Path, *, repair: bool) -> SessionReport:
    report = SessionReport(directory.name)
    epoch: int | None = None
    try:
        epoch = read_meta(directory).epoch
    except StoreError as err:
        report.findings.append(Finding("session.json", err.reason, repairable=False))
    for path in sorted(directory.iterdir()):
        seg = parse_segment(path.name)
        cp = parse_checkpoint(path.name)
        if seg is not None:
            if epoch is not None and seg[0] != epoch:
                report.notes.append(f"{path.name}: another epoch's (removed at the next start)")
                continue
            _check_segment(path, report, repair=repair)
        elif cp is not None:
            _check_checkpoint(path, report, repair=repair)
        elif parse_pack(path.name) is not None:
            _check_pack(path, report)
        elif path.name == LEGACY_CHECKPOINT:
            report.notes.append(f"{path.name}: old pickle checkpoint, never loaded (replayed)")
        elif path.name == FSCK_REPAIRS:
            lost = sum(r.records_lost for r in read_repairs(directory))
            report.notes.append(f"{path.name}: an earlier repair cut {lost} damaged record(s)")
        elif ".damaged" in path.name or ".bak-" in path.name or path.name.endswith(".rejected"):
            report.notes.append(f"{path.name}: kept copy of damaged data")
    return report


def _check_segment(path: Path, report: SessionReport, *, repair: bool) -> None:
    try:
        rec = scan_file(path)
    except RecordingError as err:
        report.findings.append(Finding(path.name, str(err), repairable=False))
        return
    report.records += rec.records
    if rec.torn_tail_bytes:
        report.notes.append(
            f"{path.name}: torn tail of {rec.torn_tail_bytes} bytes (cut on append)"
        )
    if not rec.damage:
        return
    where = ", ".join(f"{d.length_bytes} B at {d.offset}" for d in rec.damage[:5])
    finding = Finding(
        path.name,
        f"{len(rec.damage)} damaged region(s) ({where}): {rec.records_lost} record(s) and "
        f"{rec.bytes_lost} bytes lost; {rec.records} intact",
        repairable=True,
    )
    report.findings.append(finding)
    if repair:
        backup = _rewrite_intact(path)
        # Remembered for the service: the rewritten segment alone looks intact, and a session
        # that lost records must still say `degraded`, with the counts.
        record_repair(
            path.parent,
            RecordingRepair(
                segment=path.name,
                records_lost=rec.records_lost,
                bytes_lost=rec.bytes_lost,
                regions=len(rec.damage),
                backup=backup.name,
                repaired_unix_s=int(time.time()),
            ),
        )
        finding.repaired = True


def _rewrite_intact(path: Path) -> Path:
    """Replace `path` with its intact records only; the original stays as a backup (returned)."""
    tmp = path.with_name(f".{path.name}.fsck.tmp")
    with RecordingWriter(tmp) as writer:
        for record in iter_raw_records(path, RecordingReport()):  # reported already
            writer.append(record.payload)
        writer.sync()
    backup = path.with_name(f"{path.name}.bak-{int(time.time())}")
    os.link(path, backup)  # the original bytes, under a name the service ignores
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return backup


def _check_checkpoint(path: Path, report: SessionReport, *, repair: bool) -> None:
    try:
        ckpt.read(path)
    except ckpt.CheckpointError as err:
        finding = Finding(path.name, f"checkpoint rejected: {err}", repairable=True)
        report.findings.append(finding)
        if repair:
            os.replace(path, path.with_name(path.name + ".rejected"))
            _fsync_dir(path.parent)
            finding.repaired = True


def _check_pack(path: Path, report: SessionReport) -> None:
    """The array pack of the checkpoints: a damaged entry makes each checkpoint that refers
    to it (or to a later one) restore by replay; nothing to repair in place."""
    try:
        pack = statecodec.check_pack(path)
    except OSError as err:
        report.findings.append(Finding(path.name, f"unreadable: {err}", repairable=False))
        return
    if pack.torn_tail_bytes:
        report.notes.append(f"{path.name}: torn tail of {pack.torn_tail_bytes} bytes (a crash)")
    if pack.damaged_at is not None:
        report.findings.append(
            Finding(
                path.name,
                f"{pack.damage} at byte {pack.damaged_at} (after {pack.entries} intact "
                "entries): checkpoints that refer to it are replayed instead",
                repairable=False,
            )
        )


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsck(data_dir: Path, *, repair: bool) -> list[SessionReport]:
    sessions = data_dir / "sessions"
    if not sessions.is_dir():
        return []
    return [
        check_session(d, repair=repair)
        for d in sorted(sessions.iterdir())
        if d.is_dir() and not d.name.startswith(".")
    ]


def _print_text(reports: list[SessionReport], out: TextIO) -> None:
    for r in reports:
        status = "ok" if not r.findings else "DAMAGED"
        out.write(f"{r.session_id}: {status} ({r.records} intact records)\n")
        for f in r.findings:
            action = (
                "repaired" if f.repaired else "repairable" if f.repairable else "not repairable"
            )
            out.write(f"  {f.file}: {f.problem} [{action}]\n")
        for note in r.notes:
            out.write(f"  note: {note}\n")
    damaged = sum(1 for r in reports if r.findings)
    out.write(f"{len(reports)} session(s), {damaged} with damage\n")


def run_fsck(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    data_dir = Path(args.data_dir)
    if not data_dir.is_dir():
        log.error("%s is not a directory", data_dir)
        return EXIT_USAGE
    lock_path = data_dir / "service.lock"
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            log.error("%s is in use by a running mapping service: stop it first", data_dir)
            return EXIT_USAGE
        reports = fsck(data_dir, repair=args.repair)
    finally:
        os.close(fd)
    if args.json:
        json.dump([asdict(r) for r in reports], out, indent=1)
        out.write("\n")
    else:
        _print_text(reports, out)
    findings = [f for r in reports for f in r.findings]
    if not findings:
        return EXIT_CLEAN
    if all(f.repaired for f in findings):
        return EXIT_REPAIRED
    return EXIT_DAMAGED
