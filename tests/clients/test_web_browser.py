"""The live map page in a real headless Chromium (Playwright driving Debian's /usr/bin/chromium).

The emulated robot (`sensor-agent --emulate`) drives while the page shows the map and the
moving pose; then the page's Save and Stop controls are used. A screenshot is saved to
test-artifacts/web.png.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO_ROOT
from mapping_live import (
    BIN,
    SHARED_TOKEN,
    LiveService,
    ScanFeeder,
    shared_service,
    wait_for,
)

from clients import MappingClient

log = logging.getLogger(__name__)

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-dev-shm-usage",
]
ARTIFACTS = REPO_ROOT / "test-artifacts"
ROBOT = "web-1"

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def require_browser() -> Any:
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is missing (apt-get install chromium); .ci/run installs it")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the playwright Python package is not installed (pip install -e '.[dev]')")
    return sync_playwright


@contextmanager
def driving_robot(service: LiveService, client: MappingClient, session_id: str) -> Iterator[str]:
    """The emulated robot, driving; falls back to synthetic scans if the agent cannot run."""
    log_path = service.data_dir.parent / "agent.log"
    with log_path.open("wb") as agent_log:
        agent = subprocess.Popen(
            [
                str(BIN / "sensor-agent"),
                "--robot-id",
                ROBOT,
                "--emulate",
                "--zenoh-connect",
                service.zenoh_endpoint,
            ],
            stdout=agent_log,
            stderr=subprocess.STDOUT,
            cwd=REPO_ROOT,
        )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and agent.poll() is None:
            if client.get_session(session_id).poses >= 3:
                yield "sensor-agent --emulate"
                return
            time.sleep(0.1)
        reason = f"exited with {agent.returncode}" if agent.poll() is not None else "sent no scans"
        tail = log_path.read_text(errors="replace")[-600:]
        log.warning("sensor-agent --emulate %s; using synthetic scans instead:\n%s", reason, tail)
    finally:
        if agent.poll() is None:
            agent.send_signal(signal.SIGINT)
            try:
                agent.wait(timeout=10)
            except subprocess.TimeoutExpired:
                agent.kill()
                agent.wait()
    with ScanFeeder(service.zenoh_endpoint, ROBOT):
        yield "synthetic scans"


@pytest.mark.timeout(150)
def test_live_map_page(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> None:
    sync_playwright = require_browser()
    ARTIFACTS.mkdir(exist_ok=True)
    service = shared_service(request.config, tmp_path_factory)
    with ExitStack() as stack:
        client = stack.enter_context(MappingClient(service.url, token=SHARED_TOKEN))
        session = client.create_session(ROBOT)
        source = stack.enter_context(driving_robot(service, client, session.id))

        pw = stack.enter_context(sync_playwright())
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        stack.callback(browser.close)
        page = browser.new_page(viewport={"width": 1440, "height": 880})
        js_errors: list[str] = []
        page.on("pageerror", lambda err: js_errors.append(str(err)))
        external: list[str] = []
        page.on(
            "request",
            lambda req: None if req.url.startswith(service.url) else external.append(req.url),
        )

        page.goto(f"{service.url}/?session={session.id}")
        page.wait_for_selector("#map-canvas")
        assert page.title().startswith("Live map")

        # The map image arrives and is drawn; the pose moves with the robot.
        page.wait_for_function("document.body.dataset.mapLoaded !== undefined", timeout=30_000)
        page.wait_for_function(
            "document.getElementById('conn-text').textContent === 'live'", timeout=30_000
        )
        seq0 = int(page.inner_text("#pose-seq"))
        xy0 = (
            page.inner_text("#pose-x"),
            page.inner_text("#pose-y"),
            page.inner_text("#pose-theta"),
        )
        page.wait_for_function(
            f"Number(document.getElementById('pose-seq').textContent) >= {seq0 + 40}",
            timeout=30_000,
        )
        wait_for(
            lambda: (
                (
                    page.inner_text("#pose-x"),
                    page.inner_text("#pose-y"),
                    page.inner_text("#pose-theta"),
                )
                != xy0
            ),
            30,
            "the displayed pose to change",
        )
        painted = page.evaluate(
            """() => {
                const c = document.getElementById('map-canvas');
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                const colours = new Set();
                let drawn = 0;
                for (let i = 0; i < d.length; i += 4 * 7) {
                    if (d[i + 3] > 0) drawn++;
                    colours.add((d[i] >> 4) << 8 | (d[i + 1] >> 4) << 4 | (d[i + 2] >> 4));
                }
                return {drawn, colours: colours.size};
            }"""
        )
        assert painted["drawn"] > 1000, painted  # the map image covers part of the canvas
        assert painted["colours"] >= 4, painted  # walls, free, trajectory, robot
        assert page.inner_text("#s-robot") == ROBOT
        assert page.locator("#map-empty").is_hidden()

        # Controls: without a token the service refuses and the page says so.
        page.click("#btn-save")
        page.wait_for_function(
            "document.getElementById('message').textContent.includes('401')", timeout=10_000
        )
        page.fill("#token-input", SHARED_TOKEN)
        page.dispatch_event("#token-input", "change")
        page.click("#btn-save")
        page.wait_for_selector("#saved-card:not([hidden])", timeout=10_000)
        assert session.id in page.inner_text("#saved-text")
        assert any(m.session_id == session.id for m in client.list_maps())
        page.screenshot(path=str(ARTIFACTS / "web.png"))

        page.click("#btn-stop")
        page.wait_for_function(
            "document.getElementById('s-state').textContent === 'stopped'", timeout=10_000
        )
        assert client.get_session(session.id).state == "stopped"
        assert page.is_disabled("#btn-stop")

        assert not js_errors, js_errors
        assert not external, f"the page fetched external URLs: {external}"
        log.info("browser test drove the page with %s", source)
    assert (ARTIFACTS / "web.png").stat().st_size > 10_000


@pytest.mark.timeout(120)
def test_live_map_page_with_a_read_token(tmp_path: Path) -> None:
    """A service with a read token: the page asks for a token, then takes `?token=` (and
    drops it from the address), draws the map and follows the pose stream over fetch()."""
    sync_playwright = require_browser()
    control, read = "control-token-0123456789", "read-token-0123456789abc"
    service = LiveService(tmp_path / "data", token=control, read_token=read)
    service.start()
    with ExitStack() as stack:
        stack.callback(service.stop)
        client = stack.enter_context(MappingClient(service.url, token=control))
        session = client.create_session("web-read-1")
        stack.enter_context(ScanFeeder(service.zenoh_endpoint, "web-read-1"))
        wait_for(lambda: client.get_session(session.id).poses >= 5, 30, "5 poses")

        pw = stack.enter_context(sync_playwright())
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        stack.callback(browser.close)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        js_errors: list[str] = []
        page.on("pageerror", lambda err: js_errors.append(str(err)))
        urls: list[str] = []
        page.on("request", lambda req: urls.append(req.url))

        page.goto(f"{service.url}/?session={session.id}")
        page.wait_for_function("document.body.dataset.needsToken === '1'", timeout=20_000)
        assert "token" in page.inner_text("#message").lower()

        page.goto(f"{service.url}/?token={read}&session={session.id}")
        page.wait_for_function("document.body.dataset.mapLoaded !== undefined", timeout=30_000)
        page.wait_for_function(
            "document.getElementById('conn-text').textContent === 'live'", timeout=30_000
        )
        seq0 = int(page.inner_text("#pose-seq"))
        page.wait_for_function(
            f"Number(document.getElementById('pose-seq').textContent) >= {seq0 + 20}",
            timeout=30_000,
        )
        assert "token=" not in page.url
        # The token went in headers only: no request after the page load carries it.
        after_load = urls[urls.index(f"{service.url}/?token={read}&session={session.id}") + 1 :]
        assert not [u for u in after_load if read in u], after_load
        # The read token cannot control: the page says so.
        page.click("#btn-save")
        page.wait_for_function(
            "document.getElementById('message').textContent.includes('403')", timeout=10_000
        )
        assert not js_errors, js_errors
