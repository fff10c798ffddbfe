"""The Open Inference Protocol v2 over gRPC, against a real server process: the wire format against
the specification's (as Triton's client compiles it), health and reflection, inference on every
model equal to /predict and /exact, typed and raw tensors, status codes that name the tensor and
the reason, and Triton's own gRPC client in its own process (its stubs and ours, compiled from the
same ``.proto`` package, cannot share one)."""

from __future__ import annotations

import filecmp
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import grpc
import httpx
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from service.model import RETRY_SATURATED_S
from service.process import ServerProcess
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc
from tdcr.physics import solve
from tdcr.robot.design_space import sample_designs
from tdcr.robot.designs import DesignBatch

MODELS = ["deeponet", "deeponet_pose", "fno", "fno_pose"]
SERVICE = "inference.GRPCInferenceService"
#: The server's gRPC request limit in this module's server.
MAX_RECEIVE = 200_000
Tensor = pb.ModelInferRequest.InferInputTensor
Output = pb.ModelInferRequest.InferRequestedOutputTensor


@pytest.fixture(scope="module")
def server(tiny_models):
    srv = ServerProcess(tiny_models[1], max_designs=500, grpc_max_receive_bytes=MAX_RECEIVE,
                        wait_for_paths=("loaded",))
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def stub(server):
    with grpc.insecure_channel(server.grpc_target) as channel:
        yield pb_grpc.GRPCInferenceServiceStub(channel)


def _request(model: str, features: np.ndarray, *, raw: bool = True, outputs=(), **extra) -> pb.ModelInferRequest:
    """A ``ModelInferRequest`` of ``design`` (and ``extra`` FP64 inputs), raw or typed."""
    inputs = {"design": features} | extra
    tensors = [Tensor(name=n, datatype="FP64", shape=np.shape(v)) for n, v in inputs.items()]
    if not raw:
        for t, v in zip(tensors, inputs.values(), strict=True):
            t.contents.fp64_contents.extend(np.ravel(v).tolist())
    return pb.ModelInferRequest(model_name=model, inputs=tensors, outputs=[Output(name=o) for o in outputs],
                                raw_input_contents=[np.asarray(v, "<f8").tobytes() for v in inputs.values()]
                                if raw else [])


def _outputs(response: pb.ModelInferResponse) -> dict[str, np.ndarray]:
    dtypes = {"FP32": "<f4", "FP64": "<f8", "BOOL": "?", "INT32": "<i4"}
    fields = {"FP32": "fp32_contents", "FP64": "fp64_contents", "BOOL": "bool_contents", "INT32": "int_contents"}
    out = {}
    for i, t in enumerate(response.outputs):
        if response.raw_output_contents:
            values = np.frombuffer(response.raw_output_contents[i], dtype=dtypes[t.datatype])
        else:
            values = np.array(getattr(t.contents, fields[t.datatype]), dtype=dtypes[t.datatype])
        out[t.name] = values.reshape(tuple(t.shape))
    return out


def _body(features: np.ndarray) -> dict:
    return {"designs": DesignBatch.from_features(features).to_dicts()}


