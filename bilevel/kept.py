"""Process stores that keep the last few values by key (declared problems, shared problems, starts): one rule for
recency and eviction."""

from __future__ import annotations

from typing import Callable, Hashable, TypeVar

V = TypeVar("V")
_ABSENT = object()


def kept(store: dict[Hashable, V], key: Hashable, make: Callable[[], V], limit: int,
         usable: Callable[[V], bool] | None = None) -> tuple[V, bool]:
    """(store[key], False) as the most recently used value, or (make(), True) stored there where the key is absent or
    usable(value) is false; the store keeps its `limit` most recently used keys."""
    value = store.pop(key, _ABSENT)
    made = value is _ABSENT or (usable is not None and not usable(value))
    if made:
        value = make()
    store[key] = value
    while len(store) > limit:
        del store[next(iter(store))]
    return value, made
