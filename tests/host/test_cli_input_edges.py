"""Client CLI inputs a new user tried (review of 2026-11-27): each gave a Python traceback, moved
the robot to a meaningless angle, or silently dropped part of a file. Every one is now a
one-line error; a command line that cannot work is exit 2, a file with a problem exit 1."""

from __future__ import annotations

import socket
import threading

import pytest

from tools.cli import main as ucr

pytestmark = pytest.mark.timeout(60)

from daemon_helpers import free_url  # noqa: E402


def run(capsys, *argv) -> tuple[int, str, str]:
    try:
        rc = ucr(list(argv))
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def one_line(err: str) -> bool:
    return err.count("\n") == 1 and err.startswith("ucr") and "Traceback" not in err


# ------------------------------------------------------------------ trajectory files
@pytest.mark.parametrize(
    "text,message",
    [
        ("  - t: 1\n    segments: {segment_1: {kappa: 0.5, phi_deg: .inf}}\n", "within ±360"),
        ("  - t: 1\n    segments: {segment_1: {kappa: 0.5, phi_deg: 1e308}}\n", "within ±360"),
        ("  - t: 1\n    segments: {segment_1: {kappa: 0.5, phi_deg: 400}}\n", "got 400"),
    ],
)
def test_a_phi_deg_that_names_no_plane_is_refused_not_a_traceback_or_a_wrapped_angle(
    capsys, tmp_path, text, message
):
    f = tmp_path / "t.yaml"
    f.write_text("waypoints:\n" + text)
    rc, out, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 1 and out == "" and one_line(err), err
    assert f"{f}:2: waypoint 1: segment_1: phi_deg must be a number of degrees" in err
    assert message in err


def test_a_file_that_is_not_utf8_is_one_line(capsys, tmp_path):
    f = tmp_path / "bin.yaml"
    f.write_bytes(b"\xff\xfe\x00bad")
    rc, _, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 1 and one_line(err), err
    assert "not UTF-8 text (byte 0xff at offset 0)" in err


@pytest.mark.parametrize(
    "name,text,where",
    [
        ("dup.yaml", "- t: 1\n  segments: {segment_1: {kappa: 1, phi: 1, phi: 2}}\n", ":2:"),
        ("dup2.yaml", "- t: 1\n  t: 2\n  segments: {segment_1: {kappa: 1}}\n", ":2:"),
        (
            "dup.json",
            '{"waypoints": [], "waypoints": [{"t": 1, "segments": {"segment_1": {"kappa": 1}}}]}',
            "",
        ),
    ],
)
def test_a_key_given_twice_in_a_file_is_refused_never_the_last_one_wins(
    capsys, tmp_path, name, text, where
):
    f = tmp_path / name
    f.write_text(text)
    rc, out, err = run(capsys, "trajectory", str(f), "--check")
    assert rc == 1 and out == "" and one_line(err), err
    assert "duplicate key" in err and f"{f}{where}" in err


def test_a_yaml_merge_key_still_overrides_as_yaml_says():
    from host.yamlload import safe_load

    doc = safe_load("base: &b {kappa: 1, phi: 2}\nseg: {<<: *b, phi: 3}\n")
    assert doc["seg"] == {"kappa": 1, "phi": 3}


# ------------------------------------------------------------------ the command line
@pytest.mark.parametrize(
    "url,message",
    [
        ("ws://127.0.0.1:99999", "Port out of range"),
        ("ws://127.0.0.1:abc", "Port could not be cast"),
        ("ws://[::1", "Invalid IPv6 URL"),
        ("foo", "give ws://HOST:PORT"),
        ("http://127.0.0.1:8765", "give ws://HOST:PORT"),
        ("ws://:8765", "no host"),
        ("", "--url is empty"),
    ],
)
def test_a_url_that_cannot_name_a_daemon_is_a_usage_error(capsys, url, message):
    rc, _, err = run(capsys, "status", "--url", url)
    assert rc == 2 and one_line(err) and message in err, err


