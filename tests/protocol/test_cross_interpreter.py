"""CPython and the MicroPython VM produce identical bytes and identical reader behaviour."""

from __future__ import annotations

import cbor2
import mp_runner
from protocol_testkit import approx_equal


def test_random_messages_identical_bytes_on_both_interpreters(mp_batch) -> None:
    job, res = mp_batch
    mp = {r["name"]: r for r in res["vectors"]}
    randoms = [v for v in job["vectors"] if v["name"].startswith("random_")]
    assert len(randoms) >= 200
    for v in randoms:
        cp = mp_runner.run_vector(v)
        assert "error" not in cp, (v, cp)
        assert cp["hex"] == mp[v["name"]]["hex"], v["name"]
        if v["call"] == "cbor.dumps":
            assert cp["same"] and mp[v["name"]]["same"], v["name"]  # exact float round trip
            floats = mp_runner._arg(v["args"][0])
            assert bytes.fromhex(cp["hex"]) == cbor2.dumps(floats, canonical=True)
            continue
        assert approx_equal(cp["decoded"], mp[v["name"]]["decoded"]), v["name"]
        assert cp.get("device") == mp[v["name"]].get("device"), v["name"]


def test_random_messages_round_trip(mp_batch) -> None:
    """Decoded fields equal the encoded ones within the fixed-point quantum."""
    job, _ = mp_batch
    for v in job["vectors"]:
        if v["call"] != "encode_sync" or not v["name"].startswith("random_"):
            continue
        got = mp_runner.run_vector(v)
        sps = got["decoded"]["setpoints"]
        for sent, back in zip(v["args"][2], sps, strict=True):
            if sent is None:
                assert back is None
                continue
            assert abs(sent[0] - back[0]) <= 0.5e-4 + 1e-12
        # the device decoder returns the same ints for its own position as the host decoder
        for pos, (rc, _cycle, k, p, _resume) in enumerate(got["device"]):
            if pos < len(sps) and sps[pos] is not None:
                assert (
                    rc == 1 and k == round(sps[pos][0] * 10000) and p == round(sps[pos][1] * 10000)
                )
            else:
                assert rc == 0


def test_corrupted_streams_never_crash_and_resync_on_both(mp_batch) -> None:
    job, res = mp_batch
    cp_res = mp_runner.read_streams(job["streams"])
    for s, cp, mp in zip(job["streams"], cp_res, res["streams"], strict=True):
        for r, where in ((cp, "CPython"), (mp, "MicroPython")):
            assert r["raised"] is None, (where, r["raised"])
            # every frame handed out is one that was sent (CRC caught every corruption here)
            assert set(r["frames"]) <= set(s["sent"]), where
            # every untouched frame after an intact delimiter arrives (resynchronisation)
            for i in s["clean"]:
                assert s["sent"][i] in r["frames"], (where, i)
        assert cp == mp  # identical frames and counters on both interpreters


def test_random_payloads_never_raise_on_both(mp_batch) -> None:
    job, res = mp_batch
    cp = mp_runner.decode_payloads(job["payloads"])
    for a, b in zip(cp, res["payloads"], strict=True):
        assert not any(isinstance(x, str) and x.startswith("RAISED") for x in a), a
        assert a == b


def test_viper_loops_active_on_the_vm_and_equal_to_pure_loops(mp_batch, mp_batch_pure) -> None:
    """The machine-code CRC/COBS/collector give exactly the pure-Python results."""
    _, fast = mp_batch
    assert fast["fast"] is True
    assert mp_batch_pure["fast"] is False
    for key in ("vectors", "streams", "payloads"):
        assert fast[key] == mp_batch_pure[key], key
