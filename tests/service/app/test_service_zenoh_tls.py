"""Zenoh's own protection, end to end on loopback: TLS plus user/password authentication.

A CA and a server certificate for 127.0.0.1 are made here (`cryptography`), the service and a
real `sensor-agent --emulate` get a `--zenoh-config` each (docs/service.md, "Securing Zenoh"):
the authenticated agent's scans are mapped; a peer without credentials, one with a wrong
password and one speaking plain TCP cannot connect, so their scans never reach a session.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port
from svc_testkit import ServiceProc, SimRobot, agent, wait_for

from clients.keyexpr import scan_key

pytestmark = pytest.mark.slow

AGENT_USER, AGENT_PASSWORD = "robot-r1", "agent-password-0123"
SERVICE_USER, SERVICE_PASSWORD = "mapping-service", "service-password-0123"
NO_SCOUTING = {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def make_certificates(folder: Path) -> dict[str, Path]:
    """A throwaway CA and a server certificate for 127.0.0.1 and localhost (EC P-256, 1 day)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)

    def name(common_name: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])

    def builder(subject: str, issuer: x509.Name, key: Any) -> x509.CertificateBuilder:
        return (
            x509.CertificateBuilder()
            .subject_name(name(subject))
            .issuer_name(issuer)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
        )

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        builder("mapping test CA", name("mapping test CA"), ca_key)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        builder("localhost", ca.subject, key)
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    paths = {"ca": folder / "ca.pem", "cert": folder / "server.pem", "key": folder / "server.key"}
    paths["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    paths["cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["key"].write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    paths["key"].chmod(0o600)
    return paths


def write_config(path: Path, config: dict[str, Any]) -> Path:
    path.write_text(json.dumps(config, indent=2))  # JSON is JSON5
    return path


def client_config(endpoint: str, ca: Path, user: str | None, password: str | None) -> Any:
    config: dict[str, Any] = {
        "mode": "peer",
        "connect": {"endpoints": [endpoint]},
        "listen": {"endpoints": []},
        "scouting": NO_SCOUTING,
        "transport": {"link": {"tls": {"root_ca_certificate": str(ca)}}},
    }
    if user is not None:
        config["transport"]["auth"] = {"usrpwd": {"user": user, "password": password}}
    return config


def test_only_authenticated_tls_peers_get_scans_mapped(tmp_path: Path) -> None:
    certs = make_certificates(tmp_path)
    users = tmp_path / "zenoh-users.txt"
    users.write_text(f"{AGENT_USER}:{AGENT_PASSWORD}\n")
    users.chmod(0o600)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    service_config = write_config(
        tmp_path / "service-zenoh.json5",
        {
            "mode": "peer",
            "listen": {"endpoints": [endpoint]},
            "scouting": NO_SCOUTING,
            "transport": {
                "link": {
                    "tls": {
                        "listen_certificate": str(certs["cert"]),
                        "listen_private_key": str(certs["key"]),
                        "root_ca_certificate": str(certs["ca"]),
                    }
                },
                "auth": {
                    "usrpwd": {
                        "user": SERVICE_USER,
                        "password": SERVICE_PASSWORD,
                        "dictionary_file": str(users),
                    }
                },
            },
        },
    )
    agent_config = write_config(
        tmp_path / "agent-zenoh.json5",
        client_config(endpoint, certs["ca"], AGENT_USER, AGENT_PASSWORD),
    )
    svc = ServiceProc(
        tmp_path / "data",
        extra_args=["--zenoh-config", str(service_config)],
        zenoh_endpoint=endpoint,
        listen_flag=False,
    )
    svc.start()
    rogues: list[Any] = []
    try:
        good = svc.create_session("r1")["id"]
        bad = svc.create_session("rogue")["id"]
        with agent(
            svc,
            "r1",
            1,
            tmp_path / "agent.log",
            zenoh_args=["--zenoh-config", str(agent_config)],
        ):
            wait_for(
                lambda: int(svc.json(f"/sessions/{good}")["scans_accepted"]) >= 20,
                60,
                "the authenticated agent's scans to be mapped over TLS",
            )
            attempts = {
                "no credentials": client_config(endpoint, certs["ca"], None, None),
                "wrong password": client_config(endpoint, certs["ca"], AGENT_USER, "guess"),
                "plain tcp": client_config(
                    endpoint.replace("tls/", "tcp/"), certs["ca"], AGENT_USER, AGENT_PASSWORD
                ),
            }
            for label, config in attempts.items():
                path = write_config(tmp_path / f"rogue-{label.replace(' ', '-')}.json5", config)
                rogues.append(zenoh.open(zenoh.Config.from_file(str(path))))
            robot = SimRobot("rogue")
            start = int(svc.json(f"/sessions/{good}")["scans_accepted"])
            deadline = time.monotonic() + 60
            # Publish the rogue's valid scans until the real agent has had 40 more mapped.
            while int(svc.json(f"/sessions/{good}")["scans_accepted"]) < start + 40:
                assert time.monotonic() < deadline, "the authenticated agent stopped"
                payload = robot.next_payload()
                for session in rogues:
                    session.put(scan_key("rogue"), payload)
                time.sleep(0.025)  # the robot's own 40 Hz pace, not a synchronisation
            assert svc.json(f"/sessions/{bad}")["scans_accepted"] == 0
            assert "rogue" not in svc.get("/metrics").text
            for label, session in zip(attempts, rogues, strict=True):
                assert list(session.info.peers_zid()) == [], label  # refused at the door
        assert svc.json(f"/sessions/{good}")["scans_accepted"] >= start + 40
    finally:
        for session in rogues:
            session.close()
        svc.stop()
