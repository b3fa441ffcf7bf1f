"""tmrl.realtime.clock: virtual time semantics and the real clock's basic contract."""

from __future__ import annotations

import queue
import threading

import pytest

from tmrl.realtime import FakeClock, PerfCounterClock


def test_fake_clock_is_per_thread_and_messages_carry_time():
    clock = FakeClock(start=1.0)
    ch, back = clock.channel(), clock.channel()
    seen = {}

    def other():
        seen["start"] = clock.now()
        item = ch.get()  # sent at 3.5: this thread jumps there
        seen["after_get"] = clock.now()
        clock.sleep(0.5)
        back.put(item + 1)

    t = threading.Thread(target=other)
    t.start()
    clock.sleep(2.5)
    ch.put(41)
    assert back.get(timeout=10) == 42
    t.join()
    assert seen == {"start": 1.0, "after_get": 3.5}
    assert clock.now() == 4.0  # the reply was sent at 4.0
    clock.sleep_until(2.0)  # the past: no change
    assert clock.now() == 4.0
    clock.sleep(-1)
    assert clock.now() == 4.0


def test_perf_counter_clock_sleeps_until_deadline():
    clock = PerfCounterClock(spin=0.001)
    deadline = clock.now() + 0.01
    clock.sleep_until(deadline)
    assert clock.now() >= deadline
    t0 = clock.now()
    clock.sleep(0.002)
    assert clock.now() - t0 >= 0.002
    ch = clock.channel()
    ch.put("x")
    assert ch.get(timeout=1) == "x"
    with pytest.raises(queue.Empty):
        ch.get(timeout=0.001)


def test_receive_waits_in_short_slices_until_an_item_comes():
    # On Windows, Ctrl-C reaches a thread blocked on a lock only when its wait ends: receive()
    # never waits longer than WAKE_EVERY at a time, and goes on until the item comes.
    from tmrl.realtime.clock import WAKE_EVERY, receive

    class Slow:
        def __init__(self) -> None:
            self.timeouts: list[float | None] = []

        def get(self, timeout: float | None = None) -> str:
            self.timeouts.append(timeout)
            if len(self.timeouts) < 3:
                raise queue.Empty
            return "late"

    channel = Slow()
    assert receive(channel) == "late"
    assert channel.timeouts == [WAKE_EVERY] * 3 and 0 < WAKE_EVERY <= 0.5
    clock = FakeClock(start=1.0)
    real = clock.channel()
    real.put("now")
    assert receive(real) == "now"
