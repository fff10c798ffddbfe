"""The 3-D shape viewer (GET / -> /viewer/): its files, headers and vendored JavaScript over HTTP, and
the page itself in a real headless Chromium (Debian's, driven by Playwright): a slider moved by
keyboard updates both shapes, the canvas is drawn, and the error shown equals the one computed
here from /predict and /exact for the same design, beside the operator's calibrated bound."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import time

import httpx
import numpy as np
import pytest

from service.process import ServerProcess
from tdcr.metrics import relative_l2

VENDOR = ("three.min.js", "OrbitControls.js")
#: Chromium in a container: software WebGL, no sandbox (we run as root in CI).
CHROMIUM_ARGS = ["--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]


@pytest.fixture(scope="module")
def server():
    from tdcr.surrogates.runtime import DEFAULT_MODELS_DIR

    srv = ServerProcess(DEFAULT_MODELS_DIR, wait_for_paths=("loaded",))  # the shipped models: calibrated bounds
    yield srv
    srv.stop()


def test_files_headers_and_redirect(server, root):
    home = httpx.get(server.url + "/")
    assert home.status_code == 307 and home.headers["location"] == "/viewer/"
    types = {"/viewer/": "text/html", "/viewer/viewer.js": "text/javascript", "/viewer/viewer.css": "text/css",
             "/viewer/vendor/three.min.js": "text/javascript", "/viewer/vendor/OrbitControls.js": "text/javascript"}
    for path, media in types.items():
        r = httpx.get(server.url + path)
        assert r.status_code == 200 and r.headers["content-type"].startswith(media), (path, r.headers)
        csp = r.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "default-src 'none'" in csp and "unsafe" not in csp
        assert r.headers["x-content-type-options"] == "nosniff"
    assert httpx.get(server.url + "/viewer/../settings.py").status_code == 404
    assert httpx.get(server.url + "/design-space").json()["parameters"]["tension"]["table_i"] == [0.0, 5.0]


def test_vendored_javascript_is_what_its_readme_says(root):
    folder = root / "service" / "static" / "viewer" / "vendor"
    readme = (folder / "README.md").read_text()
    for name in VENDOR:
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() in readme, name
    assert "MIT" in readme and (folder / "LICENSE.three.txt").exists()
    html = (root / "service" / "static" / "viewer" / "index.html").read_text()
    assert "http://" not in html and "https://" not in html  # no CDN


def _chromium() -> str:
    """The system Chromium, installed from Debian's packages when missing and possible."""
    found = shutil.which("chromium")
    if found is None and os.geteuid() == 0 and shutil.which("apt-get"):
        subprocess.run(["apt-get", "install", "-y", "-q", "chromium"], capture_output=True, timeout=900,
                       env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
        found = shutil.which("chromium")
    if found is None:
        pytest.skip("no Chromium here and it cannot be installed (needs root and apt-get)")
    return found


def _attr(page, name: str) -> str | None:
    return page.get_attribute("body", f"data-{name}")


def _wait(predicate, timeout: float = 60.0) -> None:
    """Poll ``predicate`` (the page's Content-Security-Policy forbids Playwright's in-page polling)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.1)
    raise AssertionError("timed out")


# counts the canvas pixels that differ from the background (white), through a 2-D copy
DRAWN_PIXELS = """() => {
  const source = document.getElementById("canvas");
  const copy = document.createElement("canvas");
  copy.width = source.width; copy.height = source.height;
  const ctx = copy.getContext("2d");
  ctx.drawImage(source, 0, 0);
  const data = ctx.getImageData(0, 0, copy.width, copy.height).data;
  let drawn = 0;
  for (let i = 0; i < data.length; i += 4) if (data[i] < 240 || data[i + 1] < 240 || data[i + 2] < 240) drawn++;
  return [drawn, copy.width * copy.height];
}"""


@pytest.mark.slow
def test_the_page_in_a_real_browser(server, tmp_path):
    executable = _chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(server.url + "/")
            assert page.url.endswith("/viewer/")
            _wait(lambda: int(_attr(page, "updates") or 0) >= 1)
            # every control has a label; the model picker is filled from /models
            assert page.evaluate("[...document.querySelectorAll('input, select, textarea')]"
                                 ".every(e => e.labels && e.labels.length > 0)")
            models = page.eval_on_selector_all("#model option", "options => options.map(o => o.value)")
            assert models == httpx.get(server.url + "/models").json()["loaded"]

            before = int(_attr(page, "updates"))
            page.focus("#p-tension_0")
            page.keyboard.press("End")  # the tension slider of tendon 1 to its Table I maximum, by keyboard
            _wait(lambda: json.loads(_attr(page, "design") or "{}").get("tendons", [{}])[0].get("tension") == 5.0
                  and int(_attr(page, "updates")) > before)
            design = json.loads(_attr(page, "design"))
            model = page.eval_on_selector("#model", "select => select.value")
            predicted = httpx.post(server.url + "/predict", json={"model": model, "designs": [design]}).json()
            exact = httpx.post(server.url + "/exact", json={"designs": [design]}, timeout=60).json()
            expected = relative_l2(np.array(predicted["results"][0]["tendons"])[None],
                                   np.array(exact["results"][0]["tendons"])[None])[0]
            assert float(_attr(page, "error")) == pytest.approx(expected, rel=1e-9)
            shown = float(page.inner_text("#error").split()[0])
            assert shown == pytest.approx(expected, rel=1e-3)
            assert expected > 0
            # the operator's calibrated bound beside the measured error
            bound = predicted["results"][0]["error_bound"]
            assert bound is not None and float(_attr(page, "error-bound")) == pytest.approx(bound, rel=1e-12)
            assert float(page.inner_text("#error-bound").split()[0]) == pytest.approx(bound, rel=1e-3)

            # gravity and a tip force: a loaded operator over the exact loaded shape
            before = int(_attr(page, "updates"))
            page.select_option("#gravity", "0,0,-1")
            page.focus("#p-tip_force_x")
            page.keyboard.press("End")  # +0.02 N along x
            _wait(lambda: json.loads(_attr(page, "design") or "{}").get("tip_force", [0])[0] == 0.02
                  and int(_attr(page, "updates")) > before)
            design = json.loads(_attr(page, "design"))
            assert design["gravity"] == [0, 0, -9.81] and abs(design["density"] - 7800) < 5  # a slider step
            loaded = page.eval_on_selector("#model", "select => select.value")
            assert loaded == httpx.get(server.url + "/models").json()["default_loaded_operator"]
            predicted = httpx.post(server.url + "/predict", json={"model": loaded, "designs": [design]}).json()
            exact = httpx.post(server.url + "/exact", json={"designs": [design]}, timeout=60).json()
            expected = relative_l2(np.array(predicted["results"][0]["tendons"])[None],
                                   np.array(exact["results"][0]["tendons"])[None])[0]
            assert float(_attr(page, "error")) == pytest.approx(expected, rel=1e-9)
            # the router's operator takes loads itself, so the page had no operator to switch
            assert "loads" in httpx.get(server.url + "/models").json()["models"][loaded]["inputs"]

            # a tendon that ends before the tip: segments, the exact solver alone, drawn to its end
            before = int(_attr(page, "updates"))
            page.focus("#p-end_1")
            page.keyboard.press("Home")  # tendon 2 ends at 0.05 L
            _wait(lambda: "end" in json.loads(_attr(page, "design") or "{}").get("tendons", [{}, {}])[1]
                  and int(_attr(page, "updates")) > before)
            design = json.loads(_attr(page, "design"))
            assert design["tendons"][1]["end"] == pytest.approx(0.05 * design["L"])
            points = json.loads(_attr(page, "tendon-points"))
            assert points[1] < points[0] == 42  # drawn from the base to its end only
            assert "exact solver alone" in page.inner_text("#message") and _attr(page, "error") == "none"

            drawn, total = page.evaluate(DRAWN_PIXELS)
            assert drawn > 0.005 * total, (drawn, total)  # not blank
            page.click("#reset")
            page.screenshot(path=str(tmp_path / "viewer.png"))
            assert (tmp_path / "viewer.png").stat().st_size > 10_000

            phone = browser.new_page(viewport={"width": 390, "height": 844})
            phone.goto(server.url + "/viewer/")
            _wait(lambda: int(_attr(phone, "updates") or 0) >= 1)
            assert phone.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
            assert phone.is_visible("#canvas") and phone.is_visible("#p-tension_0")
            phone.screenshot(path=str(tmp_path / "viewer-phone.png"))
            assert not errors, errors
        finally:
            browser.close()
