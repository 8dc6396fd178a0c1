"""Why a serial port did not open, in one line a person can act on (docs/daemon.md, Serial ports).

pyserial reports ``[Errno 13] Permission denied``; on a Raspberry Pi the fix is nearly always the
same few things, so say them: the group that owns the device (``dialout``) and whether this user
is in it, the process that holds a busy port (from ``/proc/*/fd``, where this user may see it),
where the stable names are (``/dev/serial/by-id/``), how ``/dev/serial0`` is enabled.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import re
import stat
from pathlib import Path

#: The alias Raspberry Pi OS gives the UART on GPIO 14/15 (when enabled).
PI_UART_ALIAS = "/dev/serial0"
BY_ID = "/dev/serial/by-id"


def _is_path(url: str) -> bool:
    return "://" not in url


def _user() -> str:
    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return f"uid {os.geteuid()}"


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return f"gid {gid}"


def holders(
    path: str, proc: Path = Path("/proc"), device_ends: list[tuple[int, str]] | None = None
) -> list[tuple[int, str]]:
    """(pid, command name) of the other processes that have ``path`` open, as far as this user
    can see them (another user's /proc/PID/fd is unreadable without privileges). A process with
    the pty's master is the device's end, not a competitor: it goes to ``device_ends`` if given
    (an emulator; a daemon running in its process, as ``ucr demo``'s, is hidden behind it)."""
    try:
        target = os.path.realpath(path)
    except OSError:
        return []
    pts = re.fullmatch(r"/dev/pts/(\d+)", target)
    found = []
    me = os.getpid()
    for entry in proc.iterdir() if proc.is_dir() else []:
        if not entry.name.isdigit() or int(entry.name) == me:
            continue
        try:
            fds = list((entry / "fd").iterdir())
        except OSError:
            continue
        holds = master = False
        for fd in fds:
            try:
                link = os.readlink(fd)
                if link == target:
                    holds = True
                elif pts and link in ("/dev/ptmx", "/dev/pts/ptmx"):
                    info = (entry / "fdinfo" / fd.name).read_text()
                    master = master or f"tty-index:\t{pts.group(1)}\n" in info + "\n"
            except OSError:
                continue
        # the process with the pty's master is its other end (`ucr emulate`: the emulated
        # segment, as a board is a USB port's), not a program competing for the port
        if holds:
            try:
                comm = (entry / "comm").read_text().strip()
            except OSError:
                continue
            if not master:
                found.append((int(entry.name), comm))
            elif device_ends is not None:
                device_ends.append((int(entry.name), comm))
    return sorted(found)


def _permission(path: str) -> str:
    """Advice for EACCES: the owning group, and whether (and since when) this user is in it."""
    try:
        st = os.stat(path)
    except OSError:
        return "permission denied"
    group = _group_name(st.st_gid)
    user = _user()
    members = set()
    try:
        members = set(grp.getgrgid(st.st_gid).gr_mem)
    except KeyError:
        pass
    if st.st_gid in os.getgroups() or st.st_gid == os.getegid():
        return (
            f"permission denied although this process is in the group '{group}' that owns it "
            f"(mode {st.st_mode & 0o777:o}: does the group have rw?)"
        )
    if user in members:
        return (
            f"permission denied: the user '{user}' was added to the group '{group}' that owns "
            "it after this process started (log in again, or restart the service)"
        )
    return (
        f"permission denied: the user '{user}' is not in the group '{group}' that owns it "
        f"(sudo usermod -aG {group} {user}, then log in again or restart the service)"
    )


def _busy(path: str) -> str:
    ends: list[tuple[int, str]] = []
    held = holders(path, device_ends=ends)
    if held:
        names = ", ".join(f"PID {pid} ({comm})" for pid, comm in held)
        return f"busy: held by {names}; stop it, then retry"
    if ends:  # e.g. `ucr demo`: its emulator and its daemon are one process
        names = ", ".join(f"PID {pid} ({comm})" for pid, comm in sorted(ends))
        return (
            f"busy: held inside {names}, the process that emulates this port (its own daemon, "
            "e.g. `ucr demo`'s, uses it); stop that daemon or talk to it through its API"
        )
    return (
        "busy: another process holds it, not one this user can see "
        f"(sudo fuser -v {path}; on a Pi often a serial console: raspi-config, Serial Port)"
    )


def _missing(path: str) -> str:
    if path == PI_UART_ALIAS:
        return (
            "does not exist: the Pi's UART is not enabled (raspi-config → Interface Options → "
            "Serial Port: login shell no, hardware yes; or enable_uart=1 in config.txt)"
        )
    stable = sorted(os.listdir(BY_ID)) if os.path.isdir(BY_ID) else []
    where = f"present: {', '.join(BY_ID + '/' + n for n in stable)}" if stable else "none present"
    return f"does not exist (adapter plugged in? stable names under {BY_ID}/: {where})"


def _is_char_device(path: str) -> bool:
    """True if ``path`` is a character device, or cannot be judged (missing, unreadable)."""
    try:
        return stat.S_ISCHR(os.stat(path).st_mode)
    except OSError:
        return True  # (missing or unreadable: errno says more)


def describe_open_error(url: str, exc: BaseException) -> str:
    """One line saying why ``url`` did not open and what to do (``exc`` from pyserial/OS)."""
    code = getattr(exc, "errno", None)
    if _is_path(url) and not _is_char_device(url):  # pyserial's termios ioctl fails on it
        return (
            f"cannot open chain port {url!r}: not a serial port (not a character device); "
            "give the serial device of the chain with --port, e.g. /dev/ttyUSB0"
        )
    if not _is_path(url) or code is None:
        return f"cannot open chain port {url!r}: {exc}"
    if code == errno.ENOENT:
        why = _missing(url)
    elif code == errno.EACCES:
        why = _permission(url)
    elif code == errno.EPERM:
        why = (
            "operation not permitted (a sandbox refused it: under systemd the unit's "
            "DeviceAllow= must list this device's class, e.g. char-ttyUSB rw)"
        )
    elif code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK):
        why = _busy(url)
    else:
        why = str(exc)
    real = os.path.realpath(url)
    shown = url if real == url else f"{url} (→ {real})"
    return f"cannot open chain port {shown}: {why}"


def access_problem(
    path: str, *, uid: int | None = None, groups: set[int] | None = None
) -> tuple[str, str] | None:
    """Why this user cannot use the serial device ``path``, judged by its mode bits (not by
    being root: ``uid``/``groups`` default to this process's), as (problem, fix); None if it
    can. pyserial URLs are not device files: None. ``ucr doctor`` asks this before opening."""
    if not _is_path(path):
        return None
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return (
            f"{path} {_missing(path)}",
            (
                "plug in the USB serial adapter of the chain; `ls /dev/ttyUSB* /dev/ttyACM*` "
                "lists the candidates; give the right one with --port"
            ),
        )
    except OSError as exc:
        return f"{path}: {exc.strerror}", "check the path given to --port"
    if not stat.S_ISCHR(st.st_mode):
        return (
            f"{path} is not a character device (a serial port)",
            "give the serial device of the chain with --port, e.g. /dev/ttyUSB0",
        )
    uid = os.geteuid() if uid is None else uid
    groups = (set(os.getgroups()) | {os.getegid()}) if groups is None else groups
    if uid == 0:
        return None
    if st.st_uid == uid:
        bits = stat.S_IRUSR | stat.S_IWUSR
    elif st.st_gid in groups:
        bits = stat.S_IRGRP | stat.S_IWGRP
    else:
        bits = stat.S_IROTH | stat.S_IWOTH
    if st.st_mode & bits == bits:
        return None
    group = _group_name(st.st_gid)
    return (
        f"no permission to read and write {path} (group {group}, mode {stat.filemode(st.st_mode)})",
        f"add yourself to the group: `sudo usermod -aG {group} $USER`, then log out and in",
    )
