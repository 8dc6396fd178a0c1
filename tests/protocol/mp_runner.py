# ruff: noqa: UP031 - kept in the MicroPython/CPython common subset on purpose
"""Runs protocol checks on whichever interpreter imports it (CPython or the MicroPython VM).

Written in the common subset on purpose: the tests run the very same functions under both
interpreters and compare the JSON results. ``main(in_path, out_path)`` is the VM entry point.
"""

import json
import struct

from protocol import calibration as CAL
from protocol import cbor, cobs, crc
from protocol import device as D
from protocol import frame as F
from protocol import messages as M
from protocol import relay as RL
from protocol import relay_py as RLP

_FRAME_CALLS = {
    "encode_discover": M.encode_discover,
    "encode_sync": M.encode_sync,
    "encode_heartbeat": M.encode_heartbeat,
    "encode_param_get": M.encode_param_get,
    "encode_param_set": M.encode_param_set,
    "encode_hold": M.encode_hold,
    "encode_clear_fault": M.encode_clear_fault,
    "encode_alive": M.encode_alive,
    "encode_descriptor": M.encode_descriptor,
    "encode_state": M.encode_state,
    "encode_param_value": M.encode_param_value,
    "encode_event": M.encode_event,
    "encode_error": M.encode_error,
    "encode_version_error": M.encode_version_error,
    "encode_calibrate": CAL.encode_calibrate,
    "encode_calibration": CAL.encode_calibration,
}


def _hex(b):
    return "".join("%02x" % x for x in b)


def _unhex(s):
    return bytes(int(s[i : i + 2], 16) for i in range(0, len(s), 2))


def norm(v):
    """JSON-able form of a decoded value: sets sorted, tuples as lists, bytes as hex."""
    if isinstance(v, dict):
        out = {}
        for k in v:
            out[str(k)] = norm(v[k])
        return out
    if isinstance(v, (list, tuple)):
        return [norm(x) for x in v]
    if isinstance(v, set):
        return sorted(v)
    if isinstance(v, (bytes, bytearray)):
        return _hex(v)
    if isinstance(v, float) and (v != v or v - v != 0):
        return {"$float": "nan" if v != v else ("inf" if v > 0 else "-inf")}  # JSON has none
    return v


def _device_sync(wire, positions):
    """decode_sync for each position on the payload of ``wire``: [[rc, cycle, k, p, resume]]."""
    r = F.FrameReader()
    r.feed(b"")
    data = _unhex(wire) if isinstance(wire, str) else wire
    pos = r.scan(data, 0, len(data))
    if not r.ready or pos != len(data):
        return None
    out = [0, 0, 0, 0]
    res = []
    for p in positions:
        rc = D.decode_sync(r.raw, 5, r.payload_end, p, out)
        res.append([rc] + (out if rc >= 0 else [0, 0, 0, 0]))
    return res


def _arg(a):
    """JSON has no NaN/inf: {"$float": "nan" | "inf" | "-inf"} stands for them in vectors;
    {"$f64": "<16 hex digits>"} is an exact float64 bit pattern (no decimal parsing involved)."""
    if isinstance(a, dict):
        if "$float" in a:
            return float(a["$float"])
        if "$f64" in a:
            return struct.unpack(">d", _unhex(a["$f64"]))[0]
        out = {}
        for k in a:
            out[k] = _arg(a[k])
        return out
    if isinstance(a, list):
        return [_arg(x) for x in a]
    return a


def run_vector(v):
    """Execute one vector description; return {"name", "hex", "decoded"?, "device"?, "error"?}."""
    call = v["call"]
    args = _arg(v.get("args", []))
    kwargs = _arg(v.get("kwargs", {}))
    res = {"name": v["name"]}
    try:
        if call in _FRAME_CALLS:
            wire = _FRAME_CALLS[call](*args, **kwargs)
        elif call == "device.state_frame":
            raw = bytearray(250)
            out = bytearray(252)
            n = D.state_frame(raw, out, *args)
            wire = bytes(out[:n])
        elif call == "device.event_frame":
            raw = bytearray(250)
            out = bytearray(252)
            n = D.event_frame(raw, out, *args)
            wire = bytes(out[:n])
        elif call == "device.alive_frame":
            raw = bytearray(250)
            out = bytearray(252)
            n = D.alive_frame(raw, out, *args)
            wire = bytes(out[:n])
        elif call == "forward":
            fr = F.decode_frame(_unhex(args[0]))
            raw = bytearray(fr.raw())
            out = bytearray(252)
            n = F.forward_into(raw, len(raw), args[1], out, 0)
            wire = bytes(out[:n])
        elif call == "decode":
            wire = _unhex(args[0])
        elif call == "cbor.dumps":
            res["hex"] = _hex(cbor.dumps(args[0]))
            back = cbor.loads(cbor.dumps(args[0]))
            res["decoded"] = norm(back)
            res["same"] = back == args[0]
            return res
        elif call == "cobs.encode":
            enc = cobs.encode(_unhex(args[0]))
            res["hex"] = _hex(enc)
            res["decoded"] = _hex(cobs.decode(enc))
            return res
        elif call == "config_hash":
            res["hex"] = "%08x" % CAL.config_hash(args[0])
            res["decoded"] = CAL.config_text(args[0])
            return res
        elif call == "crc16":
            res["hex"] = "%04x" % crc.crc16(_unhex(args[0]))
            return res
        else:
            res["error"] = "unknown call " + call
            return res
    except ValueError as e:  # ProtocolError is a ValueError: expected for invalid input vectors
        res["error"] = type(e).__name__
        return res
    res["hex"] = _hex(wire)
    try:
        fr = F.decode_frame(wire)
    except ValueError as e:
        res["decoded"] = {"error": type(e).__name__}
        return res
    try:
        res["decoded"] = norm(M.decode_message(fr))
    except ValueError as e:
        res["decoded"] = {"error": type(e).__name__}
    if fr.mtype == 0x02:
        res["device"] = _device_sync(wire, v.get("positions", [0, 1, 2, 3]))
    return res


