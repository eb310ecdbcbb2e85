"""The one exception type of the configuration layer."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["ConfigError", "did_you_mean"]


class ConfigError(ValueError):
    """A problem with a scene or fit configuration, as one line: ``SOURCE: KEY: what was expected``.

    ``source`` is the config file (or ``"<dict>"``), ``key`` the dotted key path with list indices in
    brackets (``occluder[0].radius``); either may be ``None`` and is then left out of the message.
    The command line prints ``str(err)`` as its single line on stderr and exits with status 2.
    """

    def __init__(self, source: str | None, key: str | None, message: str):
        self.source = source
        self.key = key
        self.message = message
        super().__init__(": ".join(p for p in (source, key, message) if p))


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``choices`` to ``name`` (difflib), or ``""``."""
    close = difflib.get_close_matches(str(name), sorted(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""
