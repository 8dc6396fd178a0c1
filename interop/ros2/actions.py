"""ROS 2 action definitions (``action/<package>/<Action>.action``: goal, result and feedback
separated by ``---``; published text, comments left out) and the messages and services rosidl
generates from them, which is what travels on the wire and what the type hashes describe:

- ``A_Goal``, ``A_Result``, ``A_Feedback`` (the three parts);
- ``A_SendGoal`` service: request ``unique_identifier_msgs/UUID goal_id, A_Goal goal``, response
  ``bool accepted, builtin_interfaces/Time stamp``;
- ``A_GetResult`` service: request ``UUID goal_id``, response ``int8 status, A_Result result``;
- ``A_FeedbackMessage``: ``UUID goal_id, A_Feedback feedback``;
- the action type ``A``: ``goal, result, feedback, send_goal_service, get_result_service,
  feedback_message``.

Names are ``pkg/action/A_…``; the CDR codecs here use the same definitions.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from interop import ros2

ACTION_DIR = Path(__file__).resolve().parent / "action"
UUID = "unique_identifier_msgs/UUID"


class UnknownActionType(LookupError):
    """An action type for which ucr ships no definition."""


def split_name(action: str) -> tuple[str, str]:
    parts = action.split("/")
    if len(parts) == 3 and parts[1] == "action":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise UnknownActionType(f"not a ROS 2 action type name: {action!r}")


def full_name(action: str) -> str:
    pkg, name = split_name(action)
    return f"{pkg}/action/{name}"


@cache
def action_text(action: str) -> tuple[str, str, str]:
    """Goal, result and feedback definitions of a shipped action."""
    pkg, name = split_name(action)
    path = ACTION_DIR / pkg / f"{name}.action"
    if not path.is_file():
        raise UnknownActionType(f"no ROS 2 definition shipped for {action!r}")
    lines = path.read_text(encoding="utf-8").splitlines()
    seps = [i for i, ln in enumerate(lines) if ln.strip() == "---"]
    if len(seps) != 2:
        raise UnknownActionType(f"{path}: an .action needs exactly two '---' lines")
    parts = (lines[: seps[0]], lines[seps[0] + 1 : seps[1]], lines[seps[1] + 1 :])
    from interop.ros2.services import qualify  # noqa: PLC0415

    out = [qualify("\n".join(p).strip(), pkg) for p in parts]
    return tuple(t + "\n" if t else "" for t in out)  # type: ignore[return-value]


def shipped_actions() -> list[str]:
    return sorted(
        f"{p.parent.name}/action/{p.stem}" for p in ACTION_DIR.glob("*/*.action") if p.is_file()
    )


@cache
def generated(action: str) -> dict[str, str]:
    """Every message rosidl generates for ``action`` (services as request/response messages,
    without the service types themselves): ``{pkg/action/Name: .msg text}``."""
    base = full_name(action)
    goal, result, feedback = action_text(base)
    return {
        f"{base}_Goal": goal,
        f"{base}_Result": result,
        f"{base}_Feedback": feedback,
        f"{base}_SendGoal_Request": f"{UUID} goal_id\n{base}_Goal goal\n",
        f"{base}_SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp\n",
        f"{base}_GetResult_Request": f"{UUID} goal_id\n",
        f"{base}_GetResult_Response": f"int8 status\n{base}_Result result\n",
        f"{base}_FeedbackMessage": f"{UUID} goal_id\n{base}_Feedback feedback\n",
    }


def action_type_text(action: str) -> str:
    base = full_name(action)
    return (
        f"{base}_Goal goal\n{base}_Result result\n{base}_Feedback feedback\n"
        f"{base}_SendGoal send_goal_service\n{base}_GetResult get_result_service\n"
        f"{base}_FeedbackMessage feedback_message\n"
    )


def _base_type(line: str) -> str | None:
    line = line.split("#", 1)[0].strip()
    if not line or "=" in line.split(None, 1)[-1]:
        return None
    base = line.split()[0].split("[")[0].split("<=")[0]
    return None if base in ros2.PRIMITIVES else base


def schema(name: str, texts: dict[str, str], pkg: str) -> str:
    """The ros2msg schema (root text, then each dependency once) of ``name``, whose definition
    and those of its generated siblings are in ``texts``; other types come from
    :mod:`interop.ros2`. Generated names are written ``pkg/NameWithoutUnderscores`` (mcap's
    parser takes only two-part names without ``_``; CDR does not depend on names)."""

    def short(full: str) -> str:
        p = full.split("/")
        return f"{p[0]}/{p[-1].replace('_', '')}"

    gen = {short(k): v for k, v in texts.items()}
    order: list[str] = []

    def text_of(dep: str) -> str:
        return gen[dep] if dep in gen else ros2.message_text(dep)

    def resolve(base: str, where: str) -> str:
        if base.count("/") == 2:
            return short(base)
        return ros2.short_name(base if "/" in base else f"{where.split('/', 1)[0]}/{base}")

    def rewrite(body: str, where: str) -> str:
        out = []
        for line in body.splitlines():
            base = _base_type(line)
            if base and base.count("/") == 2:
                line = line.replace(base, short(base), 1)
            out.append(line)
            if base:
                dep = resolve(base, where)
                if dep not in order:
                    order.append(dep)
                    visit(dep)
        return "\n".join(out)

    rewritten: dict[str, str] = {}

    def visit(dep: str) -> None:
        rewritten[dep] = rewrite(text_of(dep), dep)

    root = rewrite(texts[name] or "uint8 structure_needs_at_least_one_member\n", f"{pkg}/x")
    parts = [root.rstrip("\n")]
    for dep in order:
        body = rewritten[dep] or "uint8 structure_needs_at_least_one_member"
        parts.append(f"{'=' * 80}\nMSG: {dep}\n{body.rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


class ActionCodec(ros2.Codec):
    """CDR codec of one generated message of an action (``part``: ``SendGoal_Request``,
    ``SendGoal_Response``, ``GetResult_Request``, ``GetResult_Response``, ``FeedbackMessage``,
    ``Goal``, ``Result``, ``Feedback``)."""

    def __init__(self, action: str, part: str) -> None:  # noqa: D107 - no super(): other source
        from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic  # noqa: PLC0415

        base = full_name(action)
        texts = generated(base)
        full = f"{base}_{part}"
        if full not in texts:
            raise ValueError(f"{action} has no generated message {part!r}")
        pkg = base.split("/")[0]
        self.name = f"{pkg}/{base.split('/')[-1]}{part.replace('_', '')}"
        self.schema_text = schema(full, texts, pkg)
        self.type_name = full
        self._encode = serialize_dynamic(self.name, self.schema_text)[self.name]
        self._decode = generate_dynamic(self.name, self.schema_text)[self.name]


@cache
def codec(action: str, part: str) -> ActionCodec:
    return ActionCodec(action, part)
