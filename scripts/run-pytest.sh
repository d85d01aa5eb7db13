#!/usr/bin/env bash
# Runs the test suite and refuses to call "no tests collected" (pytest exit 5) a pass.
set -u
python="${1:-python3}"
shift || true
"$python" -m pytest "$@"
rc=$?
if [ "$rc" -eq 5 ]; then
    echo "run-pytest: pytest collected no tests; failing on purpose" >&2
    exit 1
fi
exit "$rc"
