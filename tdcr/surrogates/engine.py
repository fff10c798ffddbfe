"""The surrogate engine, shared by ``tdcr predict`` and the service: prepare -> predict -> encode.

* **prepare**: a JSON body, or a ``.npy`` body with its query parameters, to a validated
  :class:`tdcr.api.validation.ShapeRequest`, through the one validation path of :mod:`tdcr.api.validation`;
* **predict**: the request on a surrogate (``Predictor``: a :class:`tdcr.surrogates.runtime.Surrogate`, or the
  service's dynamic batcher in front of one) to a :class:`Prediction`;
* **encode**: a :class:`Prediction` to JSON (``PredictResponse``) or ``.npz`` bytes.

Nothing here knows HTTP: errors are :class:`tdcr.api.validation.InvalidRequest`.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import orjson

from tdcr.api.checks import check_model_loads, loaded_rows
from tdcr.api.schemas import EXACT_MODEL, RESPONSE_FORMAT_VERSION
from tdcr.api.validation import InvalidRequest, Limits, Problem, ShapeRequest, quote, validate_features, validate_json
from tdcr.physics.exact import ExactAnswer
from tdcr.physics.status import STATUS, Status
from tdcr.robot.design_space import N_FEATURES, load_warnings, range_warnings
from tdcr.robot.designs import L_COLUMN, LOAD_COLUMNS, N_LOAD_COLUMNS, ExternalLoads
from tdcr.search.inverse import model_tip_pose, tip_by_differences
from tdcr.surrogates.bounds import EXACT, EXACT_TOLERANCE, SOURCES, Calibration
from tdcr.surrogates.router import Costs, choose, known_bound
from tdcr.surrogates.runtime import finite_rows, keep_tolerance, on_grid_tendons

#: Media types of the binary path.
NPY = "application/x-npy"
NPZ = "application/x-npz"
#: Query parameters of a ``.npy`` request.
QUERY_FIELDS = ("model", "points", "s", "arclength", "outputs", "tolerance")


class Predictor(Protocol):
    """What runs a surrogate: :meth:`tdcr.surrogates.runtime.Surrogate.predict` or a batcher in front of it;
    ``takes_loads`` and ``load_ranges`` as :class:`tdcr.surrogates.runtime.Surrogate`'s."""

    takes_loads: bool
    load_ranges: dict | None

    def predict(self, features: np.ndarray, fractions: np.ndarray, *, loads=None, pose: bool = True,
                check: bool = True) -> dict[str, np.ndarray]: ...


@dataclass(frozen=True)
class Guard:
    """What bounds an operator's answers and keeps a request's tolerance: its ``calibration``
    (:class:`tdcr.surrogates.bounds.Calibration`; None: uncalibrated, so no answer has a finite bound and a
    tolerance sends every design to the solver), the ``companion`` predictor its score needs (None: none),
    and ``exact``: the exact solver's answer (:class:`tdcr.physics.exact.ExactAnswer`) to a sub-request of
    the designs that fall back (:meth:`tdcr.api.validation.ShapeRequest.take`), with whatever admission
    and deadline the caller keeps."""

    calibration: Calibration | None
    companion: Predictor | None
    exact: Callable[[ShapeRequest], ExactAnswer]


def local_guard(surrogate) -> Guard:
    """The :class:`Guard` of a loaded :class:`tdcr.surrogates.runtime.Surrogate` in this process (``tdcr
    predict``): its calibration (if any), its companion and the exact solver here, unlimited."""
    from tdcr.physics.exact import solve_request

    return Guard(calibration=surrogate.calibration, companion=surrogate.companion(), exact=solve_request)


@dataclass(frozen=True)
class Prediction:
    """A surrogate's answer: ``model``; the arclengths as ``fractions`` of L ``(n,)`` and in metres,
    ``arclength`` ``(B, n)``; the wanted ``arrays`` (backbone
    ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)``, tendons ``(B, n, 4, 3)`` m; float32 from the graph,
    float64 where post-processed: the pose fit of tendon models, FNO interpolation off the grid); and per
    design the range ``warnings`` (empty: in distribution) and whether its answer is ``finite``
    (far outside the trained ranges a network can overflow; such rows are zeros)."""

    model: str
    fractions: np.ndarray
    arclength: np.ndarray
    arrays: dict[str, np.ndarray]
    warnings: list[list[str]]
    finite: np.ndarray  # (B,) the answer is finite (else its rows are zeros)
    tip_jacobian: np.ndarray | None = None  # (B, 6, N_t) with "jacobian": true, by central differences
    error_bound: np.ndarray | None = None  # (B,) calibrated 99 % bound of the relative l2 error; inf: none
    source: np.ndarray | None = None  # (B,) int32: 0 the surrogate answered, 1 the exact solver

    @property
    def n_designs(self) -> int:
        return len(self.warnings)

    @property
    def bounds(self) -> np.ndarray:
        """``error_bound``, ``inf`` (none) for every design of a model without a calibration."""
        return np.full(self.n_designs, np.inf) if self.error_bound is None else self.error_bound

    @property
    def sources(self) -> np.ndarray:
        """``source``, 0 (the surrogate) for every design when no tolerance was kept."""
        return np.zeros(self.n_designs, dtype=np.int32) if self.source is None else self.source

    @property
    def n_exact(self) -> int:
        """Designs the exact solver answered."""
        return int((self.sources == EXACT).sum())


