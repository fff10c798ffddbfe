"""What the JSON routes of the service's own API share: a JSON body to the data plane with the
route's codec, and the data plane's errors as HTTP errors (service/errors.py)."""

from __future__ import annotations

from fastapi import Request, Response

from service.errors import from_inference, require_json
from service.metrics import HTTP
from service.model import Codec, InferenceError, InferenceRequest, Kind
from service.state import ServiceState

#: The 503 of a route that runs the solver (the OpenAPI description).
UNAVAILABLE = "the solver is saturated or still starting: retry after the Retry-After header's seconds"


async def answer(request: Request, state: ServiceState, codec: Codec, *, kind: Kind, endpoint: str) -> Response:
    """The JSON body (415 unless declared JSON) on the default model of ``kind``."""
    require_json(request.headers.get("content-type", ""))
    body = await request.body()
    try:
        answer = await state.plane.infer(None, InferenceRequest(body, codec), kind=kind, protocol=HTTP,
                                         endpoint=endpoint)
    except InferenceError as exc:
        raise from_inference(exc) from None
    return Response(answer.body, media_type="application/json")
