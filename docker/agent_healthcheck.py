"""Container healthcheck for `sensor-agent` (the agent has no health endpoint of its own).

Exit 0 when a `sensor-agent` process is alive (not a zombie) and, unless AGENT_HEALTH_PORT is
empty, this container has an established TCP connection to that port (the Zenoh router).
Reads /proc only; no third-party imports.
"""

import os
import sys
from pathlib import Path

_ESTABLISHED = "01"


def agent_running() -> bool:
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            cmdline = (status.parent / "cmdline").read_bytes()
            state = next(
                line.split()[1]
                for line in status.read_text().splitlines()
                if line.startswith("State:")
            )
        except (OSError, StopIteration, IndexError):
            continue  # the process went away while we looked
        if b"sensor-agent" in cmdline and state != "Z":
            return True
    return False


def connected_to(port: int) -> bool:
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            remote_port = int(fields[2].rsplit(":", 1)[1], 16)
            if remote_port == port and fields[3] == _ESTABLISHED:
                return True
    return False


def main() -> int:
    if not agent_running():
        sys.stderr.write("no running sensor-agent process\n")
        return 1
    port = os.environ.get("AGENT_HEALTH_PORT", "").strip()
    if port and not connected_to(int(port)):
        sys.stderr.write(f"sensor-agent has no established connection to port {port}\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
