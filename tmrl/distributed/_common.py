"""What the three roles share: the defaults read from the config when an object is built (never
at import), and the making of a transport link from those settings."""

from __future__ import annotations

import os
from typing import Any

from tmrl.config.settings import NetSettings
from tmrl.errors import UserError

LOGGER_NAME = "tmrl.networking"
"""The roles' log lines keep tmrl 0.7's logger name, wherever their code now lives: a user's
logging configuration for ``tmrl.networking`` and the lines the documentation shows stay true."""

STOP_TIMEOUT = 2.0
"""Seconds a role interrupted by a signal gives its network process to flush before killing it
(a role must be gone within 5 s of SIGTERM or Ctrl-C)."""


def _one_line(err: BaseException) -> str:
    """An exception as one short line (its message's first line, or its type)."""
    text = str(err).strip().splitlines()
    return (text[0] if text else type(err).__name__)[:300]


class PasswordRefused(UserError):
    """The server refused this role's password: retrying cannot help, the role stops."""


def check_refused(link: Any, role: str, where: str) -> None:
    """Raise :class:`PasswordRefused` once the server has refused ``link``'s password (tlspyo's
    "wrong password", a NATS authorization violation); other refusals are the link's business.

    Args:
        link: a transport link (its ``refused`` attribute: the last refusal reason, or None).
        role: ``"worker"`` or ``"trainer"``, for the message.
        where: the server's address, for the message.
    """
    reason = getattr(link, "refused", None)
    if not reason or not any(w in str(reason).lower() for w in ("wrong password", "authorization")):
        return
    raise PasswordRefused(
        f"the server at {where} refused this {role}'s password ({reason}): set PASSWORD in config.json to the "
        "server's (the same on every machine of a run), or pass it with -d '{\"PASSWORD\": \"...\"}'"
    )


def close_budget(link: Any, timeout: float) -> float:
    """How long closing ``link`` may flush: ``timeout``, or at most :data:`STOP_TIMEOUT` once the
    server refused it (nothing will be delivered: waiting would only delay the refusal's line)."""
    return min(timeout, STOP_TIMEOUT) if getattr(link, "refused", None) else timeout


class _FromConfig:
    """Default of an argument whose ``None`` has a meaning of its own (for example
    ``checkpoint_path=None``: no checkpoint); the real default is read from the config."""

    def __repr__(self) -> str:
        return "<from config>"


FROM_CONFIG: Any = _FromConfig()


class _NotGiven:
    """Default of an argument whose ``None`` has a meaning of its own and whose absence too."""

    def __repr__(self) -> str:
        return "<not given>"


NOT_GIVEN: Any = _NotGiven()


def _given(value: Any, default: Any) -> Any:
    """``value`` unless it is ``None`` or ``FROM_CONFIG`` (then ``default``, from the settings)."""
    return default if value is None or value is FROM_CONFIG else value


def _given_keep_none(value: Any, default: Any) -> Any:
    """``value`` unless it is ``FROM_CONFIG``: an explicit ``None`` means something of its own."""
    return default if value is FROM_CONFIG else value


def _settings(settings: NetSettings | None) -> NetSettings:
    """``settings``, or those of ``config.json`` (loaded now: a role reads the config when it is
    built, never at import)."""
    return settings if settings is not None else NetSettings.load()


# ================================================================================================
# Buffer


def _make_link(
    link_cls: Any,
    server_ip: str,
    server_port: int | None,
    password: str | None,
    local_port: int | None,
    header_size: int | None,
    security: str | None,
    keys_dir: str | os.PathLike[str] | None,
    hostname: str | None,
    settings: NetSettings | None = None,
    **extra: Any,
) -> Any:
    """A transport link (``WorkerLink`` or ``TrainerLink``) with every unset argument taken from
    the settings, as the worker and the trainer both need; ``extra`` goes to the link as is."""
    cfg = _settings(settings)
    keys_dir = _given(keys_dir, cfg.credentials_directory)
    return link_cls(
        server_ip,
        int(_given(server_port, cfg.port)),
        _given(password, cfg.password),
        local_port=local_port,
        header_size=int(_given(header_size, cfg.header_size)),
        security=_given_keep_none(security, cfg.security),
        keys_dir=str(keys_dir) if keys_dir is not None else None,
        hostname=_given(hostname, cfg.hostname),
        **cfg.link_options(),
        **extra,
    )