def read_streams(streams):
    """Feed each corrupted stream (hex, chunk sizes) through a fresh FrameReader.

    Returns per stream {"frames": [raw hex...], "stats": counters, "raised": text or None}.
    """
    results = []
    for s in streams:
        data = _unhex(s["hex"])
        chunks = s.get("chunks", [len(data) or 1])
        r = F.FrameReader()
        frames = []
        raised = None
        try:
            pos = 0
            ci = 0
            while pos < len(data):
                n = chunks[ci % len(chunks)]
                ci += 1
                for fr in r.feed(data[pos : pos + n]):
                    frames.append(_hex(fr.raw()))
                pos += n
            # also run the payload decoders on what came through: they must not raise
            for h in frames:
                raw = _unhex(h)
                pe = len(raw) - (2 if raw[0] == 1 else 3)  # version 1: no pad before the CRC
                fr = F.Frame(raw[0], raw[1], raw[2], raw[3], raw[4], raw[5:pe])
                try:
                    M.decode_message(fr)
                except ValueError:
                    pass
                D.decode_sync(raw, 5, pe, 1, [0, 0, 0, 0])
                D.decode_cycle(raw, 5, pe)
                D.decode_empty(raw, 5, pe)
        except Exception as e:  # noqa: BLE001 - the property under test is "never raises"
            raised = type(e).__name__ + ": " + str(e)
        results.append({"frames": frames, "stats": r.stats(), "raised": raised})
    return results


def decode_payloads(payloads):
    """Run every decoder on random payload bytes; return per payload the outcome names."""
    out = []
    for h in payloads:
        p = _unhex(h)
        res = []
        try:
            for t in (0x01, 0x02, 0x03, 0x04, 0x05, 0x81, 0x83, 0x84, 0x85, 0xFF, 0x42):
                try:
                    M.decode_message(F.Frame(1, 0, 0, t, 0, p))
                    res.append("ok")
                except ValueError as e:
                    res.append(type(e).__name__)
            res.append(D.decode_sync(p, 0, len(p), 2, [0, 0, 0, 0]))
            res.append(D.decode_cycle(p, 0, len(p)))
            res.append(D.decode_empty(p, 0, len(p)))
        except Exception as e:  # noqa: BLE001 - the property under test is "never raises"
            res.append("RAISED " + type(e).__name__ + ": " + str(e))
        out.append(res)
    return out


def use_pure_loops():
    """Switch off the viper loops (protocol/_fast.py) so the pure-Python ones run."""
    crc._fast_crc = None
    cobs._fast_enc = None
    cobs._fast_dec = None
    F._scan = F._scan_py
    RL._feed = RLP.feed
    D._sync_entry = None
    D._state_wire = None


def fast_loops_active():
    """True when the viper loops are in use (MicroPython with the viper emitter)."""
    return (
        crc._fast_crc is not None
        and cobs._fast_enc is not None
        and F._scan is not F._scan_py
        and RL._feed is not RLP.feed
        and D._sync_entry is not None
        and D._state_wire is not None
    )


def main(in_path, out_path, pure=False):
    """VM entry: read {"vectors", "streams", "payloads"} JSON, write the results as JSON."""
    if pure:
        use_pure_loops()
    with open(in_path) as f:
        job = json.load(f)
    res = {"fast": fast_loops_active()}
    if "vectors" in job:
        res["vectors"] = [run_vector(v) for v in job["vectors"]]
    if "streams" in job:
        res["streams"] = read_streams(job["streams"])
    if "payloads" in job:
        res["payloads"] = decode_payloads(job["payloads"])
    with open(out_path, "w") as f:
        json.dump(res, f)
