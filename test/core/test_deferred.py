"""A value computed once, when first asked for."""

from __future__ import annotations

import pytest

from gft_odom.core.deferred import Deferred, resolved


def test_computes_once_at_the_first_get_and_derived_values_wait_too():
    calls = []

    def compute():
        calls.append(1)
        return [1, 2, 3]

    value = Deferred(compute)
    doubled = value.then(lambda xs: [2 * x for x in xs])
    assert not value.done and not doubled.done and calls == []
    assert doubled.get() == [2, 4, 6]
    assert value.done and calls == [1]
    assert value.get() is value.get() and calls == [1]
    assert value.seconds >= 0.0
    assert resolved(value) == [1, 2, 3] and resolved(7) == 7 and resolved(None) is None


def test_a_failed_computation_raises_again_without_running_again():
    calls = []

    def broken():
        calls.append(1)
        raise ValueError('no spectrum')

    value = Deferred(broken)
    for _ in range(2):
        with pytest.raises(ValueError, match='no spectrum'):
            value.get()
    assert calls == [1] and not value.done


def test_a_deep_copy_keeps_what_was_computed_and_shares_what_was_not():
    import copy

    import numpy as np
    computed = Deferred(lambda: np.arange(3))
    computed.get()
    twin = copy.deepcopy(computed)
    assert twin.done and twin.get() is not computed.get()
    np.testing.assert_array_equal(twin.get(), computed.get())
    pending = Deferred(lambda: np.arange(4))
    assert copy.deepcopy(pending) is pending and not pending.done
