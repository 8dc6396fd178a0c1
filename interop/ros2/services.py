"""ROS 2 service definitions (``srv/<package>/<Service>.srv``, published Jazzy text, comments left
out) and the CDR codecs of their request and response, beside the message definitions of
:mod:`interop.ros2`. A ``.srv`` is a request and a response definition separated by ``---``;
rosidl makes each a message ``<pkg>/srv/<Service>_Request`` / ``_Response`` (an empty one gets
the member ``uint8 structure_needs_at_least_one_member``, which is also what goes on the wire).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from interop import ros2

SRV_DIR = Path(__file__).resolve().parent / "srv"
EMPTY_MEMBER = "uint8 structure_needs_at_least_one_member\n"


class UnknownServiceType(LookupError):
    """A service type for which ucr ships no definition."""


def split_name(srvtype: str) -> tuple[str, str]:
    """``std_srvs/srv/Trigger`` (or ``std_srvs/Trigger``) -> ``("std_srvs", "Trigger")``."""
    parts = srvtype.split("/")
    if len(parts) == 3 and parts[1] == "srv":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise UnknownServiceType(f"not a ROS 2 service type name: {srvtype!r}")


def full_name(srvtype: str) -> str:
    pkg, name = split_name(srvtype)
    return f"{pkg}/srv/{name}"


def qualify(text: str, pkg: str) -> str:
    """Field types without a package get ``pkg/`` (they name messages of the same package; left
    bare inside a ``pkg/srv/…`` or ``pkg/action/…`` type they would be looked up there)."""
    out = []
    for line in text.splitlines():
        code = line.split("#", 1)[0].strip()
        if code and "=" not in code.split(None, 1)[-1]:
            ftype = code.split()[0]
            base = ftype.split("[")[0].split("<=")[0]
            if "/" not in base and base not in ros2.PRIMITIVES and base != "Header":
                line = line.replace(ftype, f"{pkg}/{ftype}", 1)
            elif base == "Header":
                line = line.replace(ftype, "std_msgs/" + ftype, 1)
        out.append(line)
    return "\n".join(out) + ("\n" if text.endswith("\n") else "")


@cache
def service_text(srvtype: str) -> tuple[str, str]:
    """The request and response definitions of a shipped service (either may be empty)."""
    pkg, name = split_name(srvtype)
    path = SRV_DIR / pkg / f"{name}.srv"
    if not path.is_file():
        raise UnknownServiceType(f"no ROS 2 definition shipped for {srvtype!r}")
    lines = path.read_text(encoding="utf-8").splitlines()
    seps = [i for i, ln in enumerate(lines) if ln.strip() == "---"]
    if len(seps) != 1:
        raise UnknownServiceType(f"{path}: a .srv needs exactly one '---' line")
    req = "\n".join(lines[: seps[0]]).strip()
    resp = "\n".join(lines[seps[0] + 1 :]).strip()
    return (qualify(req, pkg) + "\n" if req else ""), (qualify(resp, pkg) + "\n" if resp else "")


def shipped_services() -> list[str]:
    """Every service with a definition here, as ``pkg/srv/Service``."""
    return sorted(f"{p.parent.name}/srv/{p.stem}" for p in SRV_DIR.glob("*/*.srv") if p.is_file())


class PartCodec(ros2.Codec):
    """CDR codec of a service's request or response (``part`` is ``Request`` or ``Response``);
    the definitions it uses from other packages come from :mod:`interop.ros2`."""

    def __init__(self, srvtype: str, part: str) -> None:  # noqa: D107 - no super(): other source
        from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic  # noqa: PLC0415

        if part not in ("Request", "Response"):
            raise ValueError(f"service part {part!r}: Request or Response")
        pkg, name = split_name(srvtype)
        req, resp = service_text(srvtype)
        text = (req if part == "Request" else resp) or EMPTY_MEMBER
        self.name = f"{pkg}/srv/{name}_{part}"
        self.schema_text = _with_dependencies(text, pkg)
        self._encode = serialize_dynamic(self.name, self.schema_text)[self.name]
        self._decode = generate_dynamic(self.name, self.schema_text)[self.name]


def _with_dependencies(text: str, pkg: str) -> str:
    """``text`` followed by every message it uses, in the ros2msg layout of
    :func:`interop.ros2.definition`."""
    deps: list[str] = []

    def visit(body: str) -> None:
        for line in body.splitlines():
            line = line.split("#", 1)[0].strip()
            if not line or "=" in line.split(None, 1)[-1]:
                continue
            base = line.split()[0].split("[")[0].split("<=")[0]
            if base in ros2.PRIMITIVES:
                continue
            dep = ros2.short_name(base if "/" in base else f"{pkg}/{base}")
            if dep not in deps:
                deps.append(dep)
                visit(ros2.message_text(dep))

    visit(text)
    parts = [text.rstrip("\n")]
    for dep in deps:
        parts.append(f"{'=' * 80}\nMSG: {dep}\n{ros2.message_text(dep).rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


@cache
def codecs(srvtype: str) -> tuple[PartCodec, PartCodec]:
    """The shared (request, response) codecs of a shipped service."""
    return PartCodec(srvtype, "Request"), PartCodec(srvtype, "Response")
