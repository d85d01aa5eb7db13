"""What other programs use to talk to the mapping system: wire messages, HTTP client, CLI."""

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
    "OdometryPose",
    "Pose",
    "PoseFlag",
    "Scan",
    "WireError",
    "decode_pose",
    "decode_scan",
    "encode_pose",
    "encode_scan",
]
