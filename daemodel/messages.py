"""How error messages show user values: cut to a length a message can carry."""

from __future__ import annotations


def clip(text: str, limit: int = 80) -> str:
    """``text`` cut to ``limit`` characters, ending in ``...`` when cut."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def quoted(value, limit: int = 80) -> str:
    """``repr(value)`` in at most ``limit`` characters; a long string is cut inside its quotes."""
    if isinstance(value, str) and len(value) > limit:
        return repr(value[: limit - 3] + "...")
    return clip(repr(value), limit)


def listed(items, most: int = 10) -> str:
    """The first ``most`` of ``items``, each :func:`quoted`, and how many more there are."""
    items = list(items)
    shown = ", ".join(quoted(item) for item in items[:most])
    return shown + (f" and {len(items) - most:,} more" if len(items) > most else "")
