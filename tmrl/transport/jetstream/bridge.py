"""The NATS backend's bridge from the synchronous contract to asyncio: the event loop each link runs
in a background thread, and a rate-limited log.

``nats-py`` is asyncio; the transport contract (:mod:`tmrl.transport.base`) is synchronous. A link
owns one :class:`_Loop`: the roles' threads hand it coroutines (:meth:`_Loop.submit`) and
callbacks (:meth:`_Loop.call`). Importing this module starts no thread and makes no event loop.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from typing import Any

logger = logging.getLogger("tmrl.transport.nats")


class _Rate:
    """Logs one line per ``period`` seconds at most (with the count of the ones held back)."""

    def __init__(self, level: int, period: float = 10.0):
        self.level, self.period, self.last, self.held = level, period, 0.0, 0

    def __call__(self, msg: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self.last >= self.period:
            extra = f" ({self.held} more like it)" if self.held else ""
            logger.log(self.level, msg + extra, *args)
            self.last, self.held = now, 0
        else:
            self.held += 1


class _Loop:
    """An asyncio event loop running in a daemon thread."""

    def __init__(self, name: str):
        import asyncio

        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self._run, daemon=True, name=name)
        self.thread.start()

    def _run(self) -> None:
        import asyncio

        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_forever()
        finally:
            tasks = asyncio.all_tasks(self.loop)
            for t in tasks:
                t.cancel()
            if tasks:
                self.loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            self.loop.close()

    def submit(self, coro: Any) -> concurrent.futures.Future[Any]:
        """Run ``coro`` on the loop; a future of its result."""
        import asyncio

        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    def call(self, fn: Any, *args: Any) -> None:
        """Call ``fn(*args)`` on the loop's thread, soon."""
        if not self.loop.is_closed():
            try:
                self.loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:  # closed meanwhile
                pass

    def stop(self, timeout: float) -> None:
        """Cancel every task, stop the loop and join its thread."""
        self.call(self.loop.stop)
        self.thread.join(max(timeout, 0.1))