def prepare_json(body: bytes | str | dict, *, limits: Limits) -> ShapeRequest:
    """A JSON ``PredictRequest`` (raw bytes or decoded), validated."""
    return validate_json(body, target="surrogate", limits=limits)


def prepare_npy(body: bytes, params: Mapping[str, list[str]], *, limits: Limits) -> ShapeRequest:
    """A ``.npy`` body of raw SI designs ``(B, 15)``, or ``(B, 25)``: each design followed by its
    loads (:data:`tdcr.robot.designs.LOAD_COLUMNS`: gravity, density, tip force, tip moment; for a loaded
    operator), and the query ``params`` (name -> values)."""
    problems = [Problem((k,), "may be given once", "repeated") for k in ("model", "points", "outputs", "tolerance")
                if len(params.get(k, [])) > 1]
    points = _query_int(params, "points", problems)
    tolerance = (_query_floats(params, "tolerance", problems) or [None])[0]
    s = _query_floats(params, "s", problems)
    arclength = _query_floats(params, "arclength", problems)
    if problems:
        raise InvalidRequest(problems)
    features = read_npy(body)
    loads = None
    if features.ndim == 2 and features.shape[1] == N_FEATURES + N_LOAD_COLUMNS:  # designs, then their loads
        features, matrix = features[:, :N_FEATURES], np.asarray(features[:, N_FEATURES:], dtype=np.float64)
        as_loads = ExternalLoads.from_matrix(matrix)
        loads = {name: getattr(as_loads, name) for name in LOAD_COLUMNS}
    outputs = params.get("outputs")
    return validate_features(features, target="surrogate", points=points, s=s, arclength=arclength,
                             model=(params.get("model") or [None])[0],
                             outputs=None if outputs is None else outputs[0].split(","), limits=limits, loads=loads,
                             tolerance=tolerance)


def predict(predictor: Predictor, request: ShapeRequest, *, model: str, guard_with: Guard | None = None
            ) -> Prediction:
    """A validated request on ``predictor`` (the surrogate ``model``); blocking.  A design with loads
    for an operator that takes none is an :class:`InvalidRequest` naming its load field.

    ``guard_with``: the model's :class:`Guard`: every answer gets its ``error_bound``, and with the
    request's ``tolerance`` the designs whose bound exceeds it are the exact solver's (``source``).
    A tolerance without a guard is an :class:`InvalidRequest` naming ``tolerance``."""
    features, loads = request.features, request.loads
    if request.tolerance is not None and guard_with is None:
        raise InvalidRequest([Problem(("tolerance",), f"model {model!r} is run here without an exact solver to "
                                      "keep it with (engine.local_guard)", "tolerance_unguarded")])
    if not predictor.takes_loads:
        problems = check_model_loads(loads, np.arange(len(features)), model=model)
        if problems:
            raise InvalidRequest(problems)
        loads = None
    matrix = None if loads is None else np.nan_to_num(loads.matrix(len(features)))  # (B, 10), the graph's input
    with np.errstate(all="ignore"):  # overflow far outside the trained ranges is reported per design
        out = predictor.predict(features, request.fractions, loads=matrix, pose=request.pose, check=False)  # validated
    arrays = {k: out[k] for k in request.outputs}
    finite = finite_rows(arrays.values(), len(features))
    bounds = source = None
    if guard_with is not None:
        given = np.zeros((len(features), N_LOAD_COLUMNS)) if matrix is None else matrix
        arrays, kept = keep_tolerance(arrays, features, request.fractions, given if predictor.takes_loads else None,
                                      tendons=on_grid_tendons(out, request.fractions), own=predictor.predict,
                                      calibration=guard_with.calibration, companion=guard_with.companion,
                                      tolerance=request.tolerance, finite=finite,
                                      exact=lambda rows: exact_arrays(guard_with.exact(request.take(rows))))
        bounds, source = kept.error_bound, kept.source if request.tolerance is not None else None
        finite = finite | (kept.source == EXACT)
    if not finite.all():
        arrays = {k: np.where(finite.reshape(-1, *[1] * (v.ndim - 1)), v, 0).astype(v.dtype)
                  for k, v in arrays.items()}
    arclength = features[:, L_COLUMN, None] * request.fractions[None, :]
    tip_jacobian = None
    if request.jacobian:
        tip_pose = model_tip_pose(predictor.predict, check=False)  # the differences may leave the bounds
        with np.errstate(all="ignore"):
            tip_jacobian = np.ascontiguousarray(np.nan_to_num(tip_by_differences(features, tip_pose)[2]))
    warnings = range_warnings(features)
    if predictor.takes_loads and predictor.load_ranges is not None:
        given = np.zeros((len(features), N_LOAD_COLUMNS)) if matrix is None else matrix
        warnings = [w + v for w, v in zip(warnings, load_warnings(given, predictor.load_ranges), strict=True)]
    return Prediction(model=model, fractions=request.fractions, arclength=arclength, arrays=arrays,
                      warnings=warnings, finite=finite, tip_jacobian=tip_jacobian, error_bound=bounds, source=source)