def test_impossible_option_values_are_usage_errors_before_anything_moves(capsys):
    url = free_url()  # nothing listens: a value that got through would say so instead
    cases = [
        (["status", "--timeout", "1e10"], "must be <= 86400 s"),
        (["move", "--segment", "s1", "--kappa", "1", "--phi", "1e308"], "within ±360"),
        (["move", "--segment", "s1", "--kappa", "1", "--duration", "1e9"], "<= 604800 s"),
        (["watch", "--rate", "0.05"], "[0.1, 1000] lines/s"),
        (["status", "--token", "abcdefghijklmnopq"], "--token is refused"),
        (["status", "--ca", "/nonexistent/ca.pem"], "verifies a wss:// daemon"),
    ]
    for argv, message in cases:
        rc, out, err = run(capsys, *argv, "--url", url)
        assert rc == 2 and out == "" and message in err, (argv, err)
        assert "Traceback" not in err and "cannot reach" not in err, argv


def test_a_missing_ca_file_is_named_not_called_an_absent_daemon(capsys):
    url = free_url().replace("ws://", "wss://")
    rc, _, err = run(capsys, "status", "--url", url, "--ca", "/nonexistent/ca.pem")
    assert rc == 1 and one_line(err)
    assert "cannot load the CA file '/nonexistent/ca.pem'" in err and "running?" not in err


def test_a_short_token_in_the_environment_is_refused_as_in_a_token_file(capsys, monkeypatch):
    monkeypatch.delenv("UCR_TOKEN_FILE", raising=False)
    monkeypatch.setenv("UCR_TOKEN", "short")
    rc, _, err = run(capsys, "status", "--url", free_url())
    assert rc == 1 and one_line(err) and "$UCR_TOKEN: a token needs at least 16" in err


def test_a_server_that_never_answers_is_a_timeout_not_an_absent_daemon(capsys):
    """A port that accepts TCP but never completes the handshake (a loaded daemon, another
    program): said so, with the timeout, not "is `ucr daemon` running?"."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(srv.accept()[0])  # accepted, never answered
            except OSError:
                continue

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    try:
        url = f"ws://127.0.0.1:{srv.getsockname()[1]}"
        rc, _, err = run(capsys, "status", "--url", url, "--timeout", "0.5")
    finally:
        stop.set()
        t.join(2)
        for s in held:
            s.close()
        srv.close()
    assert rc == 1 and one_line(err), err
    assert f"no answer from {url} within 0.5 s" in err and "running?" not in err


def test_doctor_checks_its_options_before_the_chain(capsys, tmp_path):
    bad = tmp_path / "bad.ucrdf"
    bad.write_text("<robot")
    for argv, message in (
        (["--robot", "/nonexistent/robot.ucrdf"], "cannot read file"),
        (["--robot", str(bad)], f"{bad}:"),
    ):
        rc, out, err = run(capsys, "doctor", "--port", "loop://", "--seconds", "0", *argv)
        assert rc == 2 and out == "" and message in err and "Traceback" not in err, err
    rc, _, err = run(capsys, "doctor", "--port", "loop://", "--baud", "0")
    assert rc == 2 and "--baud: must be >= 1" in err


def test_the_daemons_config_file_refuses_a_key_given_twice_and_names_a_non_utf8_file(tmp_path):
    from host.config import ConfigError, load_config

    dup = tmp_path / "dup.yaml"
    dup.write_text("rate_hz: 100\nrate_hz: 50\n")
    with pytest.raises(ConfigError, match=r"line 2: invalid YAML: found duplicate key 'rate_hz'"):
        load_config(dup)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"\xff\xfe")
    with pytest.raises(ConfigError, match=r"bin.yaml.*not UTF-8 text \(byte 0xff at offset 0\)"):
        load_config(binary)


def test_an_http_server_that_is_no_daemon_is_not_called_a_daemon(capsys):
    """A URL at some other HTTP server answering 404 with an empty body said "the daemon at …
    refused the connection: " (an empty reason): it is no daemon (the daemon always says why)."""
    import http.server

    class NotFound(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"  # as any web server today (websockets wants 1.1)

        def do_GET(self):  # noqa: N802 - the stdlib's name
            self.send_response(404)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args):
            pass

    srv = http.server.HTTPServer(("127.0.0.1", 0), NotFound)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    try:
        url = f"ws://127.0.0.1:{srv.server_address[1]}"
        rc, _, err = run(capsys, "status", "--url", url)
    finally:
        srv.shutdown()
        srv.server_close()
    assert rc == 1 and one_line(err), err
    assert "answered HTTP 404 with no reason: not a ucr daemon's API" in err
    assert "the daemon at" not in err
