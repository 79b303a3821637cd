"""Quoting and reading values from untrusted files in bounded time: messages and ids.

A data file can hold a structure whose ``repr`` is exponential in its size (one list
shared at every level), a string of hundreds of megabytes, or an integer of millions of
digits (``str`` of one refuses past 4,300 digits, with a message that names nothing).
Error messages therefore quote a value read from a file only through :func:`brief` (a
repr cut to :data:`MAX_QUOTE` characters, or a type name and a length), quote an
underlying exception only through :func:`error_text`, and read ids only through
:func:`entry_id`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

MAX_QUOTE = 80  # [characters] of a value read from a file quoted in an error message
MAX_MESSAGE = 300  # [characters] of an underlying exception's message kept
MAX_ID_CHARS = 256  # [characters] longest id (scenario, track, map feature, file entry)
MAX_ID_BITS = 64  # longest integer id [bits]

_SCALARS = (bool, float, complex, type(None), np.bool_, np.number)


def brief(value: Any, limit: int = MAX_QUOTE) -> str:
    """A description of ``value`` of at most about ``limit`` characters, in time that
    does not depend on its size: the repr of a short string, number or tuple of numbers
    (a shape), else its type and length."""
    if isinstance(value, (str, bytes, bytearray)):
        text = repr(value[:limit])
        return text if len(value) <= limit else f"{text}... ({len(value)} characters)"
    if isinstance(value, int) and not isinstance(value, bool):
        bits = value.bit_length()
        return repr(value) if bits <= MAX_ID_BITS else f"an int of {bits} bits"
    if isinstance(value, _SCALARS):
        return repr(value)[:limit]
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} ({value.dtype.str})"
    if isinstance(value, tuple) and len(value) <= 8:
        if all(isinstance(v, int) and abs(v) < 2**MAX_ID_BITS for v in value):
            return repr(tuple(int(v) for v in value))
    if isinstance(value, (list, tuple, dict, set, frozenset)):
        return f"a {type(value).__name__} of {len(value)} items"
    return f"a {type(value).__name__}"


def error_text(error: BaseException, limit: int = MAX_MESSAGE) -> str:
    """``"<type>: <message>"`` of ``error``, the message cut to ``limit`` characters and
    built without formatting any argument that is not a short string or number (a
    ``KeyError``'s key is quoted with :func:`brief`)."""
    args = error.args
    plain = all(
        isinstance(a, (str, float)) or (isinstance(a, int) and a.bit_length() <= MAX_ID_BITS)
        for a in args
    )
    if plain and not isinstance(error, KeyError):
        text = str(error) if len(args) != 1 else str(args[0])
    else:
        text = ", ".join(brief(a) for a in args[:4])
    if len(text) > limit:
        text = text[:limit] + "..."
    return f"{type(error).__name__}: {text}"


def entry_id(value: Any, what: str) -> str:
    """``value``, an id read from a file (a str, or an int as some converters write), as a
    str.

    Raises:
        ValueError naming ``what`` for anything else, a str of more than
        :data:`MAX_ID_CHARS` characters or an int of more than :data:`MAX_ID_BITS` bits.
    """
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        if int(value).bit_length() <= MAX_ID_BITS:
            return str(int(value))
    elif isinstance(value, str) and len(value) <= MAX_ID_CHARS:
        return str(value)
    raise ValueError(
        f"{what} must be an id: a str of at most {MAX_ID_CHARS} characters or an int of at "
        f"most {MAX_ID_BITS} bits, got {brief(value)}"
    )


__all__ = [
    "MAX_ID_BITS",
    "MAX_ID_CHARS",
    "MAX_MESSAGE",
    "MAX_QUOTE",
    "brief",
    "entry_id",
    "error_text",
]
