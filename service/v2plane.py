"""The Open Inference Protocol's models, transport-neutral: what the REST routes (service/routers/v2.py)
and the gRPC servicer (service/grpc_server.py) both call.

Every manifest operator is a model, the physics solver is the model ``exact`` and its inverse
kinematics (POST /inverse with the exact model) the model ``inverse``; each has the
single version ``"1"``.  Inputs arrive decoded (:class:`service.oip.InferRequest`) and leave as
tensors ``name -> (datatype, array)``; errors are :class:`service.oip.OipError` with a kind that
each transport maps to its own status.
"""

from __future__ import annotations

import numpy as np
import orjson

import tdcr
from service.dataplane import ModelNotFound
from service.oip import (
    EXACT_OUTPUTS,
    INVERSE_INPUTS,
    INVERSE_OUTPUTS,
    INVERSE_STATUS,
    LOAD_INPUTS,
    SURROGATE_INPUTS,
    SURROGATE_OUTPUTS,
    InferRequest,
    OipError,
)
from service.solver_pool import WorkerDied
from service.state import ServiceState
from tdcr.design_space import range_warnings
from tdcr.designs import DesignBatch
from tdcr.exact import TooMuchWork
from tdcr.physics import STATUS
from tdcr.schemas import EXACT_MODEL
from tdcr.validation import OUTPUTS, InvalidRequest, validate_features

#: The solver's model name, the inverse-kinematics model's, and the one version of every model.
EXACT = EXACT_MODEL
INVERSE = "inverse"
SOLVER_MODELS = (EXACT, INVERSE)
VERSION = "1"
EXACT_INPUTS = SURROGATE_INPUTS | LOAD_INPUTS
#: What the server says of itself (OIP server metadata).
SERVER_NAME = "tdcr-surrogates"
EXTENSIONS = ["binary_tensor_data"]

#: Output tensors: name -> (datatype, array).
Tensors = dict[str, tuple[str, np.ndarray]]


