"""`ucr zenoh` over Zenoh TLS on loopback: a router with a certificate from a test CA
(`ucr zenoh-router --zenoh-config`), the bridge in client mode trusting that CA
(`ucr zenoh --zenoh-config`), a subscriber with the CA receives /joint_states, one without it
cannot join. Mutual TLS as docs/ros2.md documents it (`enable_mtls`): a session without a
client certificate from the CA is refused, sessions with one join, and the router's access
control tells them apart by `cert_common_names`. Certificates are made here with the openssl
command."""

from __future__ import annotations

import json
import shutil
import signal
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
            assert code == 130, err[-2000:]  # Ctrl-C
        code, _, err = stop(router, signal.SIGTERM)
        assert code == 0, err[-2000:]  # a requested stop
        time.sleep(0.1)


ACL_KEYS = [  # docs/ros2.md's access control rule
    "*/**/jtc/joint_trajectory/**",
    "*/**/jtc/follow_joint_trajectory/**",
    "*/**/ucr/stop/**",
]


def _client_cert(d, cn: str) -> None:
    """A client certificate ``<cn>.pem`` / ``<cn>.key`` (P-256: quick to make) from the CA."""
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", f"{cn}.key", "-out", f"{cn}.csr", "-subj", f"/CN={cn}", cwd=d)  # fmt: skip
    (d / f"{cn}.cnf").write_text(
        "basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=clientAuth\n"
    )
    _openssl("x509", "-req", "-in", f"{cn}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", f"{cn}.pem", "-days", "2", "-extfile", f"{cn}.cnf",
             cwd=d)  # fmt: skip


def test_mutual_tls_refuses_sessions_without_a_certificate_and_acl_names_them(pki):
    """`enable_mtls` on the router: a session trusting the CA but without a client certificate
    cannot join; sessions with one do. The router's ACL denies the command key expressions to
    the certificate common name "viewer": its JointTrajectory is dropped, "operator"'s passes."""
    import zenoh

    d, _ = pki
    for cn in ("operator", "viewer"):
        _client_cert(d, cn)
    port = free_port()
    tls = {"listen_certificate": str(d / "router.pem"), "listen_private_key": str(d / "router.key"),
           "root_ca_certificate": str(d / "ca.pem"), "enable_mtls": True}  # fmt: skip
    router_conf = {
        "mode": "router",
        "listen": {"endpoints": [f"tls/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
        "access_control": {
            "enabled": True,
            "default_permission": "allow",
            "rules": [{"id": "no_commands", "permission": "deny", "flows": ["ingress"],
                       "messages": ["put", "query"], "key_exprs": ACL_KEYS}],
            "subjects": [{"id": "viewers", "cert_common_names": ["viewer"]}],
            "policies": [{"rules": ["no_commands"], "subjects": ["viewers"]}],
        },
    }  # fmt: skip

    def client(cn: str | None):
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
        conf.insert_json5("connect/timeout_ms", "{router: -1, peer: -1, client: 1500}")
        conf.insert_json5("scouting/multicast/enabled", "false")
        own = {"root_ca_certificate": str(d / "ca.pem")}  # TLS trusting the CA: it alone
        if cn:  # ... and a client certificate
            own |= {"enable_mtls": True, "connect_certificate": str(d / f"{cn}.pem"),
                    "connect_private_key": str(d / f"{cn}.key")}  # fmt: skip
        conf.insert_json5("transport/link/tls", json.dumps(own))
        return zenoh.open(conf)

    # the router in this process (the configuration `ucr zenoh-router --zenoh-config` would load,
    # as the test above runs it): one process fewer to start
    router = zenoh.open(zenoh.Config.from_json5(json.dumps(router_conf)))
    try:
        with pytest.raises(zenoh.ZError):  # no certificate: the handshake fails, nothing joins
            client(None).close()
        key = "0/mtls_robot/jtc/joint_trajectory/trajectory_msgs::msg::dds_::JointTrajectory_/x"
        got: list[bytes] = []
        with client("operator") as listener, client("operator") as op, client("viewer") as viewer:
            sub = listener.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))

            def both() -> bool:  # the viewer's first: it would arrive before the operator's
                viewer.put(key, b"viewer")
                op.put(key, b"operator")
                return b"operator" in got

            assert wait_for(both, 20, 0.3)
            time.sleep(0.3)
            assert set(got) == {b"operator"}, got
            sub.undeclare()
    finally:
        router.close()
