"""A segment flashed with another protocol version is refused at discovery with a message that
says to reflash it (docs/protocol.md section 10), and the descriptor announces the version."""

from __future__ import annotations

import io
import shutil
import subprocess
import tarfile
import time
from pathlib import Path

import pytest

from host.link import LinkError, ProtocolVersionError
from protocol import constants as C
from tests.chain.chain_helpers import chain_and_link, protocol_speaking, wait_discover

REPO = Path(__file__).resolve().parents[2]


def test_segment_speaking_another_protocol_version_is_refused_with_reflash_message(
    tmp_path: Path,
) -> None:
    other = C.VERSION_MAX + 1
    with chain_and_link(1, protocol_dir=protocol_speaking(tmp_path, other)) as (_chain, link):
        end = time.monotonic() + 30.0
        refusal: ProtocolVersionError | None = None
        while refusal is None and time.monotonic() < end:
            try:
                link.discover(timeout=1.0)
            except ProtocolVersionError as exc:
                refusal = exc
            except LinkError:
                time.sleep(0.1)  # still booting
        assert refusal is not None, "the segment was never refused"
        assert refusal.position == 0
        assert "ucr flash" in str(refusal)
        assert f"{other}..{other}" in str(refusal)


def test_descriptor_announces_the_protocol_version() -> None:
    with chain_and_link(1) as (_chain, link):
        (desc,) = wait_discover(link, 1)
        assert desc["protocol_version"] == C.VERSION


#: the last commit whose firmware speaks protocol version 1 (before the packed SYNC and STATE)
V1_COMMIT = "7f6dd50"


def _v1_firmware(tmp_path: Path) -> tuple[Path, Path] | None:
    """device/ and protocol/ of the last version-1 firmware, from this repository's history."""
    out = tmp_path / "v1"
    out.mkdir()
    git = shutil.which("git")
    if git is None:
        return None
    try:
        archive = subprocess.run(
            [git, "-C", str(REPO), "archive", V1_COMMIT, "device", "protocol"],
            capture_output=True,
            check=True,
            timeout=60,
        ).stdout
    except (subprocess.SubprocessError, OSError):
        return None
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(out, filter="data")
    return out / "device", out / "protocol"


def test_a_version_1_segment_is_refused_with_the_reflash_message(tmp_path: Path) -> None:
    """The real firmware of protocol version 1 (git history) on the emulated chain: this host
    (version 2) refuses it at discovery and says to reflash it; nothing is commanded."""
    v1 = _v1_firmware(tmp_path)
    if v1 is None:
        pytest.skip(f"git history with commit {V1_COMMIT} is not available (shallow checkout?)")
    device, protocol = v1
    with chain_and_link(1, firmware_dir=device, protocol_dir=protocol) as (_chain, link):
        end = time.monotonic() + 30.0
        refusal: ProtocolVersionError | None = None
        while refusal is None and time.monotonic() < end:
            try:
                link.discover(timeout=1.0)
            except ProtocolVersionError as exc:
                refusal = exc
            except LinkError:
                time.sleep(0.1)  # still booting
        assert refusal is not None, "the version-1 segment was never refused"
        assert refusal.position == 0
        assert "ucr flash" in str(refusal) and "version 1" in str(refusal)