def test_committed_stubs_match_the_proto(root, tmp_path):
    """The committed stubs are what scripts/generate-grpc.sh makes of the committed .proto."""
    done = subprocess.run(["bash", "scripts/generate-grpc.sh", str(tmp_path)], cwd=root, capture_output=True,
                          text=True, env={"PYTHON": sys.executable, "PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 0, done.stderr
    generated = sorted(p.name for p in (tmp_path / "tdcr" / "oip_grpc").iterdir())
    assert generated == ["open_inference_grpc_pb2.py", "open_inference_grpc_pb2.pyi", "open_inference_grpc_pb2_grpc.py"]
    match, mismatch, errors = filecmp.cmpfiles(tmp_path / "tdcr" / "oip_grpc", root / "tdcr" / "oip_grpc", generated,
                                               shallow=False)
    assert not mismatch and not errors, "run scripts/generate-grpc.sh and commit the stubs"


_DESCRIBE = """
import json, sys
from google.protobuf import descriptor_pool
{imports}
pool = descriptor_pool.Default()
messages = {{}}
def walk(d):
    messages[d.full_name] = sorted((f.name, f.number, f.type, f.label if hasattr(f, "label") else 0,
                                    f.message_type.full_name if f.message_type else "") for f in d.fields)
    for n in d.nested_types:
        walk(n)
for name in {names!r}:
    walk(pool.FindMessageTypeByName(name))
service = pool.FindServiceByName("inference.GRPCInferenceService")
methods = {{m.name: (m.input_type.full_name, m.output_type.full_name) for m in service.methods
           if m.name in {methods!r}}}
print(json.dumps({{"messages": messages, "methods": methods}}))
"""


def test_wire_format_matches_the_specification(root):
    """Every message, field (name, number, type) and method of our .proto as Triton's client compiles
    the same protocol: each side described in its own process."""
    methods = [m.name for m in pb.DESCRIPTOR.services_by_name["GRPCInferenceService"].methods]
    names = [m.full_name for m in pb.DESCRIPTOR.message_types_by_name.values()]
    assert len(methods) == 6 and len(names) == 14
    described = {}
    for side, imports in (("ours", "import tdcr.oip_grpc.open_inference_grpc_pb2"),
                          ("triton", "import tritonclient.grpc.service_pb2")):
        code = _DESCRIBE.format(imports=imports, names=names, methods=methods)
        done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-2000:]
        described[side] = json.loads(done.stdout)
    assert described["ours"] == described["triton"]
    assert len(described["ours"]["messages"]) > len(names)  # nested messages compared too


def test_raw_answers_are_the_bytes_protobuf_writes():
    """The hand-written raw encoding (one copy of each array) equals protobuf's serialisation of the
    same message, for every output datatype and for buffers past one varint byte."""
    from service.grpc_server import encode_raw

    rng = np.random.default_rng(0)
    tensors = {"tendons": ("FP32", rng.normal(size=(3, 7, 4, 3))), "in_distribution": ("BOOL", np.array([1, 0, 1])),
               "residual": ("FP64", rng.normal(size=3)), "big": ("FP32", rng.normal(size=(300, 100)))}
    message = pb.ModelInferResponse(model_name="m", model_version="1", id="x")
    for name, (datatype, array) in tensors.items():
        message.outputs.add(name=name, datatype=datatype, shape=np.shape(array))
        message.raw_output_contents.append(np.asarray(array, {"FP32": "<f4", "FP64": "<f8", "BOOL": "?"}[datatype])
                                           .tobytes())
    assert encode_raw("m", tensors, request_id="x") == message.SerializeToString()


def test_health_reflection_and_metadata(server, stub):
    with grpc.insecure_channel(server.grpc_target) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        for service in ("", SERVICE):
            assert health.Check(health_pb2.HealthCheckRequest(service=service)).status == \
                health_pb2.HealthCheckResponse.SERVING
        reflect = reflection_pb2_grpc.ServerReflectionStub(channel)
        answer = next(reflect.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")])))
        assert {s.name for s in answer.list_services_response.service} >= {SERVICE, "grpc.health.v1.Health"}
    assert stub.ServerLive(pb.ServerLiveRequest()).live and stub.ServerReady(pb.ServerReadyRequest()).ready
    meta = stub.ServerMetadata(pb.ServerMetadataRequest())
    assert meta.name == "tdcr-surrogates" and "binary_tensor_data" in meta.extensions
    rest = httpx.get(server.url + "/v2/models/fno").json()
    for model in [*MODELS, "exact"]:
        for version in ("", "1"):
            assert stub.ModelReady(pb.ModelReadyRequest(name=model, version=version)).ready
            meta, call = stub.ModelMetadata.with_call(pb.ModelMetadataRequest(name=model, version=version))
            assert meta.name == model and list(meta.versions) == ["1"]
            assert [t.name for t in meta.inputs][:2] == ["design", "s"]
            # the operators take 4 tendons; the exact model any number (and their layout)
            assert list(meta.inputs[0].shape) == ([-1, -1] if model == "exact" else [-1, 15])
            assert meta.inputs[0].datatype == "FP64"
            assert {t.name: t.datatype for t in meta.outputs}["tendons"] == "FP32"
    _, call = stub.ModelMetadata.with_call(pb.ModelMetadataRequest(name="fno"))
    assert dict(call.trailing_metadata())["tdcr-sha256"] == rest["parameters"]["sha256"]
    for bad in (pb.ModelMetadataRequest(name="nope"), pb.ModelMetadataRequest(name="fno", version="2")):
        with pytest.raises(grpc.RpcError) as err:
            stub.ModelMetadata(bad)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("raw", [True, False])
def test_inference_equals_predict(server, stub, model, raw):
    features = sample_designs(5, seed=8).features()
    s = np.linspace(0.0, 1.0, 11)
    response = stub.ModelInfer(_request(model, features, raw=raw, s=s))
    assert response.model_name == model and bool(response.raw_output_contents) == raw
    out = _outputs(response)
    ref = httpx.post(server.url + "/predict", json=_body(features) | {"model": model, "s": s.tolist()}).json()
    for name in ("backbone", "rotation", "tendons"):
        np.testing.assert_allclose(out[name], np.array([r[name] for r in ref["results"]]), rtol=1e-6, atol=1e-9)
    assert out["in_distribution"].tolist() == [r["in_distribution"] for r in ref["results"]]
    assert out["tendons"].dtype == np.float32 and out["tendons"].shape == (5, 11, 4, 3)


def test_the_solver_as_a_model_equals_exact(server, stub):
    features = sample_designs(2, seed=9).features()
    gravity = np.array([[0.0, 0.0, -9.81], [9.81, 0.0, 0.0]])
    response = stub.ModelInfer(_request("exact", features, outputs=["tendons", "converged", "residual"],
                                        gravity=gravity, density=np.array([7800.0, 6500.0])))
    out = _outputs(response)
    designs = _body(features)["designs"]
    for d, g, rho in zip(designs, gravity.tolist(), (7800.0, 6500.0), strict=True):
        d |= {"gravity": g, "density": rho}
    r = httpx.post(server.url + "/exact", json={"designs": designs}, timeout=60)
    assert r.status_code == 200, r.text
    ref = r.json()["results"]
    np.testing.assert_allclose(out["tendons"], np.array([x["tendons"] for x in ref]), rtol=1e-6, atol=1e-9)
    assert set(out) == {"tendons", "converged", "residual"} and out["converged"].all()
    assert out["residual"].dtype == np.float64
    status = _outputs(stub.ModelInfer(_request("exact", features, outputs=["status", "error_estimate"],
                                               gravity=gravity, density=np.array([7800.0, 6500.0]))))
    assert status["status"].dtype == np.int32 and status["status"].tolist() == [0, 0]
    np.testing.assert_allclose(status["error_estimate"], [x["error_estimate"] for x in ref], rtol=1e-12)


def test_bad_tensors_get_a_clear_status(stub):
    good = sample_designs(2, seed=0).features()
    nan = good.copy()
    nan[0, 0] = np.nan
    invalid = grpc.StatusCode.INVALID_ARGUMENT
    wrong_size = _request("fno", good)
    wrong_size.raw_input_contents[0] = wrong_size.raw_input_contents[0][:-8]
    wrong_type = _request("fno", good)
    wrong_type.inputs[0].datatype = "INT32"
    wrong_name = _request("fno", good)
    wrong_name.inputs[0].name = "designs"
    cases = [
        (wrong_name, invalid, "unexpected input 'designs'"),
        (_request("fno", good[:, :14]), invalid, "input 'design': shape must be [-1, 15]"),
        (wrong_type, invalid, "input 'design': datatype must be one of"),
        (wrong_size, invalid, "input 'design': 232 raw bytes do not match its shape [2, 15]"),
        (_request("fno", nan), invalid, "designs[0].E: must be a finite number, got nan"),
        (_request("fno", np.tile(good[0], (501, 1))), invalid, "501 designs exceed the limit of 500"),
        (_request("fno", good, outputs=["everything"]), invalid, "unknown output 'everything'"),
        (pb.ModelInferRequest(model_name="fno"), invalid, "missing input(s) ['design']"),
        (_request("nope", good), grpc.StatusCode.NOT_FOUND, "unknown model 'nope'"),
        (_request("fno", np.tile(good[0], (MAX_RECEIVE // 120 + 1, 1))), grpc.StatusCode.RESOURCE_EXHAUSTED, ""),
    ]
    for request, code, message in cases:
        with pytest.raises(grpc.RpcError) as err:
            stub.ModelInfer(request)
        assert err.value.code() == code, (message, err.value.details())
        assert message in err.value.details()


def test_saturated_and_late_solver_calls(tiny_models):
    """Slow loaded solves against a 1 s deadline and one solver slot: one call runs past the deadline
    (DEADLINE_EXCEEDED), the other finds the slot taken (RESOURCE_EXHAUSTED, with the server's
    pushback of 1 s: ``grpc-retry-pushback-ms``); the server goes on."""
    heavy = sample_designs(200, seed=3).features()  # 200 loaded designs at 400 points: seconds of the compiled solver
    slow = _request("exact", heavy, s=np.linspace(0.0, 1.0, 400), gravity=np.tile([0.0, 9.81, 0.0], (200, 1)),
                    density=np.full(200, 7800.0))
    with ServerProcess(tiny_models[1], exact_timeout_s=1, exact_max_pending=1, exact_admission_factor=100,
                       wait_for_paths=("loaded",)) as srv:
        with grpc.insecure_channel(srv.grpc_target) as channel:
            infer = pb_grpc.GRPCInferenceServiceStub(channel).ModelInfer

            pushbacks = []

            def call(request):
                try:
                    infer(request, timeout=60)
                    return grpc.StatusCode.OK
                except grpc.RpcError as exc:
                    if exc.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                        pushbacks.append(dict(exc.trailing_metadata()).get("grpc-retry-pushback-ms"))
                    return exc.code()

            with ThreadPoolExecutor(1) as pool:
                first = pool.submit(call, slow)
                codes = []  # calls while the first runs: refused once it holds the slot
                while not first.done() and grpc.StatusCode.RESOURCE_EXHAUSTED not in codes:
                    codes.append(call(slow))
                codes.append(first.result())
            assert grpc.StatusCode.RESOURCE_EXHAUSTED in codes and grpc.StatusCode.DEADLINE_EXCEEDED in codes, codes
            assert pushbacks and set(pushbacks) == {str(1000 * RETRY_SATURATED_S)}, pushbacks
            assert infer(_request("fno", heavy[:2])).model_name == "fno"


def test_tritonclient_grpc(server, run_triton_example):
    """Triton's gRPC client, in its own process: raw tensors in and out on every model."""
    run_triton_example("grpc", server.grpc_target, server.url, MODELS)


def test_metrics_are_labelled_by_protocol(server, stub):
    stub.ModelInfer(_request("deeponet", sample_designs(1, seed=1).features()))
    text = httpx.get(server.url + "/metrics").text
    assert 'tdcr_requests_total{endpoint="ModelInfer",protocol="grpc",status="OK"}' in text
    assert 'tdcr_designs_total{endpoint="ModelInfer",model="deeponet",protocol="grpc"}' in text
    assert 'tdcr_errors_total{endpoint="ModelInfer",kind="not_found",protocol="grpc"}' in text


def test_loadtest_speaks_grpc(server, root):
    done = subprocess.run([sys.executable, "-m", "tdcr.cli", "loadtest", "--url", server.url, "--protocol", "grpc",
                           "--grpc-target", server.grpc_target, "--concurrency", "1,4", "--batch", "1,32",
                           "--requests", "30", "--seconds", "5"],
                          capture_output=True, text=True, cwd=root, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("| grpc raw |") == 4


def test_api_keys_guard_grpc_too(tiny_models):
    """With TDCR_API_KEYS, gRPC inference and metadata need a key as HTTP does; health stays open."""
    features = sample_designs(1, seed=2).features()
    with ServerProcess(tiny_models[1], api_keys='["k1"]') as srv, grpc.insecure_channel(srv.grpc_target) as channel:
        stub = pb_grpc.GRPCInferenceServiceStub(channel)
        assert stub.ServerLive(pb.ServerLiveRequest()).live and stub.ServerReady(pb.ServerReadyRequest()).ready
        assert health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=SERVICE)).status == \
            health_pb2.HealthCheckResponse.SERVING
        for metadata in ((), (("x-api-key", "nope"),)):
            for call, request in ((stub.ModelInfer, _request("fno", features)),
                                  (stub.ModelMetadata, pb.ModelMetadataRequest(name="fno"))):
                with pytest.raises(grpc.RpcError) as err:
                    call(request, metadata=metadata)
                assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
        for metadata in ((("x-api-key", "k1"),), (("authorization", "Bearer k1"),)):
            assert stub.ModelInfer(_request("fno", features), metadata=metadata).model_name == "fno"


def test_inverse_kinematics_as_a_v2_model(server, stub):
    """The model ``inverse``: one design, target positions (and directions); tensions, tips, errors and
    a status code (0 reached) over gRPC, equal to POST /inverse over REST."""
    design = sample_designs(1, seed=12)
    targets = solve(design, np.array([1.0]))
    position, direction = targets.backbone[:, -1], targets.rotation[:, -1, :, 2]
    start = DesignBatch.from_features(design.features() * np.r_[np.ones(11), np.zeros(4)])  # tensions 0
    request = _request("inverse", start.features(), position=position, direction=direction)
    out = _outputs(stub.ModelInfer(request))
    rest = httpx.post(server.url + "/inverse", json={"design": start.to_dicts()[0], "targets": [
        {"position": position[0].tolist(), "direction": direction[0].tolist()}]}, timeout=60).json()["results"][0]
    assert out["status"].tolist() == [0] and rest["status"] == "reached"
    np.testing.assert_allclose(out["tensions"][0], rest["tensions"], rtol=1e-12, atol=1e-12)
    assert out["error"][0] <= 1e-4 * design.L[0]
    meta = stub.ModelMetadata(pb.ModelMetadataRequest(name="inverse"))
    assert [t.name for t in meta.inputs] == ["design", "position", "direction", "tension_max"]
    with pytest.raises(grpc.RpcError) as err:
        stub.ModelInfer(_request("inverse", start.features()))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "missing input(s) ['position']" in \
        err.value.details()


@pytest.mark.parametrize("model", ["deeponet", "exact"])
def test_fractions_within_rounding_are_clamped_and_beyond_refused(stub, model):
    """A client's s / L is 1.0000000000015 at the tip: accepted and clamped; 1 + 1e-8 is not."""
    features = sample_designs(2, seed=3).features()
    clamped = _outputs(stub.ModelInfer(_request(model, features, outputs=["tendons"], s=np.array([0.0, 0.5,
                                                                                                 1 + 1.5e-12]))))
    exact = _outputs(stub.ModelInfer(_request(model, features, outputs=["tendons"], s=np.array([0.0, 0.5, 1.0]))))
    np.testing.assert_array_equal(clamped["tendons"], exact["tendons"])
    with pytest.raises(grpc.RpcError) as err:
        stub.ModelInfer(_request(model, features, outputs=["tendons"], s=np.array([0.0, 0.5, 1 + 1e-8])))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "s[2]: must be a fraction of L in [0, 1]" in err.value.details()


def test_the_codec_peeks_at_designs_tolerance_and_loads_without_decoding():
    from service.grpc_codec import GrpcCodec
    from service.model import Peek

    codec, features = GrpcCodec(), sample_designs(3, seed=1).features()
    assert codec.peek(_request("auto", features)) == Peek(designs=3, tolerance=False, loads=False)
    loaded = _request("auto", features[:1], tip_force=np.zeros((1, 3)))
    assert codec.peek(loaded) == Peek(designs=1, tolerance=False, loads=True)
    asked = _request("auto", features[:2])
    asked.parameters["tolerance"].double_param = 0.01
    assert codec.peek(asked).tolerance
    assert codec.peek(_request("auto", features[0])) is None  # one dimension: decode refuses it, by name
    assert codec.peek(pb.ModelInferRequest(model_name="auto")) is None


def test_the_data_plane_answers_a_short_request_on_the_event_loop_only_when_nothing_else_is_in_flight():
    """A model that :meth:`answers_inline` is run on the loop's own thread when no inference is in
    flight, and on a worker thread (its ``infer``) while another one is."""
    import asyncio
    import threading

    from starlette.concurrency import run_in_threadpool

    from service.dataplane import DataPlane
    from service.metrics import Metrics
    from service.model import InferenceRequest, InferenceResponse, Model, ModelRepository

    class Echo(Model):
        name, kind, platform, inputs, outputs, blocking = "echo", "surrogate", "test", {}, {}, True

        def answers_inline(self, request):
            return request.payload == "short"

        async def infer(self, request):
            return await run_in_threadpool(self.infer_blocking, request)

        def infer_blocking(self, request):
            if request.payload == "slow":
                assert release.wait(30.0), "never released"
            return InferenceResponse(threading.get_ident(), 1)

    release = threading.Event()  # the slow inference holds its worker thread until then

    repository = ModelRepository()
    repository.register(Echo())
    plane = DataPlane(repository, Metrics.create())

    async def main():
        loop_thread = threading.get_ident()
        ask = lambda payload: plane.infer("echo", InferenceRequest(payload, None), protocol="grpc",  # noqa: E731
                                          endpoint="ModelInfer")
        alone = (await ask("short")).body
        long = (await ask("long")).body
        slow = asyncio.ensure_future(ask("slow"))
        while plane.in_flight == 0:  # until the slow inference is in flight (a failure ends it: no hang)
            assert not slow.done(), "the slow inference ended before it was in flight"
            await asyncio.sleep(0)
        beside = (await ask("short")).body
        release.set()
        await slow
        return loop_thread, alone, long, beside

    loop_thread, alone, long, beside = asyncio.run(main())
    assert alone == loop_thread
    assert long != loop_thread and beside != loop_thread
    assert plane.in_flight == 0
