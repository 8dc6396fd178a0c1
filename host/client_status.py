"""Human lines for a daemon's status (``ucr status``): its state, link health, who holds a
manual takeover and the segments; the command itself is in :mod:`host.client_cli`."""

from __future__ import annotations

from typing import Any

from host.api.client_behalf import sender_words
from host.api.client_errors import ApiError
from host.client_common import deg, format_missing, kap


def format_link_health(st: dict) -> tuple[str, list[str]]:
    """The loop rate as the status line shows it, and the lines on a degraded link: which link,
    its loss, the exchange latency, usable versus nominal rate (docs/daemon.md "Degrade, don't
    stall"). Positions and links count from 1, as the daemon reports them."""
    health = st.get("link_health") or {}
    nominal = st.get("nominal_rate_hz", health.get("nominal_rate_hz", st.get("rate_hz", 0)))
    usable = health.get("usable_rate_hz", st.get("rate_hz", 0)) or 0
    if not health.get("degraded"):
        return f"loop: {usable:g} Hz", []
    rate = f"loop: {usable:g} Hz (slowed from {nominal:g} Hz: link degraded)"
    last = health.get("last_change") or {}
    link = last.get("link", last.get("position"))
    into = f" (into {last['segment']})" if last.get("segment") else ""
    where = f"link {link}{into}" if link is not None else "a link"
    loss = last.get("loss")
    lat = health.get("latency_ms_p90")
    lines = [
        f"link degraded: {where} is slow"
        + (f", {loss:.0%} missed" if isinstance(loss, int | float) else "")
        + (f" at {last['measured_at_hz']:g} Hz" if last.get("measured_at_hz") else "")
        + f"; loop at {usable:g} Hz of {nominal:g} Hz nominal",
    ]
    per = health.get("loss") or []
    if any(per) or lat is not None:
        shares = ", ".join(f"{i + 1}: {x:.0%}" for i, x in enumerate(per))  # 1-based
        lines.append(
            f"  loss per position (last 30 exchanges) {shares or '-'}; exchange latency p90 "
            + ("-" if lat is None else f"{lat:g} ms")
        )
    return rate, lines


def manual_senders(c: Any, st: dict) -> dict[str, str]:
    """Per manual controller holding a takeover: who sent its latest input, in words (its
    ``controllers.list`` entry's ``input_from``); asked only during a takeover."""
    manual = st.get("manual_control") or []
    if not manual or not isinstance(manual, list):
        return {}
    try:
        ctrls = c.controllers()
    except ApiError:  # not known this time: the status line says less
        return {}
    return {
        str(x.get("name")): sender_words(x.get("input_from"))
        for x in (ctrls if isinstance(ctrls, list) else [])
        if isinstance(x, dict) and x.get("name") in manual and sender_words(x.get("input_from"))
    }


#: a status older than this (s; the daemon sends one every 50 ms) is said to be old
STALE_STATUS_S = 1.0


def format_status(
    st: dict, topo: dict | None = None, senders: dict[str, str] | None = None
) -> list[str]:
    """Human lines for a daemon status; ``topo`` (the daemon's topology, if known) adds the
    segments of the description that are missing and where the chain is cut; ``senders``
    (:func:`manual_senders`) who drives each manual controller."""
    rate, degraded = format_link_health(st)
    lines = [
        (
            f"daemon: {st.get('state')}  robot: {st.get('robot')}  port: {st.get('port')}  "
            f"{rate}  up {st.get('uptime_s', 0):.0f} s"
        ),
        *degraded,
    ]
    age = st.get("status_age_s")
    if isinstance(age, int | float) and age > STALE_STATUS_S:
        lines.append(
            f"  this status is {age:.1f} s old: the daemon has sent none since (its process is "
            "frozen or its control loop holds it up); what follows is how it was then"
        )
    if st.get("error"):
        lines.append(f"  error: {st['error']}")
    lines.append(
        f"hardware interface: {st.get('hwi')}  controllers: "
        f"{', '.join(st.get('active_controllers') or []) or 'none'}"
    )
    if st.get("manual_control"):
        lines.append(
            f"manual control: {', '.join(map(str, st['manual_control']))} (`ucr controllers "
            "hand-back` to return to trajectories)"
        )
        for name, who in (senders or {}).items():
            lines.append(f"  {name}: latest input from {who}")
    if st.get("running_goals"):
        lines.append(f"running goals: {', '.join(map(str, st['running_goals']))}")
    js = st.get("joint_states") or {}
    expected = topo.get("expected") if isinstance(topo, dict) else None
    of = f" of {len(expected)}" if isinstance(expected, list) and len(expected) != len(js) else ""
    lines.append(f"segments ({len(js)}{of}):")
    faults = st.get("faults") or {}
    for name, j in js.items():
        flag = "" if j.get("valid", True) else "  (no answer)"
        if name in faults:
            f = faults[name]
            flag += f"  FAULT {f.get('name')}: {f.get('text') or '?'}"
        lines.append(
            f"  {name:<16} kappa {kap(j.get('kappa'))} 1/m   phi {deg(j.get('phi'))}{flag}"
        )
    lines.extend(format_missing(topo))
    if faults:
        lines.append(
            f"{len(faults)} segment(s) in FAULT, holding: `ucr clear-fault [SEGMENT]` clears it "
            "once the cause is understood"
        )
    return lines
