"""Mutation check: hand-written mutants, each applied alone in a scratch copy of the checkout.

`make mutation` runs it (not part of `make test` or `.ci/run`). Every mutant is a plausible bug
in one of three places the issue names: the wire decoder (`clients/wire.py`), the recording
writer (`clients/recording.py`) and the front end, the matcher ("matcher": its search,
`matcher.py` and `search.py` with the branch and bound's bounds in `kernels.py`; its
Gauss-Newton refinement; its covariance, the weakest axis from the response; the walls' heading
prior, `walls.py`; the motion prior's mixture). For each, only the fast
tests of that place run, in stages (a later stage only when the earlier ones pass), with
`-x`: a mutant is *killed* when a test fails, *survived* when all pass. The unmutated copy
must pass every stage first.

    python scripts/mutation.py [--only wire,recording,matcher] [--jobs 2] [--write DOC]

Two scratch copies run side by side by default (`--jobs`).
A mutant whose text no longer occurs exactly once stops the run: update the mutant.
`--write` replaces DOC's whole mutation section: write it from a run of every part.

Exits 1 when a mutant survives (the target is none), 0 otherwise.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
# bench.report keeps `<!-- keep:NAME -->` blocks when it regenerates docs/benchmarks.md.
START, END = "<!-- keep:mutation -->", "<!-- /keep:mutation -->"
STAGE_TIMEOUT_S = 300.0

WIRE_STAGES = (
    ("tests/clients/test_wire_roundtrip.py",),
    ("tests/clients/test_wire_fuzz.py::test_declared_geometry_must_agree_with_the_arrays",),
    (
        "tests/clients/test_wire_fuzz.py::test_fuzz_decode_scan",
        "tests/clients/test_wire_fuzz.py::test_fuzz_decode_pose",
    ),
)
RECORDING_STAGES = (
    ("tests/clients/test_recording.py", "tests/clients/test_logs.py::test_mrec_round_trip"),
)
MATCHER_STAGES = (
    ("tests/service/core/test_search.py", "tests/service/core/test_kernels.py"),
    ("tests/service/core/test_matcher.py", "tests/service/core/test_heading.py"),
)
STAGES = {
    "wire": WIRE_STAGES,
    "recording": RECORDING_STAGES,
    "matcher": MATCHER_STAGES,
}


@dataclass(frozen=True)
class Mutant:
    group: str  # "wire", "recording" or "matcher"
    name: str
    path: str  # relative to the checkout
    original: str  # must occur exactly once in the file
    mutated: str


def _w(name: str, original: str, mutated: str) -> Mutant:
    return Mutant("wire", name, "clients/wire.py", original, mutated)


def _r(name: str, original: str, mutated: str) -> Mutant:
    return Mutant("recording", name, "clients/recording.py", original, mutated)


def _m(name: str, original: str, mutated: str, path: str = "matcher.py") -> Mutant:
    return Mutant("matcher", name, f"service/core/frontend/{path}", original, mutated)


MUTANTS: tuple[Mutant, ...] = (
    # -- the wire decoder ----------------------------------------------------------------------
    _w(
        "u16 ranges: beam count taken from the array",
        "        if len(raw) != 2 * beam_count:",
        "        beam_count = len(raw) // 2\n        if len(raw) % 2:",
    ),
    _w(
        "f32 ranges: beam count taken from the array",
        "        if len(raw) != 4 * beam_count:",
        "        beam_count = len(raw) // 4\n        if len(raw) % 4:",
    ),
    _w(
        "intensities length not checked",
        "        if len(raw_i) != 4 * beam_count:",
        "        if len(raw_i) % 4:",
    ),
    _w(
        "zero angle increment accepted",
        "    if not angle_increment_rad > 0.0:",
        "    if angle_increment_rad < 0.0:",
    ),
    _w(
        "angle_min bound doubled",
        "    if abs(angle_min_rad) > 2 * math.pi:",
        "    if abs(angle_min_rad) > 4 * math.pi:",
    ),
    _w(
        "span over one revolution accepted",
        "    if angle_increment_rad * (beam_count - 1) > 2 * math.pi + 1e-6:",
        "    if angle_increment_rad * (beam_count - 1) > 4 * math.pi:",
    ),
    _w(
        "range_min == range_max accepted",
        "    if not 0.0 <= range_min_m < range_max_m:",
        "    if not 0.0 <= range_min_m <= range_max_m:",
    ),
    _w(
        "zero beams accepted",
        '    beam_count = _int(body, "beam_count", 1, MAX_BEAMS)',
        '    beam_count = _int(body, "beam_count", 0, MAX_BEAMS)',
    ),
    _w(
        "any integer schema version accepted",
        "    if type(version) is not int or version != SCHEMA_VERSION:",
        "    if type(version) is not int:",
    ),
    _w(
        "message type not checked",
        "    if msg_type != expected_type:",
        "    if msg_type is None:",
    ),
    _w(
        "payload cap doubled",
        "    if size > max_payload_bytes:",
        "    if size > 2 * max_payload_bytes:",
    ),
    _w(
        "infinite floats accepted",
        "    if not math.isfinite(result):",
        "    if math.isnan(result):",
    ),
    _w(
        "booleans accepted as integers",
        "    if type(value) is not int:",
        "    if not isinstance(value, int):",
    ),
    _w(
        "negative scan seq accepted",
        '    seq = _int(body, "seq", 0, _U64_MAX)',
        '    seq = _int(body, "seq", _I64_MIN, _U64_MAX)',
    ),
    _w(
        "unsafe robot id accepted",
        "    if not is_valid_robot_id(robot_id):\n        raise DecodeError(",
        "    if not robot_id:\n        raise DecodeError(",
    ),
    _w(
        "unsafe session id accepted",
        "    if SESSION_ID_PATTERN.fullmatch(session_id) is None:",
        "    if not session_id:",
    ),
    _w(
        "quality above 1 accepted",
        "    if not 0.0 <= quality <= 1.0:",
        "    if not 0.0 <= quality:",
    ),
    _w(
        "u16 millimetres decoded with the wrong scale",
        '        ranges_m = np.frombuffer(raw, dtype="<u2").astype(np.float64) / 1000.0',
        '        ranges_m = np.frombuffer(raw, dtype="<u2").astype(np.float64) / 1024.0',
    ),
    _w(
        "intensities decoded big-endian",
        '        intensities = np.frombuffer(raw_i, dtype="<f4").astype(np.float32)',
        '        intensities = np.frombuffer(raw_i, dtype=">f4").astype(np.float32)',
    ),
    _w(
        "odometry x read from y",
        '            x_m=_finite_float(raw_odom, "x_m", "odom."),',
        '            x_m=_finite_float(raw_odom, "y_m", "odom."),',
    ),
    _w(
        "non-string map keys accepted",
        "            strict_map_key=True,",
        "            strict_map_key=False,",
    ),
    _w(
        "map length limit lifted",
        "            max_map_len=64,",
        "            max_map_len=1 << 20,",
    ),
    _w(
        "array length limit lifted",
        "            max_array_len=1024,",
        "            max_array_len=1 << 20,",
    ),
    _w(
        "string length limit lifted",
        "            max_str_len=4096,",
        "            max_str_len=1 << 20,",
    ),
    _w(
        "encoder truncates millimetres instead of rounding",
        "    mm = np.where(np.isfinite(r) & (r > 0.0), np.rint(r * 1000.0), 0.0)",
        "    mm = np.where(np.isfinite(r) & (r > 0.0), np.floor(r * 1000.0), 0.0)",
    ),
    # -- the recording writer (and its reader) -----------------------------------------------
    _r(
        "append leaves the record in the user-space buffer",
        "        self._f.write(_RECORD_HEADER.pack(len(payload), zlib.crc32(payload)) + payload)\n"
        "        self._f.flush()\n",
        "        self._f.write(_RECORD_HEADER.pack(len(payload), zlib.crc32(payload)) + payload)\n",
    ),
    _r(
        "fsync_every never fsyncs",
        "        if self._fsync_every and self._since_sync >= self._fsync_every:",
        "        if False:",
    ),
    _r(
        "sync() does not fsync",
        "    def sync(self) -> None:\n        self._f.flush()\n        os.fsync(self._f.fileno())",
        "    def sync(self) -> None:\n        self._f.flush()",
    ),
    _r(
        "empty payload accepted",
        "        if not 0 < len(payload) <= MAX_RECORD_BYTES:",
        "        if not 0 <= len(payload) <= MAX_RECORD_BYTES:",
    ),
    _r(
        "record header fields swapped",
        "_RECORD_HEADER.pack(len(payload), zlib.crc32(payload))",
        "_RECORD_HEADER.pack(zlib.crc32(payload) & 0xFFFF, len(payload))",
    ),
    _r(
        "reopen does not cut the torn tail",
        "            if keep < size:",
        "            if keep < 0:",
    ),
    _r(
        "reopen overwrites instead of appending",
        '            self._f = open(self.path, "ab")',
        '            self._f = open(self.path, "wb")',
    ),
    _r(
        "a torn header is not restarted",
        "    return len(head) < len(MAGIC) and MAGIC.startswith(head)",
        "    return False",
    ),
    _r(
        "records_written not counted",
        "        self.records_written += 1\n",
        "",
    ),
    _r(
        "CRC not checked",
        "    if zlib.crc32(mm[start : start + length]) != crc:",
        "    if False:",
    ),
    _r(
        "a CRC mismatch anywhere is taken for a torn tail",
        "        if size - pos < _RECORD_HEADER.size or _is_zero_from(mm, pos, size):",
        "        if True:",
    ),
    _r(
        "an impossible length anywhere is taken for a torn tail",
        "            if 0 < declared <= MAX_RECORD_BYTES and end > size:",
        "            if True:",
    ),
    _r(
        "magic not checked",
        "        if f.read(len(MAGIC)) != MAGIC:",
        "        if f.read(len(MAGIC)) is None:",
    ),
    _r(
        "valid_length forgets the record header",
        "            report.valid_end = pos\n",
        "            report.valid_end = pos - _RECORD_HEADER.size\n",
    ),
    # -- the matcher (the front end) -------------------------------------------------------
    _m(
        "search: window one column short of ±3σ in x",
        "    return thetas, math.ceil(half_y / res), math.ceil(half_x / res)",
        "    return thetas, math.ceil(half_y / res), math.ceil(half_x / res) - 1",
    ),
    _m(
        "search bound: a block's rotation spread ignored",
        "            reach = range_m[i] * h + 1e-6",
        "            reach = 1e-6",
        path="kernels.py",
    ),
    _m(
        "search bound: the wall prior at the block's farthest angle",
        "            nearest = 0.0 if z0 * z1 <= 0.0 else min(abs(z0), abs(z1))",
        "            nearest = 0.0 if z0 * z1 <= 0.0 else max(abs(z0), abs(z1))",
        path="kernels.py",
    ),
    _m(
        "search cost: x-θ term of the motion prior with the wrong sign",
        "            + 2.0 * info[0, 2] * dx * dt\n",
        "            - 2.0 * info[0, 2] * dx * dt\n",
        path="search.py",
    ),
    _m(
        "refine: Gauss-Newton step uphill",
        "        step = -_solve3(h + damped, g)",
        "        step = _solve3(h + damped, g)",
        path="kernels.py",
    ),
    _m(
        "refine: a step that raises the cost is accepted",
        "            if c2 <= cost:",
        "            if True:",
        path="kernels.py",
    ),
    _m(
        "refine: the Jacobian's θ term drops the y part",
        "    return hx, hy, hx * dqx_dt + hy * dqy_dt, jx, jy, jx * dqx_dt + jy * dqy_dt",
        "    return hx, hy, hx * dqx_dt + hy * dqy_dt, jx, jy, jx * dqx_dt",
        path="kernels.py",
    ),
    _m(
        "covariance: the reported covariance without the priors",
        "    covariance = np.linalg.inv(h)\n",
        "    covariance = np.linalg.inv(h_scan)\n",
    ),
    _m(
        "weakest axis: the Hessian's information not taken out",
        "np.linalg.inv(np.linalg.inv(covariance) - h_scan + h_weak)",
        "np.linalg.inv(np.linalg.inv(covariance) + h_weak)",
    ),
    _m(
        "weakest axis: the strongest eigenvector taken",
        "    u = evecs[:, 0]",
        "    u = evecs[:, 1]",
    ),
    _m(
        "weakest axis: the response's mean not fused with the prediction",
        "    mean_m = (prior_u * pred_u + info_u * mean_m) / (prior_u + info_u)\n",
        "",
    ),
    _m(
        "heading prior: Huber's IRLS weight left at 1 beyond the knee",
        "        wz = 1.0 if a <= wall_huber else wall_huber / a",
        "        wz = 1.0",
        path="kernels.py",
    ),
    _m(
        "heading prior: σ not scaled by decisiveness",
        "math.radians(opts.sigma_deg) / math.sqrt(meas.weight)",
        "math.radians(opts.sigma_deg)",
        path="walls.py",
    ),
    _m(
        "wall families: the gate in degrees taken as radians",
        "    best, best_d = None, math.radians(opts.family_gate_deg)",
        "    best, best_d = None, opts.family_gate_deg",
        path="walls.py",
    ),
    _m(
        "heading prior: nearest member truncated, not rounded",
        "    turns = round((predicted_rad - walls_rad) / QUARTER)",
        "    turns = int((predicted_rad - walls_rad) / QUARTER)",
        path="walls.py",
    ),
    _m(
        "mixture: the broad component's cost with the wrong sign",
        "    if broad.cost + opts.broad_cost < result.cost:",
        "    if broad.cost - opts.broad_cost < result.cost:",
    ),
)


@dataclass(frozen=True)
class Result:
    mutant: Mutant
    killed: bool
    detail: str  # the first failing test, or "" for a survivor
    seconds: float


def _say(text: str) -> None:
    """Progress and the report on stdout (a command-line tool, not library code)."""
    sys.stdout.write(text.rstrip("\n") + "\n")
    sys.stdout.flush()


def _copy_checkout(dest: Path) -> None:
    ignore = shutil.ignore_patterns(
        ".venv", ".git", "__pycache__", ".mypy_cache", ".ruff_cache", ".pytest_cache",
        "test-artifacts", "bench-out", "*.pyc",
    )  # fmt: skip
    shutil.copytree(REPO_ROOT, dest, ignore=ignore, dirs_exist_ok=True)


def _run_stage(scratch: Path, tests: Sequence[str]) -> tuple[int, str]:
    env = {**os.environ, "PYTHONPATH": str(scratch), "PYTHONDONTWRITEBYTECODE": "1"}
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "--no-header", "-p", "no:cacheprovider"]
    cmd += tests
    try:
        proc = subprocess.run(
            cmd,
            check=False,
            cwd=scratch,
            env=env,
            capture_output=True,
            text=True,
            timeout=STAGE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        return -1, f"timed out after {STAGE_TIMEOUT_S:.0f} s"
    failed = [ln for ln in proc.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    tail = proc.stdout.strip().splitlines()[-1:] if proc.stdout.strip() else [proc.stderr[-300:]]
    return proc.returncode, (failed[0] if failed else tail[0]).strip()


class Runner:
    """Runs test stages in the scratch copy; each stage is checked on the unmutated code the
    first time a mutant reaches it (a stage that fails unmutated would kill every mutant)."""

    def __init__(self, scratch: Path) -> None:
        self.scratch = scratch
        self._baseline_ok: set[tuple[str, ...]] = set()

    def stages(self, stages: Sequence[Sequence[str]], mutant: Mutant) -> tuple[bool, str]:
        """(killed, detail) for `mutant`: the first stage that fails kills it."""
        target = self.scratch / mutant.path
        source = target.read_text(encoding="utf-8")
        if source.count(mutant.original) != 1:
            raise SystemExit(
                f"mutation: {mutant.path}: the text of mutant {mutant.name!r} occurs "
                f"{source.count(mutant.original)} times (the code changed: update the mutant)"
            )
        for tests in stages:
            key = tuple(tests)
            if key not in self._baseline_ok:
                rc, detail = _run_stage(self.scratch, tests)
                if rc != 0:
                    raise SystemExit(f"mutation: unmutated, {list(tests)} fail: {detail}")
                self._baseline_ok.add(key)
            target.write_text(source.replace(mutant.original, mutant.mutated), encoding="utf-8")
            try:
                rc, detail = _run_stage(self.scratch, tests)
            finally:
                target.write_text(source, encoding="utf-8")
            if rc == 5:
                raise SystemExit(f"mutation: no tests collected for {list(tests)}: {detail}")
            if rc != 0:
                return True, detail
        return False, ""


def run(mutants: Sequence[Mutant], jobs: int = 2) -> list[Result]:
    """Every mutant in one of `jobs` scratch copies (one runner thread per copy)."""
    todo: queue.SimpleQueue[tuple[int, Mutant]] = queue.SimpleQueue()
    for item in enumerate(mutants):
        todo.put(item)
    results: dict[int, Result] = {}
    lock = threading.Lock()

    def worker() -> None:
        with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
            scratch = Path(tmp)
            _copy_checkout(scratch)
            runner = Runner(scratch)
            while True:
                try:
                    i, m = todo.get_nowait()
                except queue.Empty:
                    return
                t0 = time.monotonic()
                killed, detail = runner.stages(STAGES[m.group], m)
                with lock:
                    results[i] = Result(m, killed, detail, time.monotonic() - t0)
                    verdict = "killed" if killed else "SURVIVED"
                    _say(
                        f"[{len(results)}/{len(mutants)}] {m.group}: {m.name}: {verdict} ({detail})"
                    )

    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        for future in [pool.submit(worker) for _ in range(max(1, jobs))]:
            future.result()  # re-raises a worker's SystemExit (a stale mutant, a failing baseline)
    return [results[i] for i in range(len(mutants))]


def report(results: Sequence[Result], elapsed_s: float) -> str:
    lines = [
        START,
        "## Mutation check",
        "",
        (
            "Generated by `make mutation` (`python scripts/mutation.py`) on "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {elapsed_s / 60:.1f} min on a "
            "2-core machine shared with other work. Each hand-written mutant is applied alone in "
            "a scratch copy, and only the fast tests of its part run (the list is in the script)."
        ),
        "",
        "| part | mutants | killed | score | surviving mutants |",
        "|---|---|---|---|---|",
    ]
    for group in ("wire", "recording", "matcher"):
        rs = [r for r in results if r.mutant.group == group]
        if not rs:
            continue
        killed = sum(r.killed for r in rs)
        survivors = "; ".join(r.mutant.name for r in rs if not r.killed) or "none"
        label = {
            "wire": "wire decoder (`clients/wire.py`)",
            "recording": "recording writer (`clients/recording.py`)",
            "matcher": "matcher (`service/core/frontend/matcher.py`, `search.py`, `kernels.py`, "
            "`walls.py`)",
        }[group]
        lines.append(f"| {label} | {len(rs)} | {killed} | {killed / len(rs):.0%} | {survivors} |")
    total = len(results)
    killed_all = sum(r.killed for r in results)
    lines += [
        "",
        f"Overall: {killed_all} of {total} mutants killed ({killed_all / max(total, 1):.0%}).",
        "",
        (
            "The target is no survivor (the script exits 1 otherwise); the slow dataset tests "
            "are not part of this check."
        ),
        "",
        "<details><summary>Every mutant and the test that killed it</summary>",
        "",
        "| part | mutant | result | first failing test |",
        "|---|---|---|---|",
    ]
    for r in results:
        verdict = "killed" if r.killed else "**survived**"
        detail = r.detail.replace("|", "\\|")[:140]
        lines.append(f"| {r.mutant.group} | {r.mutant.name} | {verdict} | {detail} |")
    lines += ["", "</details>", END]
    return "\n".join(lines) + "\n"


def write_section(doc: Path, section: str) -> None:
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    if START in text and END in text:
        head, rest = text.split(START, 1)
        tail = rest.split(END, 1)[1].lstrip("\n")
        text = head + section + ("\n" + tail if tail else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section
    doc.write_text(text, encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python scripts/mutation.py",
        description="Apply hand-written mutants one at a time in a scratch copy and run the "
        "fast tests of the mutated part; report killed and surviving mutants.",
    )
    parser.add_argument(
        "--only",
        default="wire,recording,matcher",
        help="comma-separated parts to mutate (default: %(default)s)",
    )
    parser.add_argument(
        "--write",
        type=Path,
        metavar="DOC",
        help="replace the mutation section of DOC (e.g. docs/benchmarks.md) with the result",
    )
    parser.add_argument(
        "--jobs", type=int, default=2, help="scratch copies run side by side (default: 2)"
    )
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = parser.parse_args(argv)
    groups = {g.strip() for g in args.only.split(",") if g.strip()}
    unknown = groups - set(STAGES)
    if unknown:
        parser.error(f"unknown parts: {sorted(unknown)}; choose from {sorted(STAGES)}")
    mutants = [m for m in MUTANTS if m.group in groups]
    if args.list:
        for m in mutants:
            _say(f"{m.group}: {m.name} ({m.path})")
        return 0
    t0 = time.monotonic()
    results = run(mutants, args.jobs)
    section = report(results, time.monotonic() - t0)
    _say(section)
    if args.write:
        write_section(args.write, section)
    target_missed = [r for r in results if not r.killed]
    return 1 if target_missed else 0


if __name__ == "__main__":
    sys.exit(main())
