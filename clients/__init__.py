"""What other programs use to talk to the mapping system: wire messages, HTTP client, CLI."""

from clients.http import (
    Graph,
    MapInfo,
    MappingClient,
    MappingConnectionError,
    MappingError,
    MappingProtocolError,
    PoseView,
    SavedMap,
    Session,
)
from clients.subscriber import PoseSubscriber, SubscriberClosedError
from clients.wire import (
    DecodeError,
    OdometryPose,
    Pose,
    PoseFlag,
    Scan,
    WireError,
    decode_pose,
    decode_scan,
    encode_pose,
    encode_scan,
)

__all__ = [
    "DecodeError",
    "Graph",
    "MapInfo",
    "MappingClient",
    "MappingConnectionError",
    "MappingError",
    "MappingProtocolError",
    "OdometryPose",
    "Pose",
    "PoseFlag",
    "PoseSubscriber",
    "PoseView",
    "SavedMap",
    "Scan",
    "Session",
    "SubscriberClosedError",
    "WireError",
    "decode_pose",
    "decode_scan",
    "encode_pose",
    "encode_scan",
]
