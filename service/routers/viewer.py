"""The 3-D shape viewer: ``GET /`` redirects to ``/viewer/``, a static page (service/static/viewer/)
that draws ``/exact``'s shape with a surrogate's prediction over it.  Its JavaScript is vendored
(no CDN), and every file goes out with a Content-Security-Policy that allows this origin only."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import RedirectResponse
from starlette.staticfiles import StaticFiles

router = APIRouter(tags=["viewer"])
ROOT = Path(__file__).resolve().parents[1] / "static" / "viewer"
MOUNT = "/viewer"
#: The page needs scripts, styles, fetches and WebGL from its own origin only.
SECURITY_HEADERS = {
    "content-security-policy": "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
                               "img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
}
#: Content types by suffix (the platform's mimetypes table may lack or differ on some).
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8",
                 ".md": "text/markdown; charset=utf-8"}


class ViewerFiles(StaticFiles):
    """Starlette's static files with the viewer's security headers and content types."""

    def file_response(self, full_path, stat_result, scope, status_code=200):
        response = super().file_response(full_path, stat_result, scope, status_code)
        response.headers.update(SECURITY_HEADERS)
        media_type = CONTENT_TYPES.get(Path(full_path).suffix)
        if media_type:
            response.headers["content-type"] = media_type
        return response


@router.get("/", summary="The 3-D shape viewer (redirects to /viewer/)", include_in_schema=False)
def home() -> RedirectResponse:
    return RedirectResponse(MOUNT + "/", status_code=307)


def mount(app) -> None:
    """Serve the viewer's files under :data:`MOUNT`."""
    app.mount(MOUNT, ViewerFiles(directory=ROOT, html=True), name="viewer")
