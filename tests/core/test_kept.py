"""bilevel.kept: the process stores' rule (the least recently used key goes first; an unusable value is made again)."""

from __future__ import annotations

from bilevel.kept import kept


def test_kept_makes_once_evicts_the_least_recently_used_and_remakes_unusable_values() -> None:
    store: dict = {}
    made = []

    def make(k: str):
        return lambda: made.append(k) or k.upper()

    assert kept(store, "a", make("a"), 2) == ("A", True)
    assert kept(store, "b", make("b"), 2) == ("B", True)
    assert kept(store, "a", make("a"), 2) == ("A", False)  # a is now the most recent
    assert kept(store, "c", make("c"), 2) == ("C", True)   # so b goes
    assert list(store) == ["a", "c"] and made == ["a", "b", "c"]
    assert kept(store, "a", make("a"), 2, usable=lambda v: v != "A") == ("A", True)  # made again, stored again
    assert made == ["a", "b", "c", "a"] and list(store) == ["c", "a"]
