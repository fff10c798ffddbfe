"""Schemathesis: cases generated from the committed OpenAPI document pass all its checks.

(The server's log is checked for unhandled exceptions when it stops; /exact may give its
documented 503 / 504 under load.)

The schemathesis pytest plugin does not run under pytest 9, so its Hypothesis strategies are
driven directly, one test per operation.
"""

from __future__ import annotations

import json

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import checks

from service.process import ServerProcess


@pytest.fixture(scope="module")
def operations(root) -> dict:
    """The committed OpenAPI document's operations, by ``METHOD /path``."""
    schema = schemathesis.openapi.from_dict(json.loads((root / "openapi" / "openapi.json").read_text()))
    return {f"{op.method.upper()} {op.path}": op for op in (r.ok() for r in schema.get_all_operations())}


@pytest.fixture(scope="module")
def live(tiny_models):
    srv = ServerProcess(tiny_models[1], exact_max_designs=50, exact_timeout_s=1, exact_admission_factor=1)
    yield srv
    srv.stop()


NAMES = ["GET /healthz", "GET /metrics", "GET /models", "GET /design-space", "GET /readyz", "POST /exact",
         "POST /inverse",
         "POST /predict",
         "GET /v2", "GET /v2/health/live", "GET /v2/health/ready", "GET /v2/models/{model}",
         "GET /v2/models/{model}/ready", "POST /v2/models/{model}/infer", "GET /v2/models/{model}/versions/{version}",
         "GET /v2/models/{model}/versions/{version}/ready", "POST /v2/models/{model}/versions/{version}/infer"]


def test_every_operation_is_fuzzed(operations):
    assert set(operations) == set(NAMES)


def _arclength_beyond_the_design(body) -> bool:
    """Whether a body's ``arclength`` (m) leaves [0, L] of a design, or its designs differ in L."""
    if not isinstance(body, dict) or not body.get("arclength"):
        return False
    lengths = {d["L"] for d in body["designs"]}
    return len(lengths) > 1 or max(body["arclength"]) > min(lengths)


def _end_beyond_the_design(body) -> bool:
    """Whether a tendon of a body's design ends beyond its L (a bound across fields, as above)."""
    if not isinstance(body, dict):
        return False
    designs = body.get("designs") or ([body["design"]] if isinstance(body.get("design"), dict) else [])
    return any(isinstance(t, dict) and isinstance(t.get("end"), (int, float)) and t["end"] > d.get("L", 0)
               for d in designs if isinstance(d, dict) for t in d.get("tendons") or [])


def _actuation_beyond_tendon_loads(body) -> bool:
    """Whether a body's design has a tendon with friction together with a Jacobian or the shortcut
    termination, or a displacement together with those or with loads (the solver refuses the first
    two, and a displaced design under loads costs 13 loaded solves in admission: a rule across
    fields, as above)."""
    if not isinstance(body, dict):
        return False
    designs = body.get("designs") or ([body["design"]] if isinstance(body.get("design"), dict) else [])
    other = bool(body.get("jacobian")) or body.get("termination", "exact") != "exact"
    for d in designs:
        if not isinstance(d, dict):
            continue
        tendons = [t for t in d.get("tendons") or [] if isinstance(t, dict)]
        friction = any((t.get("friction") or 0) > 0 for t in tendons)
        displaced = any(t.get("displacement") is not None for t in tendons)
        loaded = any(d.get(k) is not None for k in ("gravity", "tip_force", "tip_moment"))
        if (friction and other) or (displaced and (loaded or other)):
            return True
    return False


def _columns_unlike_the_tendons(body) -> bool:
    """Whether a robot file's actuation names another number of columns than its design has tendons
    (one column per tendon, checked as `tdcr replay` checks it: a rule across fields)."""
    if not isinstance(body, dict) or not all(isinstance(body.get(k), dict) for k in ("design", "actuation")):
        return False
    columns, tendons = body["actuation"].get("columns"), body["design"].get("tendons")
    return isinstance(columns, list) and isinstance(tendons, list) and len(columns) != len(tendons)


def _loads_for_a_load_free_operator(body) -> bool:
    """Whether a body names an operator that takes no loads (not ``*_loaded``, ``exact`` or ``auto``)
    for a design with a load that is not zero (refused naming the field: a rule across fields)."""
    model = body.get("model") if isinstance(body, dict) else None
    if model in (None, "exact", "auto") or str(model).endswith("_loaded"):
        return False
    designs = body.get("designs") or ([body["design"]] if isinstance(body.get("design"), dict) else [])

    def nonzero(value) -> bool:
        return isinstance(value, list) and any(isinstance(v, (int, float)) and v != 0 for v in value)

    return any(isinstance(d, dict) and ((nonzero(d.get("gravity")) and (d.get("density") or 0) != 0)
                                        or nonzero(d.get("tip_force")) or nonzero(d.get("tip_moment")))
               for d in designs)


@pytest.mark.parametrize("name", NAMES)
def test_every_check_passes(live, operations, name):
    """Schemathesis's response checks (status codes, content types, headers and bodies conform to
    the document; no server error).  Schema-valid cases must not get 422; the size limits of the
    server's settings (413) and /exact's documented 503 (saturated) and 504 (deadline) are allowed,
    which schemathesis's own acceptance and server-error checks would not know."""
    # /v2 infer may name exact; /predict with a tolerance sends designs to the exact solver
    solver = name in ("POST /exact", "POST /inverse", "POST /predict") or name.endswith("/infer")
    excluded = [checks.positive_data_acceptance] + ([checks.not_a_server_error] if solver else [])

    @settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
    @given(case=operations[name].as_strategy())  # schema-valid cases
    def run(case):
        response = case.call(base_url=live.url, timeout=60)
        case.validate_response(response, excluded_checks=excluded)
        if response.status_code == 422 and (_arclength_beyond_the_design(case.body)
                                             or _end_beyond_the_design(case.body)
                                             or _actuation_beyond_tendon_loads(case.body)
                                             or _columns_unlike_the_tendons(case.body)):
            return  # bounds across fields (metres within each design's L, ...), which a JSON schema cannot state
        if response.status_code == 422 and _loads_for_a_load_free_operator(case.body):
            assert "takes no external loads" in response.text, (name, response.text[:500])  # naming the field
            return
        assert response.status_code != 422, (name, response.text[:500])
        assert response.status_code not in (500, 502), (name, response.text[:500])

    run()
