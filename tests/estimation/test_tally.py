"""Tally: a dict whose missing keys read as 0, with a dict's own item assignment."""

from __future__ import annotations

import copy
import pickle
from collections import Counter

from pd_service.estimation.tally import Tally


def test_missing_keys_read_zero_and_insert_nothing():
    t = Tally()
    assert t["late"] == 0
    assert "late" not in t and len(t) == 0
    t["late"] += 2
    t["accepted"] += 1
    assert t == {"late": 2, "accepted": 1}
    assert list(t) == ["late", "accepted"]  # insertion order, as a Counter's
    assert t.get("future") is None  # get() is a dict's: no default of 0


def test_counts_as_a_counter_counts():
    keys = ["a", "b", "a", "c", "a", "b"]
    t, c = Tally(), Counter[str]()
    for k in keys:
        t[k] += 1
        c[k] += 1
    assert t == c and list(t.items()) == list(c.items())


def test_item_assignment_is_the_dicts_own():
    # Counter defines __delitem__ in Python, which gives every item assignment CPython's
    # generic slot (a lookup and a wrapper call); Tally must define none of these methods
    for name in ("__setitem__", "__delitem__", "__getitem__"):
        assert name not in vars(Tally), name
    assert Tally.__setitem__ is dict.__setitem__


def test_copies_and_pickles_as_a_tally():
    t = Tally({"accepted": 3})
    for other in (copy.deepcopy(t), copy.copy(t), pickle.loads(pickle.dumps(t))):
        assert type(other) is Tally and other == t
        assert other["missing"] == 0
