"""`mapctl`: control and watch a mapping service from the command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapctl", description="Control a mapping service.")
    parser.add_argument("--server", default="http://127.0.0.1:8000", help="service base URL")
    parser.add_argument("--token", default=None, help="bearer token (or env MAPPING_TOKEN)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    build_parser().parse_args(argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
