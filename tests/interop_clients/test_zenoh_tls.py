"""`ucr zenoh` over Zenoh TLS on loopback: a router with a certificate from a test CA
(`ucr zenoh-router --zenoh-config`), the bridge in client mode trusting that CA
(`ucr zenoh --zenoh-config`), a subscriber with the CA receives /joint_states, one without it
cannot join. Certificates are made here with the openssl command."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time

import pytest

from .conftest import REPO, stop, ucr, wait_for
from .test_zenoh_ros2 import _connectable, free_port

pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")
pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")
pytestmark = [
    pytest.mark.timeout(240),
    pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl command for test certs"),
]


def _openssl(*args: str, cwd) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    _openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=ucr test CA",
        cwd=d,
    )
    _openssl(
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "router.key",
        "-out",
        "router.csr",
        "-subj",
        "/CN=localhost",
        cwd=d,
    )
    (d / "ext.cnf").write_text(
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\n"
    )
    _openssl(
        "x509",
        "-req",
        "-in",
        "router.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        "router.pem",
        "-days",
        "2",
        "-extfile",
        "ext.cnf",
        cwd=d,
    )
    port = free_port()
    router = {
        "mode": "router",
        "listen": {"endpoints": [f"tls/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "listen_certificate": str(d / "router.pem"),
                    "listen_private_key": str(d / "router.key"),
                }
            }
        },
    }
    client = {
        "mode": "client",
        "connect": {"endpoints": [f"tls/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": {"root_ca_certificate": str(d / "ca.pem")}}},
    }
    (d / "router.json5").write_text(json.dumps(router))
    (d / "client.json5").write_text(json.dumps(client))
    return d, port


def test_bridge_over_tls_reaches_a_subscriber_with_the_ca_only(rig, pki):
    import zenoh

    from interop import ros2
    from interop.ros2.type_hash import type_hash
    from interop.zenoh import rmw

    d, port = pki
    url = rig.ensure_whole()
    router = ucr("zenoh-router", "--zenoh-config", str(d / "router.json5"))
    bridge = None
    try:
        assert wait_for(lambda: _connectable(port), 30)
        bridge = ucr(
            "zenoh",
            "--url",
            url,
            "--zenoh-config",
            str(d / "client.json5"),
            "--namespace",
            "/tls_robot",
        )
        line = bridge.stderr.readline()
        assert "mode client" in line and f"tls/127.0.0.1:{port}" in line, line
        key = rmw.topic_key(
            0,
            "/tls_robot/joint_states",
            "sensor_msgs/msg/JointState",
            type_hash("sensor_msgs/msg/JointState"),
        )
        got: list[bytes] = []
        with zenoh.open(zenoh.Config.from_file(str(d / "client.json5"))) as session:
            sub = session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
            assert wait_for(lambda: len(got) >= 3, 30), "no /joint_states over TLS"
            sub.undeclare()
        m = ros2.codec("sensor_msgs/msg/JointState").decode(got[-1])
        assert list(m.name)[:2] == ["segment_1/kappa", "segment_1/phi"]

        # the same configuration without the CA: the TLS handshake fails, nothing joins
        probe = (
            "import sys, zenoh\n"
            "c = zenoh.Config.from_file(sys.argv[1])\n"
            "c.insert_json5('transport/link/tls/root_ca_certificate', 'null')\n"
            "c.insert_json5('connect/timeout_ms', '{router: -1, peer: -1, client: 3000}')\n"
            "try:\n    zenoh.open(c)\nexcept Exception as e:\n    print('refused', e)\n"
            "else:\n    print('joined')\n"
        )
        out = subprocess.run(
            [sys.executable, "-c", probe, str(d / "client.json5")],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
        )
        assert out.stdout.startswith("refused"), out.stdout + out.stderr[-1000:]
    finally:
        if bridge is not None:
            code, _, err = stop(bridge)
            assert code == 0, err[-2000:]
        stop(router)
        time.sleep(0.1)
