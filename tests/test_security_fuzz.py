"""Fuzz (issue 15): random, well-formed but wrong sample batches from a real ``WorkerLink``, through
a real relay, to a real ``Trainer`` that trains while they arrive. Seeded; bounded to about 30 s.

Every hostile batch is built from a genuine one and made wrong in one random way the schema must
catch (shape, dtype, structure, non-finite or out-of-range values, bad flags...). Genuine batches,
interleaved, carry numbered samples. At the end the trainer is alive, its memory holds exactly the
genuine samples, every hostile batch was counted, and the parameters are finite.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_security import (
    attacker,
    genuine_payload,
    make_trainer,
    params_finite,
    relay,
    sac_training,
    stored_firsts,
    wait_for,
)

pytestmark = pytest.mark.timeout(180)

BUDGET_S = float(os.environ.get("TMRL_FUZZ_SECONDS", "25"))


def _float_leaf(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.standard_normal((n, 3)).astype(np.float32)


def _mutations(rng: np.random.Generator) -> list:
    """Functions ``(payload) -> None`` that each make a genuine payload wrong for the schema."""

    def cols(p: dict) -> list:
        return p["cols"]

    def obs(p: dict) -> np.ndarray:
        return cols(p)[1][1]

    def n(p: dict) -> int:
        return p["n"]

    def shape(p: dict) -> None:
        extra = [(n(p), int(rng.integers(4, 9))), (n(p), 3, 2), (n(p),), (n(p), 0, 2**40), (n(p), 1)]
        cols(p)[1] = ("A", np.zeros(extra[int(rng.integers(len(extra)))], np.float32))
        if cols(p)[1][1].ndim == 1:
            cols(p)[1] = ("f", cols(p)[1][1])

    def dtype(p: dict) -> None:
        kinds = [np.complex64, np.int64, np.int8, np.uint8, np.bool_]
        cols(p)[1] = ("A", obs(p).astype(kinds[int(rng.integers(len(kinds)))]))

    def non_finite(p: dict) -> None:
        o = obs(p)
        o[int(rng.integers(n(p))), int(rng.integers(3))] = [np.nan, np.inf, -np.inf][int(rng.integers(3))]

    def overflow(p: dict) -> None:  # finite in float64, infinite in the float32 memory
        cols(p)[1] = ("A", obs(p).astype(np.float64) * 0 + 1e300)

    def reward(p: dict) -> None:
        bad = [np.nan, np.inf, -np.inf, 1e300][int(rng.integers(4))]
        r = np.zeros(n(p))
        r[int(rng.integers(n(p)))] = bad
        cols(p)[2] = ("F", r)

    def reward_kind(p: dict) -> None:
        cols(p)[2] = [("B", np.ones(n(p), bool)), ("A", np.zeros((n(p), 2))), ("R", ["x"] * n(p))][int(rng.integers(3))]

    def action(p: dict) -> None:
        known = cols(p)[0][2][1]
        k = int(rng.integers(len(known)))
        known[k, 0] = [np.nan, np.inf, 1.5, -3.0, 1e9][int(rng.integers(5))]

    def action_shape(p: dict) -> None:
        mask, known = cols(p)[0][1], cols(p)[0][2][1]
        cols(p)[0] = ("N", mask, ("A", np.zeros((len(known), int(rng.integers(2, 5))), np.float32)))

    def action_kind(p: dict) -> None:
        mask, known = cols(p)[0][1], cols(p)[0][2][1]
        cols(p)[0] = ("N", mask, ("A", known.astype([np.complex64, np.int32, np.bool_][int(rng.integers(3))])))

    def flags(p: dict) -> None:
        i = 3 + int(rng.integers(2))
        cols(p)[i] = [("F", np.full(n(p), 0.5)), ("I", np.full(n(p), 2)), ("R", ["yes"] * n(p))][int(rng.integers(3))]

    def structure(p: dict) -> None:
        o = obs(p)
        cols(p)[1] = [("T", [("A", o)]), ("T", [("A", o), ("A", o)]), ("D", ["x"], [("A", o)]),
                      ("0",), ("N", np.arange(n(p)) % 2 == 0, ("A", o[1::2])),
                      ("R", [None] * n(p)), ("R", [{"a": 1}] * n(p))][int(rng.integers(7))]

    def strings(p: dict) -> None:
        cols(p)[1] = ("R", [str(x) for x in range(n(p))])

    def ragged(p: dict) -> None:
        cols(p)[1] = ("R", [np.zeros(3 + (i % 2), np.float32) for i in range(n(p))])

    def header(p: dict) -> None:
        choice = int(rng.integers(5))
        if choice == 0:
            p["n"] = n(p) + 1
        elif choice == 1:
            p["cols"] = cols(p)[:5]
        elif choice == 2:
            p["v"] = 99
        elif choice == 3:
            p["src"] = "me"
        else:
            p["cols"] = ("R", ["junk"] * n(p))

    return [shape, dtype, non_finite, overflow, reward, reward_kind, action, action_shape, action_kind,
            flags, structure, strings, ragged, header]


def test_random_wrong_batches_never_reach_the_memory_or_the_parameters(tmp_path, port_factory):
    rng = np.random.default_rng(15)
    port = port_factory()
    server = relay(port)
    trainer = make_trainer(tmp_path, port, sac_training(memory_size=200_000))
    bad, good = attacker(port), attacker(port)
    try:
        run = trainer._load_or_create()
        iface = trainer.interface
        assert iface.wait_connected(30)
        mutations = _mutations(rng)
        sent = {"hostile": 0, "genuine_samples": 0, "seq": 0}
        used: set[str] = set()
        deadline = time.monotonic() + BUDGET_S

        def send() -> None:
            # Its own thread: a send blocks while the relay holds the senders back for the
            # trainer, which this test's main thread keeps consuming (one thread would deadlock).
            while time.monotonic() < deadline:
                for _ in range(20):
                    size = int(rng.integers(2, 40))
                    payload = genuine_payload(10**6 + sent["hostile"] * 100, size, src=666, seq=sent["hostile"])
                    mutate = mutations[int(rng.integers(len(mutations)))]
                    mutate(payload)
                    used.add(mutate.__name__)
                    bad.send_samples(payload)
                    sent["hostile"] += 1
                size = int(rng.integers(2, 40))
                payload = genuine_payload(sent["genuine_samples"], size, src=7, seq=sent["seq"])
                if rng.random() < 0.3:  # bad statistics on a good batch: the samples still count
                    payload["stats"] = {"stat_train_return": math.nan, "stat_test_steps": -5}
                good.send_samples(payload)
                sent["genuine_samples"] += size
                sent["seq"] += 1

        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        while sender.is_alive():
            run.update_buffer(iface)
            if run.memory.total >= 16:
                for _ in range(3):
                    run.agent.train(run.memory.sample())
        hostile, genuine_samples, seq = sent["hostile"], sent["genuine_samples"], sent["seq"]
        wait_for(
            lambda: run.update_buffer(iface) >= 0
            and run.memory.total >= genuine_samples
            and iface.rejected_batches >= hostile,
            timeout=60,
            what="every batch to be stored or rejected",
        )
        assert used == {m.__name__ for m in mutations}  # every kind of wrong batch was tried
        assert iface.rejected_batches == hostile  # each hostile batch dropped, none slipped in
        assert stored_firsts(run.memory) == list(range(genuine_samples))  # only genuine samples
        assert iface.connected and server.running  # the trainer and the relay are alive
        for _ in range(20):
            run.agent.train(run.memory.sample())
        assert params_finite(run.agent) and run.agent.skipped_updates == 0
        assert math.isfinite(run.memory.stat_train_return)
        print(f"[fuzz] {hostile} hostile and {seq} genuine batches in {BUDGET_S:.0f} s")
    finally:
        for link in (bad, good):
            link.close()
        trainer.interface.close()
        server.stop()
