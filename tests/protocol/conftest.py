"""Shared fixtures: one batched MicroPython VM run for the whole protocol test area."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from protocol_testkit import load_vectors, make_streams, random_vectors, run_mp_job  # noqa: E402


@pytest.fixture(scope="session")
def mp_batch(tmp_path_factory):
    """One VM run: committed vectors, random messages, corrupted streams, random payloads."""
    rng = random.Random(20261121)
    job = {
        "vectors": load_vectors() + random_vectors(rng, 300),
        "streams": make_streams(7, 800),
        "payloads": [
            bytes(rng.randrange(256) for _ in range(rng.randrange(40))).hex() for _ in range(600)
        ]
        + [
            bytes([0xA2, 0x00, rng.randrange(256), 0x01, 0x80 | rng.randrange(32)]).hex()
            + bytes(rng.randrange(256) for _ in range(rng.randrange(20))).hex()
            for _ in range(200)
        ],
    }
    res = run_mp_job(job, tmp_path_factory.mktemp("mp"))
    return job, res


@pytest.fixture(scope="session")
def mp_batch_pure(mp_batch, tmp_path_factory):
    """The same job on the VM with the viper loops switched off."""
    job, _ = mp_batch
    return run_mp_job(job, tmp_path_factory.mktemp("mp_pure"), pure=True)
