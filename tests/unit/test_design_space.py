from __future__ import annotations

import numpy as np
import pytest

from tdcr import design_space as ds
from tdcr.api.validation import check_features, format_location


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


def test_validation_names_design_field_and_bound():
    f = ds.sample_designs(3, seed=0).features()
    f[0, 1] = -1e-3
    f[2, 5] = np.inf
    f[2, 12] = -0.5
    f[2, 0] = 5e-324  # E: positive but far below any material
    msgs = [(format_location(p.loc), p.msg) for p in check_features(f)]
    assert msgs == [
        ("designs[0].r", "must be in [0.0001, 0.05] m, got -0.001"),
        ("designs[2].E", "must be in [1e+06, 1e+12] Pa, got 4.94066e-324"),
        ("designs[2].tendons[2].offset", "must be a finite number, got inf"),
        ("designs[2].tendons[1].tension", "must be in [0, 1000] N, got -0.5"),
    ]


def test_table_i_lies_inside_the_admissible_bounds():
    for p in ds.TABLE_I.values():
        low, high = p.admissible
        assert low <= p.low < p.high <= high, p.name
    low, high, _ = ds.admissible_bounds()
    f = ds.sample_designs(1000, seed=1).features()
    assert check_features(f) == [] and (f >= low).all() and (f <= high).all()


def test_range_warnings_name_value_unit_and_range():
    f = ds.sample_designs(2, seed=0).features()
    f[1, ds.LAYOUT.group("tension")] = [0.0, 0.0, 6.5, 0.0]
    warnings = ds.range_warnings(f)
    assert warnings == [[], ["tension_2 = 6.5 N is outside the trained range [0, 5]"]]


def test_feature_layout_names_every_column():
    layout = ds.LAYOUT
    assert layout.width == ds.N_FEATURES == 15
    assert layout.names[layout.group("pitch")] == ("pitch_0", "pitch_1", "pitch_2", "pitch_3")
    f = ds.sample_designs(3, seed=5)
    np.testing.assert_array_equal(f.features()[:, layout.group("tension")], f.tension)
    np.testing.assert_array_equal(type(f).from_features(f.features()).features(), f.features())


def test_designs_round_trip_through_the_request_format(designs_from_json):
    d = ds.sample_designs(7, seed=9)
    np.testing.assert_array_equal(designs_from_json(d.to_dicts()).features(), d.features())
