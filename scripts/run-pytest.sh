#!/usr/bin/env bash
# Runs the test suite and refuses to call "no tests collected" (pytest exit 5) a pass.
set -u
python="${1:-python3}"
shift || true
# Two workers (pytest-xdist): most tests wait on real processes, sockets and timers, so two of
# them share a 2-core machine well (this one: 569 s one at a time, 322 s with two). `-n 0` after the
# script's arguments runs them one at a time.
"$python" -m pytest -n 2 "$@"
rc=$?
if [ "$rc" -eq 5 ]; then
    echo "run-pytest: pytest collected no tests; failing on purpose" >&2
    exit 1
fi
exit "$rc"
