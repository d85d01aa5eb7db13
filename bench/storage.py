"""`python -m bench.storage [--scans N]`: disk bytes per robot-hour of a mapping session.

Feeds N simulated UTM-30LX scans (1,081 beams, the synthetic building of the tests) through a
real `SessionManager` in a temporary data directory, with the service's checkpoint interval
(2,400 scans), then measures the files: the recording segments, the checkpoints and their
array pack (and a pickle of the same estimator and grid, the old format), and what retention
leaves. Bytes per robot-hour are projected at 40 Hz (144,000 scans an hour). Sizes, not speed:
the machine's load does not change them.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import pickle
import sys
import tempfile
from pathlib import Path

import numpy as np

from clients.wire import Scan, encode_scan
from sensor_agent.sim import LaserModel, RobotMotion, generate_building, simulate_scan
from service.app.mapper import Engine, LocalMapper
from service.app.sessions import MappingSession, SessionManager
from service.app.store import DataDir, MapStore

SCANS_PER_HOUR = 40 * 3600
PERIOD_NS = 25_000_000


def scans(count: int, seed: int = 1) -> list[tuple[bytes, Scan]]:
    world = generate_building(seed, "small")
    motion = RobotMotion(world, seed)
    model = LaserModel.utm30lx()
    rng = np.random.default_rng(seed)
    out = []
    for seq in range(count):
        sample = simulate_scan(world, motion.pose_at(seq * PERIOD_NS / 1e9), model, rng)
        scan = Scan(
            robot_id="bench",
            seq=seq,
            sensor_stamp_ns=seq * PERIOD_NS,
            host_stamp_ns=1_700_000_000_000_000_000 + seq * PERIOD_NS,
            angle_min_rad=model.angle_min_rad,
            angle_increment_rad=model.angle_increment_rad,
            range_min_m=model.range_min_m,
            range_max_m=model.range_max_m,
            ranges_m=np.nan_to_num(sample.ranges_m, nan=0.0),
        )
        out.append((encode_scan(scan), scan))
    return out


def measure(count: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        data = DataDir(Path(tmp))
        data.open()
        try:
            maps = MapStore(data.maps_dir)
            maps.load()
            manager = SessionManager(data, maps, engine=Engine())
            session = manager.create("bench", 0.05, True)
            for payload, scan in scans(count):
                session.ingest(payload, scan)
            folder = Path(tmp) / "sessions" / session.id
            mapper = session._mapper
            assert isinstance(mapper, LocalMapper)
            pickled = len(pickle.dumps((mapper._estimator, mapper._grid), protocol=5))
            recording = sum(p.stat().st_size for p in folder.glob("epoch-*.mrec"))
            checkpoints = [p.stat().st_size for p in folder.glob("checkpoint-*.mck")]
            # What the checkpoints hold that never changes, written once: kept for the session.
            pack = sum(p.stat().st_size for p in folder.glob("frozen-*.mpack"))
            freed = session.prune(0.0)
            retained = sum(p.stat().st_size for p in folder.glob("epoch-*.mrec"))
            pose_only = sum(p.stat().st_size for p in folder.glob("epoch-*.poses.mrec"))
            pruned_segments = len(list(folder.glob("epoch-*.poses.mrec")))
            session.close()
        finally:
            data.close()
    interval = MappingSession.checkpoint_every_scans
    per_scan = recording / count
    pose_per_scan = pose_only / (pruned_segments * interval) if pruned_segments else math.nan
    pack_per_scan = pack / count
    hour_no_retention = (per_scan + pack_per_scan) * SCANS_PER_HOUR + max(
        checkpoints, default=0
    ) * 2
    # With retention: poses of the whole hour, the scans of the two newest checkpoint intervals
    # (all retention keeps), two checkpoints, and the array pack (never pruned).
    hour_retained = (
        (pose_per_scan + pack_per_scan) * SCANS_PER_HOUR
        + per_scan * 2 * interval
        + max(checkpoints, default=0) * 2
    )
    return {
        "scans": count,
        "recording_bytes_per_scan": per_scan,
        "pose_bytes_per_scan_after_pruning": pose_per_scan,
        "checkpoint_bytes": float(max(checkpoints, default=0)),
        "array_pack_bytes_per_scan": pack_per_scan,
        "pickle_bytes_same_state": float(pickled),
        "freed_by_pruning_bytes": float(freed),
        "retained_bytes_after_pruning": float(retained),
        "mb_per_robot_hour_recording": hour_no_retention / 1e6,
        "mb_per_robot_hour_with_retention_0_days": hour_retained / 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.storage", description=__doc__)
    parser.add_argument("--scans", type=int, default=7300, help="scans to feed (default: 7300)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    json.dump(measure(args.scans), sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
