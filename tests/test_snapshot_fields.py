"""kernels._snapshot.fill_views: the one check-then-copy of snapshot arrays into state views."""

from typing import NamedTuple

import numpy as np
import pytest

from kernels._snapshot import fill_views


class _Views(NamedTuple):
    x: np.ndarray
    idx: np.ndarray


def _views():
    return _Views(x=np.zeros(3), idx=np.zeros(2, dtype=np.int64))


def test_copies_every_field_with_its_prefix():
    v = _views()
    fill_views(v, {"p.x": [1.0, 2.0, 3.0], "p.idx": np.array([4, 5])}, ("x", "idx"), prefix="p.")
    np.testing.assert_array_equal(v.x, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(v.idx, [4, 5])


@pytest.mark.parametrize("snap, message", [
    ({"x": np.ones(3)}, "state is missing 'idx'"),
    ({"x": np.ones(4), "idx": np.zeros(2, int)}, r"'x' has shape \(4,\), expected \(3,\)"),
    ({"x": np.ones(3), "idx": np.zeros(2)}, "'idx' holds float64, expected int64"),
    ({"x": np.array(["a", "b", "c"]), "idx": np.zeros(2, int)}, "'x' holds <U1, expected float64"),
])
def test_refuses_naming_the_entry_and_changes_nothing(snap, message):
    v = _views()
    with pytest.raises(ValueError, match=message):
        fill_views(v, snap, ("x", "idx"), what="state")
    assert not v.x.any() and not v.idx.any()
