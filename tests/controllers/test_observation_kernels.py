"""The compiled tokens equal sim.observations.fleet_tokens_np in a float32 buffer, bit for bit."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.observation_kernels import fleet_tokens
from sim.observations import fleet_tokens_np, object_token_constants

ARENA = (1.0, 1.2)
SHAPES = {
    "box": np.array([[0.4, 0.45], [0.6, 0.45], [0.6, 0.55], [0.4, 0.55]]),
    "rotated box": np.array([[0.5, 0.35], [0.65, 0.5], [0.5, 0.65], [0.35, 0.5]]),
    "L (not convex)": np.array([[0.35, 0.35], [0.65, 0.35], [0.65, 0.45], [0.45, 0.45], [0.45, 0.65],
                                [0.35, 0.65]]),
}


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 9), shape=st.sampled_from(sorted(SHAPES)))
def test_compiled_tokens_equal_the_numpy_layout(seed, n, shape):
    """Robots anywhere: outside the object, inside it, on its boundary (the box's closed form
    then gives way to the edge projections for every robot)."""
    rng = np.random.default_rng(seed)
    pos, vel, targets = rng.uniform(0, 1, (n, 2)), rng.normal(0, 0.3, (n, 2)), rng.uniform(0, 1, (n, 2))
    polygon = SHAPES[shape]
    if rng.random() < 0.3:
        pos[0] = polygon.mean(axis=0)                             # inside
    if rng.random() < 0.2:
        pos[-1] = polygon[1]                                      # on a vertex
    want = fleet_tokens_np(pos, vel, targets, polygon, ARENA, np.empty((n, 2 * n + 1, 4), dtype=np.float32))
    got = np.full((n, 2 * n + 1, 4), np.nan, dtype=np.float32)
    fleet_tokens(pos, vel, targets, *object_token_constants(polygon), ARENA[0] / 2, ARENA[1] / 2, got)
    np.testing.assert_array_equal(got, want)