class V2Plane:
    """Health, metadata and inference of the v2 models of one service ``state``."""

    def __init__(self, state: ServiceState):
        self.state = state

    # -- health and metadata ------------------------------------------------------------------

    def server_ready(self) -> bool:
        return self.state.ready and self.state.pool_healthy

    def server_metadata(self) -> dict:
        return {"name": SERVER_NAME, "version": tdcr.__version__, "extensions": EXTENSIONS}

    def check_model(self, model: str, version: str | None) -> None:
        """:class:`OipError` ``not_found`` unless ``model`` is loaded and ``version`` is empty or ``"1"``."""
        if model not in SOLVER_MODELS and model not in self.state.models:
            raise OipError("not_found", f"unknown model {model[:64]!r}; available: "
                                        f"{sorted(self.state.models) + list(SOLVER_MODELS)}")
        if version not in (None, "", VERSION):
            raise OipError("not_found", f"model {model!r} has only version {VERSION}, not {version[:16]!r}")

    def model_ready(self, model: str, version: str | None = None) -> bool:
        self.check_model(model, version)
        return self.state.pool_healthy if model in SOLVER_MODELS else True

    @staticmethod
    def tensors(model: str) -> tuple[dict, dict, tuple[str, ...]]:
        """The ``(inputs, outputs, required inputs)`` of ``model``; specifications name -> (datatype, shape)."""
        if model == INVERSE:
            return INVERSE_INPUTS, INVERSE_OUTPUTS, ("design", "position")
        if model == EXACT:
            return EXACT_INPUTS, EXACT_OUTPUTS, ("design",)
        return SURROGATE_INPUTS, SURROGATE_OUTPUTS, ("design",)

    def model_metadata(self, model: str, version: str | None = None) -> dict:
        """Name, versions, platform, inputs and outputs (name, datatype, shape) and parameters: the
        manifest's sha256, architecture, kind, metrics and ranges (the last two as JSON text)."""
        self.check_model(model, version)
        inputs, outputs, _ = self.tensors(model)
        meta = {"name": model, "versions": [VERSION],
                "inputs": [{"name": n, "datatype": d, "shape": s} for n, (d, s) in inputs.items()],
                "outputs": [{"name": n, "datatype": d, "shape": s} for n, (d, s) in outputs.items()]}
        if model in SOLVER_MODELS:
            extra = {"status": orjson.dumps(INVERSE_STATUS).decode()} if model == INVERSE else {}
            return meta | {"platform": "tdcr_cosserat_solver",
                           "parameters": {"deadline_s": self.state.settings.exact_timeout_s} | extra}
        entry = self.state.manifest["models"][model]
        return meta | {"platform": "onnxruntime_onnx",
                       "parameters": {"sha256": entry["sha256"], "architecture": entry["architecture"],
                                      "kind": entry["kind"], "metrics": orjson.dumps(entry.get("metrics")).decode(),
                                      "ranges": orjson.dumps(entry.get("ranges")).decode()}}

    # -- inference ----------------------------------------------------------------------------

    def surrogate(self, model: str, request: InferRequest) -> tuple[Tensors, int]:
        """The wanted output tensors of an operator, and the number of designs (blocking: run it
        off the event loop)."""
        arrays_wanted = [n for n in request.outputs if n in OUTPUTS]
        try:
            shape_request = validate_features(request.inputs["design"], target="surrogate", model=model,
                                              s=request.inputs.get("s"), outputs=arrays_wanted or ["tendons"],
                                              limits=self.state.settings.predict_limits())
            prediction = self.state.dataplane.run(shape_request)
        except InvalidRequest as exc:
            raise OipError("too_large" if exc.too_large else "invalid",
                           f"input 'design' or 's': {exc.message}") from None
        except ModelNotFound as exc:
            raise OipError("not_found", str(exc)) from None
        values = {"in_distribution": ("BOOL", np.array([not w for w in prediction.warnings]))}
        values |= {k: ("FP32", v) for k, v in prediction.arrays.items()}
        return {n: values[n] for n in request.outputs}, len(prediction.s)

    @staticmethod
    def solve_body(request: InferRequest) -> tuple[np.ndarray, bytes]:
        """The designs ``(B, 15)`` of a decoded ``exact`` request, and the equivalent JSON
        ``SolveRequest`` of /exact (which the solver process validates)."""
        features = np.asarray(request.inputs["design"], dtype=np.float64)
        designs = DesignBatch.from_features(features).to_dicts()
        for name in LOAD_INPUTS:
            if name in request.inputs:
                values = request.inputs[name]
                if len(values) != len(designs):
                    raise OipError("invalid", f"input {name!r} has {len(values)} rows, 'design' has {len(designs)}")
                for d, v in zip(designs, values.tolist(), strict=True):
                    d[name] = v
        body = {"designs": designs} | ({"s": request.inputs["s"].tolist()} if "s" in request.inputs else {})
        return features, orjson.dumps(body)

    @staticmethod
    def inverse_body(request: InferRequest) -> bytes:
        """The JSON ``InverseRequest`` (model exact) of a decoded ``inverse`` request."""
        design = DesignBatch.from_features(np.asarray(request.inputs["design"], dtype=np.float64)).to_dicts()[0]
        positions = request.inputs["position"]
        directions = request.inputs.get("direction")
        if directions is not None and len(directions) != len(positions):
            raise OipError("invalid", f"input 'direction' has {len(directions)} rows, 'position' has {len(positions)}")
        targets = [{"position": p} for p in positions.tolist()]
        if directions is not None:
            for target, d in zip(targets, directions.tolist(), strict=True):
                target["direction"] = d
        body = {"design": design, "targets": targets, "model": EXACT}
        if "tension_max" in request.inputs:
            body["tension_max"] = float(request.inputs["tension_max"][0])
        return orjson.dumps(body)

    def solver_body(self, model: str, request: InferRequest) -> tuple[np.ndarray | None, bytes]:
        """The designs (``exact``) and the JSON body a solver process validates and answers."""
        return (None, self.inverse_body(request)) if model == INVERSE else self.solve_body(request)

    async def solver(self, model: str, request: InferRequest, features: np.ndarray | None,
                     body: bytes) -> tuple[Tensors, int]:
        """``exact`` or ``inverse`` on ``body`` (from :meth:`solver_body`), within /exact's bounded
        pool and deadline."""
        if model == INVERSE:
            results = await self._in_pool(self.state.inverse_json, body)
            values = {"tensions": ("FP64", np.array([r["tensions"] for r in results])),
                      "position": ("FP64", np.array([r["position"] for r in results])),
                      "error": ("FP64", np.array([r["error"] for r in results])),
                      "status": ("INT32", np.array([INVERSE_STATUS[r["status"]] for r in results]))}
            return {n: values[n] for n in request.outputs}, len(results)
        return await self.exact(request, features, body)

    async def _in_pool(self, call, body: bytes) -> list[dict]:
        """``call(body)`` in a solver process, with /exact's slots; its errors as :class:`OipError`."""
        state = self.state
        if state.pool is None or state.exact_slots is None:
            raise OipError("unavailable", "the solver pool is not running")
        if state.exact_slots.locked():
            raise OipError("saturated", "the solver is saturated; retry later")
        async with state.exact_slots:
            try:
                return await call(body)
            except InvalidRequest as exc:
                raise OipError("too_large" if exc.too_large else "invalid", f"inputs: {exc.message}") from None
            except TooMuchWork as exc:
                raise OipError("too_large", str(exc)) from None
            except TimeoutError:
                raise OipError("deadline", f"the solver did not finish within {state.settings.exact_timeout_s} s"
                               ) from None
            except (WorkerDied, RuntimeError):
                raise OipError("unavailable", "the solver failed on this request; retry later") from None

    async def exact(self, request: InferRequest, features: np.ndarray, body: bytes) -> tuple[Tensors, int]:
        """The solver's shapes for ``body`` (from :meth:`solve_body`)."""
        results = await self._in_pool(self.state.solve_json, body)
        values = {"backbone": ("FP32", np.array([r["backbone"] for r in results])),
                  "rotation": ("FP32", np.array([r["rotation"] for r in results])),
                  "tendons": ("FP32", np.array([r["tendons"] for r in results])),
                  "in_distribution": ("BOOL", np.array([not w for w in range_warnings(features)])),
                  "converged": ("BOOL", np.array([r["converged"] for r in results])),
                  "residual": ("FP64", np.array([r["residual"] for r in results])),
                  "status": ("INT32", np.array([STATUS.index(r["status"]) for r in results], dtype=np.int32)),
                  "error_estimate": ("FP64", np.array([-1.0 if r.get("error_estimate") is None
                                                       else r["error_estimate"] for r in results]))}
        return {n: values[n] for n in request.outputs}, len(results)
