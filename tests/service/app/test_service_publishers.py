"""A second publisher on a robot's key: detected, counted, flagged, logged once, refused.

The acceptance test runs two real `sensor-agent --emulate` processes as the same robot id, in
two different buildings, against a real `mapping-service serve`. The first one keeps the key;
the second one's scans are refused, so the trajectory never jumps between the buildings.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from svc_testkit import ServiceProc, agent, metric_sum, wait_for

if TYPE_CHECKING:
    from service.app.publishers import PublisherGuard

A, B = "aa" * 16, "bb" * 16


class FakeClock:
    def __init__(self) -> None:
        self.now_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.now_ns

    def advance(self, seconds: float) -> None:
        self.now_ns += int(seconds * 1e9)


def guard(**kwargs: object) -> PublisherGuard:
    # Imported here: the two-agent test below also runs against a tree without the guard.
    from service.app.publishers import PublisherGuard

    return PublisherGuard(**kwargs)  # type: ignore[arg-type]


def test_the_first_publisher_keeps_the_key_while_present() -> None:
    clock = FakeClock()
    refused: list[str] = []
    intruders: list[str] = []
    g = guard(
        takeover_after_s=5.0,
        clock_ns=clock,
        on_refused=refused.append,
        on_intruder=intruders.append,
    )
    g.token_changed("r9", A, present=True)
    assert g.admit("r9", A)
    g.token_changed("r9", B, present=True)
    for _ in range(3):
        assert not g.admit("r9", B)
        assert g.admit("r9", A)
    assert not g.admit("r9", None)  # no source id once the owner has one: refused too
    assert refused == ["r9"] * 4
    assert intruders == ["r9", "r9"]  # B and "no source id": each counted once
    (status,) = g.status()
    assert (status.owner, status.publishers, status.refused, status.conflict) == (A, 2, 4, True)
    # A silent owner whose token is still there keeps the key.
    clock.advance(60)
    assert not g.admit("r9", B)
    # Its token withdrawn (agent stopped or killed): the next source takes over at once.
    g.token_changed("r9", A, present=False)
    assert g.admit("r9", B)
    assert not g.admit("r9", A)
    # Other robots are independent.
    assert g.admit("r7", A)


def test_a_silent_owner_without_a_token_is_replaced_after_the_takeover_time() -> None:
    clock = FakeClock()
    g = guard(takeover_after_s=5.0, conflict_hold_s=30.0, clock_ns=clock)
    assert g.admit("r1", A)
    clock.advance(4.0)
    assert not g.admit("r1", B)
    clock.advance(5.1)  # A silent for 5.1 s since its last admitted scan
    assert g.admit("r1", B)
    assert [s.conflict for s in g.status()] == [True]  # B was refused 5.1 s ago
    clock.advance(31)
    assert [s.conflict for s in g.status()] == [False]


def test_legacy_publishers_without_source_ids_are_admitted() -> None:
    g = guard()
    assert all(g.admit("old", None) for _ in range(5))
    assert g.status()[0].refused == 0


def test_made_up_robot_ids_do_not_grow_memory() -> None:
    g = guard(max_robots=3)
    for i in range(100):
        assert g.admit(f"r{i}", A)
        g.token_changed(f"t{i}", B, present=True)
    assert len(g.status()) == 3


def test_publisher_alive_keys() -> None:
    from clients.keyexpr import publisher_alive_key, publisher_from_alive_key

    key = publisher_alive_key("r9", A, "fleet/site-1")
    assert key == f"fleet/site-1/r9/alive/{A}"
    assert publisher_from_alive_key(key, "fleet/site-1") == ("r9", A)
    for bad in (f"fleet/site-1/r9/alive/{A}/x", "fleet/site-1/r9/alive/NOT-HEX", "fleet/site-1/r9"):
        assert publisher_from_alive_key(bad, "fleet/site-1") is None


# ---------------------------------------------------------------------------------------------
# Two real agents as one robot


def robot_health(svc: ServiceProc, robot_id: str) -> dict[str, object]:
    robots = svc.json("/health")["robots"]
    assert isinstance(robots, list)
    return next((r for r in robots if r["robot_id"] == robot_id), {})


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "layout",
    [[], ["--mapper-processes", "2"]],
    ids=["one-process", "mapper-processes"],
)
def test_two_agents_as_one_robot(tmp_path: Path, layout: list[str]) -> None:
    svc = ServiceProc(tmp_path / "data", extra_args=layout)
    svc.start()
    try:
        sid = svc.create_session("r9")["id"]
        with agent(svc, "r9", 1, tmp_path / "agent-a.log"):
            wait_for(
                lambda: int(svc.json(f"/sessions/{sid}")["scans_accepted"]) >= 40,
                60,
                "the first agent's scans to be mapped",
            )
            assert robot_health(svc, "r9")["duplicate_publisher"] is False
            with agent(svc, "r9", 7, tmp_path / "agent-b.log"):
                wait_for(
                    lambda: robot_health(svc, "r9").get("duplicate_scans_refused", 0) >= 80,
                    60,
                    "the second agent's scans to be refused",
                )
                health = svc.json("/health")
                r9 = robot_health(svc, "r9")
                assert r9["duplicate_publisher"] is True
                assert r9["publishers"] == 2
                assert health["status"] == "degraded"
                assert any("r9" in w for w in health["warnings"])  # type: ignore[union-attr]
                metrics = svc.metrics()
                refused = metric_sum(
                    metrics, "mapping_scans_rejected_total", reason="duplicate_publisher"
                )
                assert refused >= 80
                assert metric_sum(metrics, "mapping_duplicate_publishers_total", robot="r9") == 1
                # The owner is still mapped meanwhile.
                before = int(svc.json(f"/sessions/{sid}")["scans_accepted"])
                wait_for(
                    lambda: int(svc.json(f"/sessions/{sid}")["scans_accepted"]) >= before + 40,
                    60,
                    "the first agent to go on being mapped",
                )
            poses = svc.json(f"/sessions/{sid}/trajectory")["poses"]
        assert isinstance(poses, list)
        # One building only: the robot drives at 0.7 m/s (~2 cm per scan); merged with a
        # second building, the pose jumped by up to 0.44 m between consecutive scans.
        steps = sorted(
            math.hypot(b["x"] - a["x"], b["y"] - a["y"]) for a, b in itertools.pairwise(poses)
        )
        assert sum(step > 0.1 for step in steps) <= len(steps) // 100, steps[-10:]
        log = svc.log_path.read_text()
        warned = [line for line in log.splitlines() if "duplicate_publisher" in line]
        assert len(warned) == 1, warned  # one line for one intruder, however many scans
        assert "refusing its scans" in warned[0]
    finally:
        svc.stop()