def exact_prediction(request: ShapeRequest, answer: ExactAnswer) -> Prediction:
    """The solver's ``answer`` to ``request`` as a :class:`Prediction` of the model ``"exact"``: every
    design's ``source`` the solver, its ``error_bound`` :data:`tdcr.surrogates.bounds.EXACT_TOLERANCE`
    where it converged (``inf`` else, with a warning naming its status)."""
    g = answer.arrays()
    arrays = {"backbone": g.backbone, "rotation": g.rotation, "tendons": g.tendons}
    warnings = [[] if ok else [f"the solver did not converge: {STATUS[k]}"]
                for ok, k in zip(g.converged.tolist(), g.status.tolist(), strict=True)]
    return Prediction(model=EXACT_MODEL, fractions=request.fractions, arclength=g.arclength,
                      arrays={k: arrays[k] for k in request.outputs}, warnings=warnings,
                      finite=g.status != Status.NOT_FINITE.value, tip_jacobian=g.tip_jacobian,
                      error_bound=np.where(g.converged, EXACT_TOLERANCE, np.inf),
                      source=np.full(len(g.converged), EXACT, dtype=np.int32))


@dataclass(frozen=True)
class Operator:
    """An operator a router may answer with: its ``name``, its ``predictor`` and its ``guard``."""

    name: str
    predictor: Predictor
    guard: Guard | None


def route(request: ShapeRequest, *, costs: Costs, operator: Operator | None,
          exact: Callable[[ShapeRequest], ExactAnswer], exact_ready: bool = True) -> Prediction:
    """A request that names no model, by the cheaper path that meets its tolerance
    (:func:`tdcr.surrogates.router.choose`): the exact solver (``exact``, for the whole request) or
    ``operator`` (the default operator for the request's loads; None: the solver only), weighed with
    the operator's bound as known before its graph runs (:func:`tdcr.surrogates.router.known_bound`)."""
    features, loads = request.features, request.loads
    matrix = None if loads is None else np.nan_to_num(loads.matrix(len(features)))
    loaded = np.zeros(len(features), dtype=bool) if matrix is None else loaded_rows(matrix)
    if operator is None:
        bound = np.full(len(features), np.inf)
    else:
        bound = known_bound(None if operator.guard is None else operator.guard.calibration, features,
                            matrix if operator.predictor.takes_loads else None, tolerance=request.tolerance)
    choice = choose(costs, bound, loaded=loaded, tolerance=request.tolerance, operator_ready=operator is not None,
                    exact_ready=exact_ready)
    if choice.path == "exact":
        return exact_prediction(request, exact(request))
    return predict(operator.predictor, request, model=operator.name, guard_with=operator.guard)


def exact_arrays(answer: ExactAnswer) -> dict[str, np.ndarray]:
    """The solver's backbone, rotation and tendons ``(m, n, ...)`` and ``converged`` ``(m,)`` of an
    answer whose designs share one tendon count, in request order."""
    g = answer.arrays()
    return {"backbone": g.backbone, "rotation": g.rotation, "tendons": g.tendons, "converged": g.converged}


