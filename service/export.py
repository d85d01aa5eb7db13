"""`mapping-service export SESSION_OR_RECORDING --mcap OUT`: a session or a recording as MCAP.

SESSION_OR_RECORDING is a `.mrec` recording file, or the id of a session in `--data-dir` (the
segments of its current recording are read in place, in order; the service may be running). The
final map is built from the recorded scans at their recorded poses (`service.mcapio.MapBuilder`).
The file is written next to OUT and renamed when complete, so OUT is never a half-written file.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from clients.recording import RecordingError, is_recording, read_messages
from service.app.store import SessionMeta, segment_files
from service.mcapio import MapBuilder, with_map, write_mcap

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


class ExportError(Exception):
    """A one-line reason the export cannot be done."""


def find_recording(source: str, data_dir: Path) -> tuple[list[Path], float]:
    """The recording files (a session's segments, in order) and the map resolution for a path
    or a session id."""
    path = Path(source)
    if path.is_file():
        if not is_recording(path):
            raise ExportError(f"{path}: not a recording (.mrec)")
        return [path], 0.05
    session_dir = data_dir / "sessions" / source
    meta_path = session_dir / "session.json"
    if not meta_path.is_file():
        raise ExportError(
            f"{source!r} is neither a recording file nor a session in {data_dir / 'sessions'}"
        )
    try:
        meta = SessionMeta.from_json(meta_path.read_bytes())
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ExportError(f"{meta_path}: unreadable: {err}") from err
    recording = segment_files(session_dir, meta.epoch)
    if not recording:
        raise ExportError(f"session {source}: no recording yet (no scan since its start or reset)")
    return recording, meta.resolution_m


def check_output(out: Path) -> None:
    """Fail before reading anything when OUT cannot be written."""
    parent = out.parent if str(out.parent) else Path(".")
    if out.is_dir():
        raise ExportError(f"{out} is a directory; --mcap names the file to write")
    if not parent.is_dir():
        raise ExportError(f"{parent}: no such directory")
    if not os.access(parent, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise ExportError(f"{out}: not writable")


def export_mcap(source: str, data_dir: Path, out: Path) -> dict[str, int]:
    check_output(out)
    recording, resolution_m = find_recording(source, data_dir)
    builder = MapBuilder(resolution_m)
    partial = out.with_name(out.name + ".partial")
    try:
        with partial.open("wb") as f:
            messages = (m for path in recording for m in read_messages(path))
            counts = write_mcap(with_map(messages, builder), f, builder.snapshot)
            f.flush()
            os.fsync(f.fileno())
        partial.replace(out)
    except RecordingError as err:
        partial.unlink(missing_ok=True)
        raise ExportError(str(err)) from err
    except OSError as err:
        partial.unlink(missing_ok=True)
        raise ExportError(f"{out}: {err.strerror or err}") from err
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return {
        "scans": counts.scans,
        "poses": counts.poses,
        "maps": counts.maps,
        "skipped": counts.skipped,
    }


def run_export(args: argparse.Namespace) -> int:
    try:
        counts = export_mcap(args.source, Path(args.data_dir), Path(args.mcap))
    except ExportError as err:
        log.error("%s", err)
        return EXIT_FAILURE
    # The command's result (stdout): what was written.
    print(  # noqa: T201
        f"{args.mcap}: {counts['scans']} scans, {counts['poses']} poses, "
        f"{counts['maps']} map (ROS 2 schemas)"
        + (
            f"; {counts['skipped']} left out (stamps outside ROS time)" if counts["skipped"] else ""
        ),
        flush=True,
    )
    return EXIT_OK
