"""Entry point of the network process behind a :class:`~tmrl.transport.RelayServer` or a link.

Started as ``python -m tmrl.transport._netproc`` by :mod:`tmrl.transport._process` (the command
line that tests and operators recognise the process by). The code lives in three modules:

- :mod:`tmrl.transport._netcommon`: framing, checks, and the process plumbing (:func:`main`: the
  pipe to the parent, signals, the parent watch);
- :mod:`tmrl.transport._netrelay`: the relay's classes (imported when ``cfg["role"]`` is
  ``"relay"``);
- :mod:`tmrl.transport._netlink`: the link's classes (a worker's or the trainer's connection).

Importing this module imports neither Twisted nor tlspyo.
"""

from __future__ import annotations

from tmrl.transport._netcommon import (  # noqa: F401 (re-exported: their home was this module)
    _frame,
    _FrameReader,
    _parse_length,
    _tune,
    main,
    session_token,
)

__all__ = ["main", "session_token"]

if __name__ == "__main__":
    main()
