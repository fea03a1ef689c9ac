"""What every command handler shares: the usage-error exit code and the one-line error."""

from __future__ import annotations

import sys

USAGE_ERROR = 2


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def fail(message: str) -> int:
    """Print ``scenegen: error: MESSAGE`` on stderr (one line) and return the usage-error code."""
    print(f"scenegen: error: {message}", file=sys.stderr)
    return USAGE_ERROR
