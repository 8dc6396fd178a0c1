"""Executable documentation: every shell command and Python snippet in README.md and docs/*.md
runs in the test suite (Sybil collects the Markdown files; this file says how a block runs).

A fenced block runs by its language:
- ``sh``: every command line (``\\`` continues a line; ``# …`` after two spaces is a comment); a
  command ending in ``&`` runs in the background until the block ends, then gets Ctrl-C;
- ``console`` (or no language, when the block starts with ``$ ``): the lines that start with
  ``$ `` (the others are sample output);
- ``python``: the block, in one namespace per document (later blocks see earlier names).
Other languages (``text``, ``json``, ``yaml``, …) are not run, except as files (below).

An HTML comment right before a block says how it runs (``<!-- doc-test: … -->``):
- ``skip "reason"`` or ``hardware "reason"``: not run; the reason shows in the test report;
- ``daemon``: an emulated 3-segment robot runs under ``ucr daemon`` with its API; ``UCR_URL``
  points at it (one for the whole session);
- ``until=S``: each command runs until stopped: alive (or exited 0) after S seconds, then SIGINT,
  and it must exit cleanly;
- ``file=NAME``: the block's text is written to NAME in the working directory (e.g. a trajectory
  file a later command reads);
- ``expect=TEXT``: the block's combined output must contain TEXT;
- ``exit=N``: every command must exit with N (e.g. 1 for a documented failure);
- ``port=host`` / ``port=repl``: the hardware port ``/dev/ttyUSB0`` in the commands becomes the
  host port (``host``) or segment 1's REPL pty (``repl``) of an emulated 3-segment chain
  configured from ``robots/softrobot3.ucrdf``, started for this block alone;
- ``cwd=repo``: run in the repository itself (``./run.sh …``) instead of a scratch directory.
Commands run in a fresh working directory per document holding a copy of ``robots/`` (plus
``robots/my.ucrdf``, "your robot": softrobot3's description, which the emulated chains run) and
links to ``examples/``, ``docs/``, ``device/`` and ``protocol/``, with the project's environment
first on PATH. The suite's own command (``./run.sh test …``) runs with ``--collect-only`` inside
the suite, so it proves the command and the collection without running the suite twice.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent
_DIRECTIVE = re.compile(r"<!--\s*doc-test:\s*(?P<body>(?:(?!-->).)*?)\s*-->\s*\Z", re.S)
_TIMEOUT_S = 180.0  # one documented command, at most (the demo runs ~15 s)

try:  # Sybil is a test dependency; without it the docs are simply not collected
    from sybil import Sybil
    from sybil.parsers.markdown.lexers import FencedCodeBlockLexer
except ImportError:  # pragma: no cover - dev extra always installs it
    Sybil = None


def _directive(text_before: str) -> dict[str, str]:
    """The ``doc-test`` directive right before a block, as {key: value}."""
    m = _DIRECTIVE.search(text_before)
    if m is None:
        return {}
    out: dict[str, str] = {}
    for token in shlex.split(m.group("body")):
        key, _, value = token.partition("=")
        out[key] = value
    body = m.group("body")
    for key in ("skip", "hardware"):
        if body.startswith(key):
            out[key] = body[len(key) :].strip().strip('"') or key
    return out


def _commands(source: str, console: bool) -> list[str]:
    """Command lines of a shell block (comments stripped, continuations joined)."""
    cmds: list[str] = []
    pending = ""
    for raw in source.splitlines():
        line = raw.rstrip()
        if console and not pending:
            if not line.startswith("$ "):
                continue
            line = line[2:]
        if pending:
            line = pending + " " + line.strip()
            pending = ""
        if line.endswith("\\"):
            pending = line[:-1].rstrip()
            continue
        line = re.split(r"\s{2,}#", line, maxsplit=1)[0].strip()
        if line and not line.startswith("#"):
            cmds.append(line)
    return cmds


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DocEnv:
    """What the documented commands run in: a working directory per document, the project's
    environment on PATH, and (on demand) an emulated robot under ``ucr daemon``."""

    def __init__(self, root: Path):
        self.root = root
        self._chain = None
        self._daemon: subprocess.Popen | None = None
        self.url: str | None = None

    def workdir(self, doc: Path) -> Path:
        d = self.root / doc.stem
        if not d.exists():
            d.mkdir(parents=True)
            # robots/ is a copy: documented commands write robot files (calibrate, adopt)
            shutil.copytree(REPO / "robots", d / "robots")
            # robots/my.ucrdf, "your robot" of docs/commissioning.md: the emulated chain's robot
            shutil.copy(REPO / "robots" / "softrobot3.ucrdf", d / "robots" / "my.ucrdf")
            for name in ("docs", "examples", "device", "protocol"):
                (d / name).symlink_to(REPO / name)
        return d

    def env(self, daemon: bool) -> dict[str, str]:
        env = dict(os.environ)
        env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
        env["PYTHONUNBUFFERED"] = "1"
        env.pop("UCR_URL", None)
        env.pop("UCR_TOKEN", None)
        if daemon:
            env["UCR_URL"] = self.start_daemon()
        return env

    def start_daemon(self) -> str:
        if self.url is not None:
            return self.url
        robot_file = REPO / "robots" / "softrobot3.ucrdf"
        self._chain = emulated_chain()
        port = _free_port()
        cfg = self.root / "daemon.yaml"
        cfg.write_text(f"api:\n  port: {port}\n")
        self._daemon = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", "daemon", "--robot", str(robot_file),
             "--port", self._chain.host_port, "--config", str(cfg)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        lines = []
        end = time.monotonic() + 60
        while time.monotonic() < end:
            line = self._daemon.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "API listening" in line or "daemon running" in line:
                break
        if self._daemon.poll() is not None:
            raise RuntimeError("ucr daemon did not start:\n" + "".join(lines))
        self.url = f"ws://127.0.0.1:{port}"
        # wait until the API answers
        from host.api.client import connect  # noqa: PLC0415

        end = time.monotonic() + 30
        while True:
            try:
                with connect(self.url) as c:
                    if len(c.status()["segments"]) == 3:
                        break
            except Exception:  # noqa: BLE001 - not up yet
                if time.monotonic() > end:
                    raise
            time.sleep(0.2)
        return self.url

    def close(self) -> None:
        if self._daemon is not None:
            self._daemon.send_signal(signal.SIGTERM)
            try:
                self._daemon.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                self._daemon.kill()
                self._daemon.communicate()
        if self._chain is not None:
            self._chain.close()


def emulated_chain():
    """An emulated 3-segment chain configured from robots/softrobot3.ucrdf, booted."""
    from host.link import ChainLink  # noqa: PLC0415
    from tools.emulator import EmulatedChain  # noqa: PLC0415
    from tools.segment_config import config_for  # noqa: PLC0415
    from ucrdf.parser import load  # noqa: PLC0415

    robot = load(REPO / "robots" / "softrobot3.ucrdf")
    names = list(robot.bendables)
    chain = EmulatedChain(3, config_for=lambda k: config_for(robot, names[k]))
    # what a reader has before typing the command: every segment booted and answering
    with ChainLink(chain.host_port) as link:
        end = time.monotonic() + 60
        while len(link.discover(timeout=0.5)) < 3:
            if time.monotonic() > end:
                chain.close()
                raise RuntimeError("the emulated chain did not boot 3 segments in 60 s")
    return chain


@pytest.fixture(scope="session")
def docenv():
    with tempfile.TemporaryDirectory(prefix="ucr-docs-") as tmp:
        env = DocEnv(Path(tmp))
        try:
            yield env
        finally:
            env.close()


def _run(cmd: str, cwd: Path, env: dict[str, str], until: float | None, exit_code: int = 0) -> str:
    """Runs one documented command; returns its output or raises AssertionError."""
    if re.match(r"(\./)?run\.sh test\b", cmd):  # the suite itself: prove it collects
        cmd = cmd + " --collect-only -q"
    proc = _popen(cmd, cwd, env)
    try:
        if until is None:
            out, _ = proc.communicate(timeout=_TIMEOUT_S)
        else:
            try:
                out, _ = proc.communicate(timeout=until)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGINT)
                out, _ = proc.communicate(timeout=30)
                if proc.returncode in (-signal.SIGINT, 130):
                    proc.returncode = 0
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        raise AssertionError(f"`{cmd}` did not finish:\n{out[-3000:]}") from None
    if proc.returncode != exit_code:
        raise AssertionError(
            f"`{cmd}` exited {proc.returncode} (documented: {exit_code}):\n{out[-3000:]}"
        )
    _no_traceback(cmd, out)
    return out


def _popen(cmd: str, cwd: Path, env: dict[str, str]) -> subprocess.Popen:
    """One documented command under bash, in a process group of its own (Ctrl-C reaches all)."""
    return subprocess.Popen(
        ["bash", "-c", cmd], cwd=cwd, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, start_new_session=True,
    )  # fmt: skip


def _no_traceback(cmd: str, out: str) -> None:
    if "Traceback (most recent call last)" in out:
        raise AssertionError(f"`{cmd}` printed a traceback:\n{out[-3000:]}")


def _start(cmd: str, cwd: Path, env: dict[str, str]) -> subprocess.Popen:
    """Starts a documented background command (``cmd &``) for the rest of its block."""
    proc = _popen(cmd, cwd, env)
    proc.cmd = cmd  # type: ignore[attr-defined]
    time.sleep(2.0)  # what a reader does: start it, then type the next command
    return proc


def _stop(proc: subprocess.Popen) -> str:
    """Stops a background command with Ctrl-C; it must still have been running and stop cleanly."""
    cmd = proc.cmd  # type: ignore[attr-defined]
    if proc.poll() is not None:
        out = proc.stdout.read() if proc.stdout else ""
        raise AssertionError(
            f"`{cmd} &` exited {proc.returncode} before its block ended:\n{out[-3000:]}"
        )
    os.killpg(proc.pid, signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        raise AssertionError(f"`{cmd} &` did not stop on Ctrl-C:\n{out[-3000:]}") from None
    if proc.returncode not in (0, 130, -signal.SIGINT):
        raise AssertionError(f"`{cmd} &` exited {proc.returncode} on Ctrl-C:\n{out[-3000:]}")
    _no_traceback(f"{cmd} &", out)
    return out


class _Block:
    def __init__(self, lang: str, source: str, directive: dict[str, str]):
        self.lang = lang
        self.source = source
        self.directive = directive

    def __call__(self, example) -> None:
        d = self.directive
        if "skip" in d or "hardware" in d:
            pytest.skip(d.get("hardware") or d["skip"])
        docenv: DocEnv = example.namespace["docenv"]
        cwd = REPO if d.get("cwd") == "repo" else docenv.workdir(Path(example.path))
        if "file" in d:
            (cwd / d["file"]).write_text(self.source)
            return
        env = docenv.env("daemon" in d)
        until = float(d["until"]) if "until" in d else None
        chain = emulated_chain() if "port" in d else None
        try:
            self._run(example, cwd, env, until, chain)
        finally:
            if chain is not None:
                chain.close()

    def _run(self, example, cwd: Path, env: dict[str, str], until, chain) -> None:
        d = self.directive
        source = self.source
        if chain is not None:
            port = chain.host_port if d["port"] == "host" else chain.repl_port(0)
            source = source.replace("/dev/ttyUSB0", port)
        if self.lang == "python":
            old = os.getcwd()
            saved = {k: os.environ.get(k) for k in ("UCR_URL", "UCR_TOKEN")}
            os.chdir(cwd)
            os.environ.update({k: env[k] for k in ("UCR_URL",) if k in env})
            try:
                code = compile("\n" * example.line + source, example.path, "exec")
                exec(code, example.namespace)
            finally:
                os.chdir(old)
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
            return
        cmds = _commands(source, self.lang == "console")
        exit_code = int(d.get("exit", "0"))
        background: list[subprocess.Popen] = []
        outs: list[str] = []
        try:
            for c in cmds:
                if c.endswith("&"):
                    background.append(_start(c[:-1].strip(), cwd, env))
                else:
                    outs.append(_run(c, cwd, env, until, exit_code))
        finally:
            for proc in background:
                outs.append(_stop(proc))
        if "expect" in d and not any(d["expect"] in o for o in outs):
            raise AssertionError(f"expected {d['expect']!r} in the output of the block")


class _DocParser:
    """Yields a region for every runnable block (and every ``file=`` block)."""

    def __init__(self):
        self.lexer = FencedCodeBlockLexer(
            language=r"[\w+-]*", mapping={"language": "language", "source": "source"}
        )

    def __call__(self, document):
        for region in self.lexer(document):
            lang = region.lexemes["language"]
            source = str(region.lexemes["source"])
            if not lang and source.lstrip().startswith("$ "):
                lang = "console"  # an unlabelled block of shell commands is run like one
            directive = _directive(document.text[: region.start])
            if lang not in ("sh", "console", "python") and "file" not in directive:
                continue
            region.parsed = _Block(lang, source, directive)
            region.evaluator = region.parsed
            yield region


if Sybil is not None:
    pytest_collect_file = Sybil(
        parsers=[_DocParser()],
        patterns=["README.md", "docs/*.md"],
        fixtures=["docenv"],
    ).pytest()


# -- where the suite's time goes, and which tests share the machine --------------------------------
# The guide's budget: the tests within 10 minutes on 2 cores, heavier end-to-end checks (a browser,
# the documentation's commands against emulated robots) within 10 more. Each run prints the split,
# so a test that grows a part shows in the next run's summary, not in a timed test.
#
# Most of a test's time is waiting on emulated segments, daemons and timeouts: a run in one process
# keeps about 0.6 of the 2 cores busy. So `./run.sh test` runs the suite in two phases:
# ``--ucr-phase=shared`` (two pytest-xdist workers, a file at a time each) and then
# ``--ucr-phase=alone`` (one process, as before) for what must have the machine to itself: the
# browser files, the documentation's commands (they use the documented default ports and one
# session daemon) and tests marked ``alone`` (they judge timing or CPU load). Without the option,
# pytest runs everything in one process.
_PARTS = ("tests", "browser tests", "documentation's commands")
_PART_KEY = {_PARTS[1]: "ucr_part_browser", _PARTS[2]: "ucr_part_docs"}
_PHASES = ("all", "shared", "alone")
_seconds = dict.fromkeys(_PARTS, 0.0)
_started = time.monotonic()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--ucr-phase",
        choices=_PHASES,
        default="all",
        help="shared: only tests that can share the machine with another worker; alone: only "
        "the others (browser, documentation's commands, tests marked alone); all: both",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "alone: judges timing or CPU load, so ./run.sh test runs it after the others, in one "
        "process (conftest.py)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def path(item: pytest.Item) -> str:
        return item.nodeid.split("::")[0]

    browser_files = {path(i) for i in items if "browser" in getattr(i, "fixturenames", ())}
    phase = config.getoption("--ucr-phase")
    keep, drop = [], []
    for item in items:
        p = path(item)
        if p.endswith(".md"):
            item.keywords[_PART_KEY[_PARTS[2]]] = True
        elif "browser" in getattr(item, "fixturenames", ()):
            item.keywords[_PART_KEY[_PARTS[1]]] = True
        alone = p.endswith(".md") or p in browser_files or item.get_closest_marker("alone")
        (keep if phase == "all" or (phase == "alone") == bool(alone) else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    part = next((p for p, k in _PART_KEY.items() if k in report.keywords), _PARTS[0])
    _seconds[part] += report.duration


def pytest_terminal_summary(terminalreporter) -> None:
    if sum(_seconds.values()) < 1.0:
        return
    config = terminalreporter.config
    split = ", ".join(f"{_seconds[p]:.0f} s {p}" for p in _PARTS)
    workers = getattr(config.option, "numprocesses", None) or 0
    where = f"{workers} workers" if workers else "one process"
    phase = config.getoption("--ucr-phase")
    terminalreporter.write_line(
        f"time by part: {split}"
        + (" (summed over the workers)" if workers else "")
        + f"; {time.monotonic() - _started:.0f} s wall in {where}"
        + ("" if phase == "all" else f" (phase {phase})")
        + "; the budget is wall time on 2 cores: 600 s for the tests, 1200 s with the other two"
    )
