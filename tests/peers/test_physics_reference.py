"""The solver against an independent C++ shooting solver (shared/reference/cosserat_cases.json)."""

from __future__ import annotations

import numpy as np
import pytest

from tdcr import relative_l2
from tdcr.physics import SolverOptions, solve

TENDON_TOL = 1e-6  # max relative l2 error of tendon positions (issue #2)
ORTHO_TOL = 1e-10  # |R^T R - I| and |det R - 1|


def test_every_reference_case_matches(reference_cases, designs_from_json):
    for case in reference_cases:
        designs = designs_from_json([case["design"]])
        sol = solve(designs, np.asarray(case["s"]) / case["design"]["L"])
        assert sol.converged[0], case["kind"]
        err = relative_l2(sol.tendons, np.asarray(case["tendons"])[None])[0]
        assert err <= TENDON_TOL, (case["kind"], err)
        np.testing.assert_allclose(sol.backbone[0], case["backbone"], atol=1e-6 * case["design"]["L"])
        np.testing.assert_allclose(sol.rotation[0], case["rotation"], atol=1e-5)
        np.testing.assert_allclose(sol.s[0], case["s"], rtol=1e-10, atol=1e-15)  # reference s has 12 digits


def test_reference_cases_as_one_batch(reference_cases, designs_from_json):
    cases = [c for c in reference_cases if len(c["s"]) == 42]
    assert len(cases) >= 10
    designs = designs_from_json([c["design"] for c in cases])
    sol = solve(designs, np.linspace(0.0, 1.0, 42))
    errors = relative_l2(sol.tendons, np.array([c["tendons"] for c in cases]))
    assert errors.max() <= TENDON_TOL, errors


@pytest.mark.parametrize("max_step", [1 / 41, 1 / 200])
def test_rotations_are_orthonormal(reference_cases, designs_from_json, max_step):
    designs = designs_from_json([c["design"] for c in reference_cases])
    sol = solve(designs, np.linspace(0, 1, 42), options=SolverOptions(max_step=max_step))
    R = sol.rotation
    gram = np.einsum("bnji,bnjk->bnik", R, R)
    assert np.abs(gram - np.eye(3)).max() < ORTHO_TOL
    assert np.abs(np.linalg.det(R) - 1.0).max() < ORTHO_TOL


@pytest.mark.parametrize("copy, original", [("cosserat_cases.json", "reference/cosserat_cases.json"),
                                            ("compose-spec.json", "schemas/compose-spec.json")])
def test_the_reference_copy_is_the_shared_file(data, shared, copy, original):
    """tests/data holds copies so that the suite runs on a clone alone; where shared/ is beside the
    checkout the copies must still be its files."""
    if shared is None:
        pytest.skip("no shared/ beside the checkout: the copies in tests/data are used as they are")
    assert (data / copy).read_bytes() == (shared / original).read_bytes()
