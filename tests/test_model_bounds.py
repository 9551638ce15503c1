"""Per-column bounds (nrpose.model.bounds.column_bounds) equal numpy's reductions exactly."""
import numpy as np
import pytest

from nrpose.model.bounds import column_bounds


@pytest.mark.parametrize("shape, dtype", [((1, 3), np.float32), ((517, 3), np.float64), ((4, 99, 3), np.float32),
                                          ((50, 16), np.float32), ((7, 3), np.int16), ((12, 1), np.int8)])
def test_column_bounds_equal_the_reductions(shape, dtype):
    rng = np.random.default_rng(len(shape) * 100 + shape[-1])
    values = (rng.normal(scale=100, size=shape)).astype(dtype)
    values.reshape(-1, shape[-1])[rng.integers(len(values.reshape(-1, shape[-1])))] = -values.max()  # ties
    axes = tuple(range(values.ndim - 1))
    low, high = column_bounds(values)
    assert low.dtype == high.dtype == values.dtype and low.shape == high.shape == (shape[-1],)
    assert np.array_equal(low, values.min(axis=axes)) and np.array_equal(high, values.max(axis=axes))
    strided = values[..., ::-1]                     # a view, not contiguous
    assert np.array_equal(column_bounds(strided)[0], strided.min(axis=axes))


def test_column_bounds_carry_nan_as_numpy_does():
    values = np.zeros((5, 3))
    values[2, 1] = np.nan
    low, high = column_bounds(values)
    assert np.isnan(low[1]) and np.isnan(high[1]) and low[0] == high[2] == 0.0
