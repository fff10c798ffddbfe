"""The field registry (tdcr.robot.fields) is the one list of design inputs: the batch, the schemas,
the checks, the OIP layout and the design space all follow it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tdcr.api import schemas
from tdcr.api.checks import LAYOUT_REASONS, InvalidRequest, check_layout, check_standard_layout, format_location
from tdcr.api.validation import validate_features, validate_json
from tdcr.robot import design_space
from tdcr.robot.designs import DesignBatch, FeatureLayout
from tdcr.robot.fields import BY_NAME, FEATURES, FIELDS, LAYOUT_COLUMNS, OPTIONAL, OWN_TENSORS, interval


def _general_designs(n: int, seed: int) -> DesignBatch:
    """Table I designs with every optional field set to an admissible, non-default value."""
    rng = np.random.default_rng(seed)
    designs = design_space.sample_designs(n, seed=seed)
    n_t = designs.n_tendons
    driven = rng.random((n, n_t)) < 0.5
    return designs.replace(angle=rng.uniform(-3.0, 3.0, (n, n_t)),
                           end=designs.L[:, None] * rng.uniform(0.3, 1.0, (n, n_t)),
                           displacement=np.where(driven, rng.uniform(0.0, 1e-3, (n, n_t)), np.nan),
                           poisson=rng.uniform(0.1, 0.45, n))


def test_the_batch_holds_exactly_the_registry_fields():
    assert tuple(f.name for f in dataclasses.fields(DesignBatch)) == tuple(f.name for f in FIELDS)
    assert FeatureLayout(4).parameters == tuple(f.name for f in FEATURES if f.per == "design") + tuple(
        f.name for f in FEATURES if f.per == "tendon" for _ in range(4))
    assert tuple(design_space.TABLE_I) == tuple(f.name for f in FEATURES)
    assert tuple(design_space.LAYOUT_FIELDS) == tuple(f.name for f in OPTIONAL)


def test_the_schemas_take_the_registry_fields():
    tendon = [f.name for f in FIELDS if f.per == "tendon"]
    design = [f.name for f in FIELDS if f.per == "design"]
    loads = list(schemas._Loads.model_fields)
    assert list(schemas.Tendon.model_fields) == tendon
    assert list(schemas.SurrogateTendon.model_fields) == [f.name for f in FEATURES if f.per == "tendon"]
    assert list(schemas.InverseTendon.model_fields) == [n for n in tendon if BY_NAME[n].inverse]
    assert list(schemas.Design.model_fields) == loads + design + ["tendons"]
    assert list(schemas.SurrogateDesign.model_fields) == loads + [
        f.name for f in FEATURES if f.per == "design"] + ["tendons"]
    # the JSON schema's bounds are the registry's admissible bounds
    properties = schemas.Tendon.model_json_schema()["properties"]
    for name in tendon:
        f = BY_NAME[name]
        if f.choices:  # a field in words: its words, or null
            assert properties[name]["anyOf"][0]["enum"] == list(f.choices), name
            continue
        bound = properties[name]
        bound = bound if {"minimum", "exclusiveMinimum"} & set(bound) else bound["anyOf"][0]
        low_key = "exclusiveMinimum" if f.exclusive_min else "minimum"
        assert bound[low_key] == f.admissible[0] and f.admissible[1] in (bound.get("maximum"),
                                                                        bound.get("exclusiveMaximum")), name


def test_the_json_form_round_trips_every_field():
    designs = _general_designs(12, seed=3)
    request = validate_json({"designs": designs.to_dicts(), "points": 5}, target="solver")
    (group,) = request.groups
    for f in FIELDS:
        expected, got = designs.resolved(f.name), group.designs.resolved(f.name)
        if f.name == "tension":  # a displacement-driven tendon's tension is the solver's start, 0
            expected = np.where(designs.displacement_driven, 0.0, expected)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected), err_msg=f.name)
        np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(expected), rtol=0, atol=0, err_msg=f.name)


@pytest.mark.parametrize("field", [f for f in OPTIONAL], ids=lambda f: f.name)
def test_every_optional_field_is_checked_against_its_bounds(field):
    designs = design_space.sample_designs(3, seed=1)
    shape = (3,) if field.per == "design" else (3, designs.n_tendons)
    low, high = field.admissible
    beyond = np.full(shape, low - 1e-3 * (high - low) if not field.exclusive_min else low)
    beyond.reshape(-1)[1] = high + 1e-3 * (high - low) if not field.exclusive_max else high
    problems = check_layout(designs.replace(**{field.name: beyond}))
    where = (field.name,) if field.per == "design" else ("tendons", 0, field.name)
    assert ("designs", 0) + where in [p.loc for p in problems]
    assert any(interval(field) in p.msg or (field.within_length and "(0, L]" in p.msg)
               or (field.choices and all(repr(w) in p.msg for w in field.choices)) for p in problems)
    # and a value inside its bounds (its default where it has one) passes
    inside = field.fill(designs.L, designs.n_tendons)
    inside = np.where(np.isnan(inside), 0.5 * (low + high), inside)
    assert check_layout(designs.replace(**{field.name: inside})) == []


@pytest.mark.parametrize("field", [f for f in OPTIONAL], ids=lambda f: f.name)
def test_an_operator_refuses_each_optional_field_by_name(field):
    designs = design_space.sample_designs(2, seed=2)
    default = field.fill(designs.L, designs.n_tendons)
    assert check_standard_layout(designs.replace(**{field.name: default})) == [] or field.alternative_to
    # inside its bounds, not its default (an infinite default: rigid tendons)
    other = np.where(np.isnan(default), 1e-4, np.where(np.isinf(default), 1e3, default * 0.8 + 0.01))
    if field.choices:  # the other word
        other = np.full(default.shape, [v for v in field.choices.values() if v != field.default][0])
    problems = check_standard_layout(designs.replace(**{field.name: other}))
    where = (field.name,) if field.per == "design" else ("tendons", 0, field.name)
    assert [p.loc for p in problems] == [("designs", 0) + where, ("designs", 1) + where]
    assert problems[0].msg.startswith(LAYOUT_REASONS[field.name]) and field.refusal.split("{")[0] in problems[0].msg
    assert not designs.replace(**{field.name: other}).is_standard().any()


def test_the_oip_layout_and_the_design_space_follow_the_registry():
    assert LAYOUT_COLUMNS == ("angle", "end", "displacement", "driven", "stiffness", "zero", "friction", "motion")
    assert OWN_TENSORS == ("poisson",)
    assert set(design_space.describe()["layout"]) == {f.name for f in OPTIONAL}
    designs = _general_designs(4, seed=5)
    layout = {f.name: designs.resolved(f.name) for f in OPTIONAL}
    request = validate_features(designs.features(), target="solver", points=3, layout=layout)
    for f in OPTIONAL:
        np.testing.assert_array_equal(request.groups[0].designs.resolved(f.name), layout[f.name], err_msg=f.name)
    with pytest.raises(ValueError) as info:
        validate_features(designs.features(), target="solver", points=3, layout={"rigidity": designs.L})
    assert ("not a layout field; they are angle, end, poisson, displacement, stiffness, zero, friction and motion"
            in str(info.value))
    assert format_location(("designs", 0, "tendons", 1, "end")) == "designs[0].tendons[1].end"


def test_an_end_is_judged_against_its_own_design_length_only_where_that_length_is_admissible():
    designs = design_space.sample_designs(2, seed=4)
    n = designs.n_tendons
    half = np.repeat(designs.L[:, None] / 2, n, axis=1)  # (2, N_t) m: inside either design
    refused = designs.replace(L=np.array([-1.0, designs.L[1]]), end=half)
    # design 0's L is refused, and the one validation path names only that: its ends are not judged against it
    with pytest.raises(InvalidRequest) as refusal:
        validate_json({"designs": refused.to_dicts(), "points": 5}, target="solver")
    assert [p.loc for p in refusal.value.problems] == [("designs", 0, "L")]
    # an end beyond an admissible L is named with that L; beyond its own bound, with the bound
    beyond = designs.replace(end=np.repeat(designs.L[:, None] * 1.5, n, axis=1))
    problems = check_layout(beyond)
    assert len(problems) == 2 * n and all(p.type == "end_beyond_length" and "(0, L] = (0, " in p.msg
                                          for p in problems)
    end = BY_NAME["end"]
    far = refused.replace(end=np.full((2, n), end.admissible[1] * 2))
    by_design = {b: [p for p in check_layout(far) if p.loc[1] == b] for b in (0, 1)}
    assert len(by_design[0]) == len(by_design[1]) == n
    assert all(p.type == "out_of_range" and interval(end) in p.msg for p in by_design[0])  # L refused
    assert all(p.type == "end_beyond_length" for p in by_design[1])