def encode_json(prediction: Prediction) -> bytes:
    """``PredictResponse`` JSON (format :data:`tdcr.api.schemas.RESPONSE_FORMAT_VERSION`): per design s
    (fractions of L), arclength (m), backbone, rotation, tendons, in_distribution, warnings, finite,
    error_bound (null: none) and source."""
    arrays = {k: np.ascontiguousarray(v) for k, v in prediction.arrays.items()}  # orjson: C order only
    fractions, arclength = np.ascontiguousarray(prediction.fractions), np.ascontiguousarray(prediction.arclength)
    finite = prediction.finite.tolist()
    bounds = [b if np.isfinite(b) else None for b in prediction.bounds.tolist()]
    sources = [SOURCES[k] for k in prediction.sources.tolist()]
    results = [{"s": fractions, "arclength": arclength[j], **{k: v[j] for k, v in arrays.items()},
                "in_distribution": not w, "warnings": w, "finite": finite[j], "error_bound": bounds[j],
                "source": sources[j]}
               for j, w in enumerate(prediction.warnings)]
    if prediction.tip_jacobian is not None:
        for result, jacobian in zip(results, prediction.tip_jacobian, strict=True):
            result["tip_jacobian"] = jacobian
    return orjson.dumps({"format_version": RESPONSE_FORMAT_VERSION, "model": prediction.model, "results": results},
                        option=orjson.OPT_SERIALIZE_NUMPY)


def encode_npz(prediction: Prediction) -> bytes:
    """An uncompressed ``.npz`` (what ``np.savez`` writes; floats as float32) of s ``(B, n)``
    (fractions of L), arclength ``(B, n)`` m, the wanted arrays, in_distribution, finite,
    error_bound (float32, inf: none) and source (int32: 0 surrogate, 1 exact), each ``(B,)``, each
    member written in one piece: 19-30 ms against 32 ms for ``np.savez``'s chunked writes of an
    8192-design answer."""
    s = np.broadcast_to(prediction.fractions, prediction.arclength.shape)
    arrays = {"s": s, "arclength": prediction.arclength,
              "in_distribution": np.array([not w for w in prediction.warnings]),
              "finite": prediction.finite, "error_bound": prediction.bounds, "source": prediction.sources}
    arrays |= prediction.arrays
    if prediction.tip_jacobian is not None:
        arrays["tip_jacobian"] = prediction.tip_jacobian
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
        for key, value in arrays.items():
            value = np.ascontiguousarray(value, dtype=np.float32 if value.dtype.kind == "f" else value.dtype)
            header = io.BytesIO()
            np.lib.format.write_array_header_2_0(header, np.lib.format.header_data_from_array_1_0(value))
            archive.writestr(f"{key}.npy", b"".join([header.getvalue(), memoryview(value).cast("B")]))
    return buf.getvalue()


def read_npy(body: bytes) -> np.ndarray:
    """The array of a ``.npy`` body, read in place: its header is checked against the body's
    length before anything is allocated (``np.load`` would allocate what the header claims)."""
    buf = io.BytesIO(body)
    fmt = np.lib.format
    try:
        version = fmt.read_magic(buf)
        reader = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
        if reader is None:
            raise ValueError(f"unsupported .npy version {version}")
        shape, fortran_order, dtype = reader(buf, max_header_size=1024)
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as exc:
        raise InvalidRequest([Problem(("designs",), f"not a valid .npy array ({quote(str(exc))})", "npy")]) from None
    count = int(np.prod(shape, dtype=object))
    if dtype.hasobject or count * dtype.itemsize != len(body) - buf.tell():
        raise InvalidRequest([Problem(("designs",), f"not a valid .npy array (header {dtype} {shape} does not "
                                      f"match the {len(body) - buf.tell()} data bytes)", "npy")])
    data = np.frombuffer(body, dtype=dtype, count=count, offset=buf.tell())
    return data.reshape(shape, order="F" if fortran_order else "C")


def _query_int(params: Mapping[str, list[str]], key: str, problems: list[Problem]) -> int | None:
    raw = params.get(key)
    if not raw:
        return None
    try:
        return int(raw[0])
    except ValueError:
        problems.append(Problem((key,), f"must be an integer, got {quote(raw[0])}", "int_parsing"))
        return None


def _query_floats(params: Mapping[str, list[str]], key: str, problems: list[Problem]) -> list[float] | None:
    raw = params.get(key)
    if not raw:
        return None
    values = []
    for i, text in enumerate(raw):
        try:
            values.append(float(text))
        except ValueError:
            problems.append(Problem((key, i), f"must be a number, got {quote(text)}", "float_parsing"))
    return values
