"""Instances that split a fleet, with real processes on loopback: one Zenoh router (a Python
session in router mode), `mapping-service serve --robots PATTERN` instances connected to it,
emulated robots (a light in-test publisher, plus one real `sensor-agent --emulate`), and the
fleet view from `mapctl fleet --zenoh-connect` and `GET /fleet`."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import REPO_ROOT, free_port
from svc_testkit import ScanPublisher, ServiceProc, metric_sum, wait_for, zenoh_router

pytestmark = pytest.mark.slow

OWNERS = {"inst-a": "wa-*", "inst-b": "wb-*", "inst-c": "wc-*"}
ROBOTS = [f"w{c}-{i}" for c in "abc" for i in (1, 2, 3)]
AGENT_ROBOT = "wc-3"  # the one robot driven by a real sensor-agent --emulate


def owner_of(robot_id: str) -> str:
    return f"inst-{robot_id[1]}"


class Instance(ServiceProc):
    """An instance connected to the router as a Zenoh client (see `ScanPublisher`)."""

    def start(
        self,
        timeout_s: float = 30.0,
        env: dict[str, str] | None = None,
        args: list[str] | None = None,
    ) -> None:
        super().start(timeout_s, {"MAPPING_ZENOH_MODE": "client", **(env or {})}, args)


def instance(tmp_path: Path, name: str, router: str, *patterns: str) -> ServiceProc:
    args = ["--instance-id", name, "--zenoh-connect", router]
    for pattern in patterns:
        args += ["--robots", pattern]
    return Instance(tmp_path / name, extra_args=args)


def mapctl_fleet(router: str) -> dict[str, Any]:
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "fleet", "--zenoh-connect", router, "--json"],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO_ROOT,
        check=True,
    )
    data = json.loads(out.stdout)
    assert isinstance(data, dict)
    return data


def owners(view: dict[str, Any]) -> dict[str, str]:
    """robot -> instance of every active session in a fleet view (fails on a duplicate)."""
    out: dict[str, str] = {}
    for inst in view["instances"]:
        for s in inst["sessions"]:
            if s["state"] == "active":
                assert s["robot_id"] not in out, f"{s['robot_id']} mapped twice: {view}"
                out[s["robot_id"]] = inst["instance_id"]
    return out


@pytest.fixture(name="router")
def router_fixture() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh_router(endpoint):
        yield endpoint


@pytest.mark.timeout(240)
def test_three_instances_split_nine_robots_and_the_fleet_view_follows_them(
    tmp_path: Path, router: str
) -> None:
    services = {name: instance(tmp_path, name, router, pat) for name, pat in OWNERS.items()}
    agent: subprocess.Popen[bytes] | None = None
    try:
        for svc in services.values():
            svc.start()
        sessions: dict[str, str] = {}
        for robot_id in ROBOTS:
            owner = services[owner_of(robot_id)]
            other = services["inst-a" if owner_of(robot_id) != "inst-a" else "inst-b"]
            refused = httpx.post(other.url + "/sessions", json={"robot_id": robot_id})
            assert refused.status_code == 409, refused.text  # not its pattern
            sessions[robot_id] = str(owner.create_session(robot_id)["id"])

        agent_log = (tmp_path / "agent.log").open("wb")
        agent = subprocess.Popen(
            [
                str(Path(sys.executable).parent / "sensor-agent"),
                "--robot-id",
                AGENT_ROBOT,
                "--emulate",
                "--zenoh-connect",
                router,
                "--zenoh-mode",
                "client",
                "--stats-interval",
                "0",
            ],
            stdout=agent_log,
            stderr=subprocess.STDOUT,
            cwd=REPO_ROOT,
        )
        light = [r for r in ROBOTS if r != AGENT_ROBOT]
        with ScanPublisher(router, light, rate_hz=8.0):

            def all_mapping() -> bool:
                assert agent is not None
                assert agent.poll() is None, "sensor-agent exited"
                for robot_id, sid in sessions.items():
                    svc = services[owner_of(robot_id)]
                    if int(svc.json(f"/sessions/{sid}")["poses"]) < 3:
                        return False
                return True

            wait_for(all_mapping, 90, "every robot's session to get poses")
            view = services["inst-a"].json("/fleet")
            cli_view = mapctl_fleet(router)

        # Every robot is mapped by exactly one instance: its owner has the only session, and
        # only the owner receives its scans (the others do not even subscribe to them).
        for v in (view, cli_view):
            assert owners(v) == {r: owner_of(r) for r in ROBOTS}
            assert {i["instance_id"] for i in v["instances"]} == set(OWNERS)
            assert v["conflicts"] == []
            for inst in v["instances"]:
                receiving = set(inst["robots_receiving"])
                assert receiving == {r for r in ROBOTS if owner_of(r) == inst["instance_id"]}
                assert inst["patterns"] == [OWNERS[inst["instance_id"]]]
        for name, svc in services.items():
            health = svc.json("/health")
            assert health["fleet"]["conflicts"] == []
            unmapped = metric_sum(svc.metrics(), "mapping_scans_unmapped_total")
            assert unmapped == 0, f"{name} saw scans it does not map"

        # Killing an instance removes its entries within seconds; a restart brings them back.
        services["inst-b"].kill9()

        def b_gone(v: dict[str, Any]) -> bool:
            return "inst-b" not in {i["instance_id"] for i in v["instances"]}

        wait_for(lambda: b_gone(services["inst-a"].json("/fleet")), 10, "inst-b gone (HTTP)")
        wait_for(lambda: b_gone(mapctl_fleet(router)), 10, "inst-b gone (mapctl)")
        assert set(owners(services["inst-c"].json("/fleet"))) == {
            r for r in ROBOTS if owner_of(r) != "inst-b"
        }
        services["inst-b"].start()
        expected = {r: owner_of(r) for r in ROBOTS}
        wait_for(lambda: owners(mapctl_fleet(router)) == expected, 15, "inst-b back (mapctl)")
        wait_for(lambda: owners(services["inst-c"].json("/fleet")) == expected, 15, "inst-b back")
    finally:
        if agent is not None:
            agent.send_signal(signal.SIGINT)
            try:
                agent.wait(timeout=15)
            except subprocess.TimeoutExpired:
                agent.kill()
                agent.wait(timeout=5)
        for svc in services.values():
            svc.stop()


@pytest.mark.timeout(180)
def test_overlapping_instances_report_the_conflict_in_health_and_the_log(
    tmp_path: Path, router: str
) -> None:
    a = instance(tmp_path, "ov-a", router, "ov-*")
    b = instance(tmp_path, "ov-b", router, "ov-1*", "other-*")
    try:
        # B maps ov-12, then goes down; A, alone, is allowed to start ov-12 too. When B comes
        # back with its session restored, both map ov-12: that must be reported, not silent.
        b.start()
        b.create_session("ov-12")
        b.stop()
        a.start()
        a.create_session("ov-12")
        b.start()

        def conflict(svc: ServiceProc) -> dict[str, Any] | None:
            health = svc.json("/health")
            found = health["fleet"]["conflicts"]
            if health["status"] == "degraded" and found and found[0]["robots"] == ["ov-12"]:
                result: dict[str, Any] = found[0]
                return result
            return None

        for svc in (a, b):
            found = wait_for(lambda svc=svc: conflict(svc), 10, "the conflict in /health")
            assert isinstance(found, dict)
            assert found["instances"] == ["ov-a", "ov-b"]
            assert found["patterns"] == [["ov-*", "ov-1*"]]
            wait_for(
                lambda svc=svc: (
                    "fleet conflict: instances ov-a and ov-b" in svc.log_tail(200)
                    and "both map ov-12" in svc.log_tail(200)
                ),
                10,
                "the conflict in the log",
            )
        # While A maps ov-13, B refuses a second session for it (it matches B's pattern too).
        a.create_session("ov-13")
        refused = httpx.post(b.url + "/sessions", json={"robot_id": "ov-13"}, timeout=10)
        assert refused.status_code == 409, refused.text
        assert "active session on ov-a" in refused.text
        assert metric_sum(a.metrics(), "mapping_fleet_conflicts") == 1
    finally:
        a.stop()
        b.stop()
