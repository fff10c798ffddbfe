from __future__ import annotations

import numpy as np
import pytest

from training import design_space as ds


def test_sampler_is_seeded_and_inside_table_i():
    a = ds.sample_designs(500, seed=11).features()
    b = ds.sample_designs(500, seed=11).features()
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, ds.sample_designs(500, seed=12).features())
    low, high = ds.feature_bounds()
    assert (a >= low).all() and (a <= high).all()
    assert a.shape == (500, 15)


@pytest.mark.parametrize("bin_range", ds.OOD_BINS)
def test_ood_bins_scale_the_upper_bounds(bin_range):
    f = ds.sample_ood_designs(300, bin_range, seed=2).features()
    _, high = ds.feature_bounds()
    p = f / high - 1.0
    assert (p >= bin_range[0] - 1e-12).all() and (p <= bin_range[1] + 1e-12).all()


def test_normalisation_maps_table_i_to_unit_box():
    low, high = ds.feature_bounds()
    np.testing.assert_allclose(ds.normalize(low[None]), -1.0)
    np.testing.assert_allclose(ds.normalize(high[None]), 1.0)
    np.testing.assert_allclose(ds.normalize(((low + high) / 2)[None]), 0.0, atol=1e-12)


def test_out_of_range_names_every_offending_parameter():
    f = ds.sample_designs(2, seed=0).features()
    f[1, 0] = 50e9  # E above 45.5 GPa
    f[1, 14] = -1.0  # tension_3 below 0
    assert ds.out_of_range(f) == [[], ["E", "tension_3"]]


def test_validation_names_design_and_field():
    d = ds.sample_designs(3, seed=0)
    f = d.features()
    f[0, 1] = -1e-3
    f[2, 5] = np.inf
    f[2, 12] = -0.5
    msgs = ds.validate_design(type(d).from_features(f))
    assert msgs == [
        "design 0: r must be positive, got -0.001",
        "design 2: offset_2 must be finite, got inf",
        "design 2: tension_1 must be non-negative, got -0.5",
    ]
