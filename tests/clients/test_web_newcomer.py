"""What a newcomer tripped on in the browser (headless Chromium, like test_web_browser.py):
/docs without internet, "Loading…" before the first map, a `?session=` that does not exist,
and the trajectory and robot in map.png's colours."""

from __future__ import annotations

import io
import time
from contextlib import ExitStack
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import wait_for
from PIL import Image
from svc_testkit import SHARED_TOKEN, ScanFeeder, shared_service
from test_web_browser import CHROMIUM, CHROMIUM_ARGS, require_browser

from clients import MappingClient
from service import mapio

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ROBOT = "webnc-1"
TRAJECTORY_RGB = tuple(mapio._TRAJECTORY_RGB)
ROBOT_RGB = tuple(mapio._ROBOT_RGB)
OLD_BLUE = (37, 99, 235)  # the page's trajectory colour before it matched map.png


def _canvas_has(page: Any, colours: list[tuple[int, int, int]]) -> list[bool]:
    """Whether each colour appears exactly (opaque) on the map canvas."""
    return list(
        page.evaluate(
            """(wanted) => {
                const c = document.getElementById('map-canvas');
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                const keys = new Set();
                for (let i = 0; i < d.length; i += 4) {
                    if (d[i + 3] === 255) keys.add((d[i] << 16) | (d[i + 1] << 8) | d[i + 2]);
                }
                return wanted.map(([r, g, b]) => keys.has((r << 16) | (g << 8) | b));
            }""",
            [list(c) for c in colours],
        )
    )


def test_docs_loading_missing_session_and_colours(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> None:
    sync_playwright = require_browser()
    service = shared_service(request.config, tmp_path_factory)
    with ExitStack() as stack:
        client = stack.enter_context(MappingClient(service.url, token=SHARED_TOKEN))
        session = client.create_session(ROBOT)
        stack.enter_context(ScanFeeder(service.zenoh_endpoint, ROBOT))
        wait_for(lambda: client.get_session(session.id).poses >= 60, 60, "60 poses")

        pw = stack.enter_context(sync_playwright())
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        stack.callback(browser.close)
        context = browser.new_context(viewport={"width": 1280, "height": 800})
        # No internet: every request that leaves the service fails, as it would offline.
        external: list[str] = []

        def offline(route: Any) -> None:
            if route.request.url.startswith(service.url):
                route.continue_()
            else:
                external.append(route.request.url)
                route.abort()

        context.route("**/*", offline)
        page = context.new_page()
        js_errors: list[str] = []
        page.on("pageerror", lambda err: js_errors.append(str(err)))

        # /docs renders Swagger UI from the service's own assets.
        page.goto(f"{service.url}/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        assert page.locator(".opblock").count() > 10
        assert not external, external

        # A ?session= that does not exist: said plainly, no other session shown.
        page.goto(f"{service.url}/?session=s-doesnotexist0000")
        page.wait_for_function(
            "document.getElementById('map-empty-title').textContent === 'No such session'",
            timeout=15_000,
        )
        assert "does not exist" in page.inner_text("#message")
        assert page.inner_text("#s-robot") == "–"
        assert page.input_value("#session-select") == ""
        assert page.locator("#map-empty").is_visible()

        # While the first map loads the page says "Loading…", not "No map yet".
        held: list[Any] = []

        def hold(route: Any) -> None:
            held.append(route)

        page.route("**/map.pgm", hold)
        page.goto(f"{service.url}/?session={session.id}")
        deadline = time.monotonic() + 15
        while not held and time.monotonic() < deadline:  # handlers run inside page calls
            page.wait_for_timeout(50)
        assert held, "the page never asked for the map"
        assert page.inner_text("#map-empty-title") == "Loading…"
        for route in held:
            route.continue_()
        page.unroute("**/map.pgm")
        page.wait_for_function("document.body.dataset.mapLoaded !== undefined", timeout=30_000)
        assert page.locator("#map-empty").is_hidden()

        # The trajectory and the robot in map.png's colours.
        deadline = time.monotonic() + 20
        while _canvas_has(page, [TRAJECTORY_RGB, ROBOT_RGB]) != [True, True]:
            assert time.monotonic() < deadline, "no trajectory and robot on the canvas"
            page.wait_for_timeout(200)
        assert _canvas_has(page, [OLD_BLUE]) == [False]
        png = httpx.get(
            f"{service.url}/sessions/{session.id}/map.png",
            params={"trajectory": "true", "robot": "true"},
        ).content
        image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
        png_colours = {tuple(int(v) for v in c) for c in np.unique(image, axis=0)}
        assert TRAJECTORY_RGB in png_colours
        assert ROBOT_RGB in png_colours
        assert not js_errors, js_errors
        client.stop_session(session.id)
