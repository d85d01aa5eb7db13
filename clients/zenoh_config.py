"""The one place that builds a Zenoh configuration, for every process of the system."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import zenoh

ZenohMode = Literal["peer", "client", "router"]


def build_zenoh_config(
    *,
    mode: ZenohMode = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | Path | None = None,
    multicast_scouting: bool = False,
) -> zenoh.Config:
    """A Zenoh config from a file (passed through untouched) plus explicit overrides.

    Without a file, listening is explicit (`[]` listens on nothing) and multicast scouting and
    gossip are off, so that nothing leaves loopback unless asked for.
    """
    if config_file is not None:
        conf = zenoh.Config.from_file(str(config_file))
    else:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
        conf.insert_json5("scouting/gossip/enabled", json.dumps(multicast_scouting))
    if config_file is not None and listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf
