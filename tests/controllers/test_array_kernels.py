"""The compiled row checks equal their numpy formulations, NaN and infinities included."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.array_kernels import all_finite, clip_norm_rows, non_finite_rows
from sim.scenario import clip_norm

ENTRIES = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0.0, -0.0, 1.0, 1e-300, 1e300, np.nan, np.inf, -np.inf]))


def rows(n: int):
    return st.lists(st.tuples(ENTRIES, ENTRIES), min_size=n, max_size=n).map(
        lambda r: np.array(r, dtype=np.float64).reshape(n, 2))


@settings(max_examples=200, deadline=None)
@given(data=st.data(), n=st.integers(1, 8), limit=st.sampled_from([0.5, 1.0, 3.0]))
def test_row_kernels_equal_numpy(data, n, limit):
    pos, vel = data.draw(rows(n)), data.draw(rows(n))
    assert all_finite(pos) == bool(np.isfinite(pos).all())
    out = np.empty(n, dtype=bool)
    count = non_finite_rows(pos, vel, out)
    want = ~(np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1))
    np.testing.assert_array_equal(out, want)
    assert count == want.sum()
    with np.errstate(all="ignore"):
        np.testing.assert_array_equal(clip_norm_rows(pos, limit), clip_norm(pos, limit))


def test_non_finite_rows_marks_the_row_hand_worked():
    pos = np.array([[0.1, 0.2], [np.nan, 0.2], [0.3, 0.4]])
    vel = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, -np.inf]])
    out = np.empty(3, dtype=bool)
    assert non_finite_rows(pos, vel, out) == 2
    assert out.tolist() == [False, True, True]
    np.testing.assert_allclose(clip_norm_rows(np.array([[3.0, 4.0], [0.3, 0.4]]), 1.0), [[0.6, 0.8], [0.3, 0.4]],
                               rtol=1e-15)
