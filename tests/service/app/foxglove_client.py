"""A minimal Foxglove WebSocket protocol client for the tests (not a test module).

Speaks the protocol as a viewer does, over `websockets`: the `foxglove.sdk.v1` subprotocol,
`serverInfo` and `advertise` (JSON text frames), `subscribe`, then binary message-data frames
(opcode 1, subscription id u32, log time u64, payload). Payloads are decoded with the protobuf
schema the server advertised (a FileDescriptorSet), not with compiled-in classes.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import time
from dataclasses import dataclass
from typing import Any

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

SUBPROTOCOL = "foxglove.sdk.v1"
OP_MESSAGE_DATA = 1


@dataclass
class Received:
    topic: str
    log_time_ns: int
    message: Any  # a protobuf message built from the advertised schema


def message_class(schema_name: str, schema_b64: str) -> Any:
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:  # dependencies come first
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


async def receive_topics(url: str, topics: set[str], timeout_s: float) -> dict[str, Received]:
    """Connect, subscribe to `topics` once advertised, return the first message of each."""
    deadline = time.monotonic() + timeout_s
    channels: dict[int, dict[str, Any]] = {}
    subscribed: dict[int, dict[str, Any]] = {}  # subscription id -> channel
    got: dict[str, Received] = {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL]) as ws:  # type: ignore[list-item]
        while len(got) < len(topics):
            try:
                frame = await asyncio.wait_for(ws.recv(), max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                raise TimeoutError(
                    f"after {timeout_s:g} s: got {sorted(got)} of {sorted(topics)}; advertised "
                    f"{sorted(c['topic'] for c in channels.values())}"
                ) from None
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = []
                    for channel in msg["channels"]:
                        channels[channel["id"]] = channel
                        if channel["topic"] in topics:
                            sub_id = len(subscribed) + 1
                            subscribed[sub_id] = channel
                            new.append({"id": sub_id, "channelId": channel["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if frame[0] != OP_MESSAGE_DATA:
                continue
            sub_id, log_time_ns = struct.unpack_from("<IQ", frame, 1)
            channel = subscribed[sub_id]
            if channel["topic"] in got:
                continue
            assert channel["encoding"] == "protobuf", channel
            cls = message_class(channel["schemaName"], channel["schema"])
            got[channel["topic"]] = Received(
                channel["topic"], log_time_ns, cls.FromString(frame[13:])
            )
    return got


def fetch(url: str, topics: set[str], timeout_s: float = 30.0) -> dict[str, Received]:
    return asyncio.run(receive_topics(url, topics, timeout_s))
