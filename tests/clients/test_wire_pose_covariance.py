"""The pose message's optional covariance: round trip, absence, and bad values refused."""

from __future__ import annotations

import msgpack
import pytest

from clients.wire import DecodeError, Pose, PoseFlag, decode_pose, encode_pose
from service.app.api.schemas import PoseView

COV = (1e-4, 2e-6, 0.0, 2e-6, 4e-4, 0.0, 0.0, 0.0, 3e-6)


def _pose(covariance: tuple[float, ...] | None) -> Pose:
    return Pose("s-1", "r1", 3, 10, 1.0, 2.0, 0.5, 0.9, PoseFlag.AMBIGUOUS_X, covariance=covariance)


def test_covariance_round_trips_and_reaches_the_http_view() -> None:
    pose = decode_pose(encode_pose(_pose(COV)))
    assert pose.covariance == COV
    assert PoseView.of(pose).covariance == list(COV)


def test_a_pose_without_covariance_decodes_as_before() -> None:
    payload = encode_pose(_pose(None))
    assert b"cov" not in payload  # an old decoder sees exactly the old message
    assert decode_pose(payload).covariance is None
    assert PoseView.of(decode_pose(payload)).covariance is None


@pytest.mark.parametrize(
    "cov",
    [
        [0.0] * 8,  # not 3x3
        [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],  # negative variance
        [1.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],  # not symmetric
        [float("nan")] + [0.0] * 8,
        ["1"] + [0.0] * 8,
        "nine numbers",
    ],
)
def test_bad_covariance_is_refused(cov: object) -> None:
    body = msgpack.unpackb(encode_pose(_pose(None)))
    body["cov"] = cov
    with pytest.raises(DecodeError) as err:
        decode_pose(msgpack.packb(body, use_bin_type=True))
    assert err.value.reason == "bad_covariance"
