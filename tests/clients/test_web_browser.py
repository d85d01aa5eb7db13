"""The live map page in a real headless Chromium (Playwright driving Debian's /usr/bin/chromium).

The emulated robot (`sensor-agent --emulate`, the real agent path) drives the synthetic building
while the page shows the map and the moving pose. Then the robot stops, and the canvas is read
back and checked against the building itself: where the simulated laser hit walls the canvas is
dark, and beside the robot's true path it is white (free). Then the page's Save and Stop
controls are used. A screenshot is saved to test-artifacts/web.png.
"""

from __future__ import annotations

import base64
import io
import logging
import math
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import REPO_ROOT, wait_for
from PIL import Image
from svc_testkit import BIN, SHARED_TOKEN, ScanFeeder, ServiceProc, shared_service

from clients import MappingClient
from sensor_agent.sim import LaserModel, RobotMotion, generate_building

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
WORLD_SEED = 1
POSES_BEFORE_STOP = 240  # 6 s at 40 Hz, ~4 m of corridor

# What the canvas must show: at least this share of the simulated laser's wall hits within 6 m
# lies next to a dark pixel (measured 0.998-1.0, alone and beside two busy processes; the margin
# is for a full suite's load, where the service's map is rougher), and of the points beside the
# true path on white (free) pixels (measured 1.0 in every run). The map not drawn gives 0 for
# both; a map drawn in the wrong place, far less.
MIN_WALL_SHARE = 0.5
MIN_FREE_SHARE = 0.95
MAX_SHIFT_M = 0.3

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def require_browser() -> Any:
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is missing (apt-get install chromium); .ci/run installs it")
    # A development dependency (`.[dev]`): if it does not import, the install is broken, and
    # that is a failure, not a reason to skip.
    from playwright.sync_api import sync_playwright

    return sync_playwright


@contextmanager
def driving_robot(
    service: ServiceProc, client: MappingClient, session_id: str
) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """The emulated robot, driving until the block ends or the agent is stopped; yields the
    agent and the host time (`time.time_ns()`, the scans' clock) it was launched at.

    A failure of the agent path fails the test: there is no fallback to synthetic scans.
    """
    log_path = service.data_dir.parent / "agent.log"
    with log_path.open("wb") as agent_log:
        launch_ns = time.time_ns()
        agent = subprocess.Popen(
            [
                str(BIN / "sensor-agent"),
                "--robot-id",
                ROBOT,
                "--emulate",
                "--world-seed",
                str(WORLD_SEED),
                "--zenoh-connect",
                service.zenoh_endpoint,
            ],
            stdout=agent_log,
            stderr=subprocess.STDOUT,
            cwd=REPO_ROOT,
        )

    def mapping() -> bool:
        if agent.poll() is not None:
            pytest.fail(
                f"sensor-agent --emulate exited with {agent.returncode}:\n"
                + log_path.read_text(errors="replace")[-2000:]
            )
        return client.get_session(session_id).poses >= 3

    try:
        wait_for(mapping, 30, "poses from sensor-agent --emulate", period_s=0.1)
        yield agent, launch_ns
    finally:
        stop_agent(agent)


def stop_agent(agent: subprocess.Popen[bytes]) -> None:
    if agent.poll() is None:
        agent.send_signal(signal.SIGINT)
        try:
            agent.wait(timeout=10)
        except subprocess.TimeoutExpired:
            agent.kill()
            agent.wait()


def wait_until_still(client: MappingClient, session_id: str) -> int:
    """Wait until the session's counters stop moving (the robot stopped); return the poses."""
    last: list[int] = []

    def still() -> bool:
        info = client.get_session(session_id)
        now = info.poses
        steady = bool(last) and last[-1] == now and info.scans_accepted == now
        last.append(now)
        return steady

    wait_for(still, 30, "the session to stop growing", period_s=0.5)
    return last[-1]


def read_pgm(pgm: bytes) -> np.ndarray:
    """A binary PGM (P5, maxval < 256, `#` comments) as a (height, width) uint8 array, top row
    first."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        end = pgm.index(b"\n", pos)
        line = pgm[pos:end].split(b"#", 1)[0]
        tokens += line.split()
        pos = end + 1
    assert tokens[0] == b"P5", tokens[:4]
    assert int(tokens[3]) < 256, tokens[:4]
    width, height = int(tokens[1]), int(tokens[2])
    return np.frombuffer(pgm, dtype=np.uint8, count=width * height, offset=pos).reshape(
        height, width
    )


def parse_map_yaml(text: str) -> tuple[float, float, float]:
    """(resolution_m, origin_x_m, origin_y_m) of a ROS map_server YAML."""
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    origin = [float(v) for v in fields["origin"].strip().strip("[]").split(",")]
    return float(fields["resolution"]), origin[0], origin[1]


class CanvasView:
    """World (map frame) to canvas pixels, as the page's `fitView` places the map: the map's
    extent and the trajectory, fitted with a 24 px margin, centred."""

    def __init__(
        self,
        css_w: float,
        css_h: float,
        dpr: float,
        bounds: tuple[float, float, float, float],
    ) -> None:
        min_x, min_y, max_x, max_y = bounds
        self.css_w, self.css_h, self.dpr = css_w, css_h, dpr
        self.scale = min((css_w - 48) / max(max_x - min_x, 4), (css_h - 48) / max(max_y - min_y, 4))
        self.cx, self.cy = (min_x + max_x) / 2, (min_y + max_y) / 2

    def css(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) map-frame metres to (N, 2) CSS pixels (x right, y down)."""
        x = self.css_w / 2 + (xy_m[:, 0] - self.cx) * self.scale
        y = self.css_h / 2 - (xy_m[:, 1] - self.cy) * self.scale
        return np.column_stack((x, y))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`a ∘ b` for a (3,) pose and (N, 3) poses."""
    c, s = math.cos(a[2]), math.sin(a[2])
    x = a[0] + c * b[:, 0] - s * b[:, 1]
    y = a[1] + s * b[:, 0] + c * b[:, 1]
    return np.column_stack((x, y, a[2] + b[:, 2]))


def world_to_map(
    first_est: np.ndarray, first_truth: np.ndarray, xy_world: np.ndarray
) -> np.ndarray:
    """The map frame is the first estimated pose at the first true pose."""
    c, s = math.cos(first_truth[2]), math.sin(first_truth[2])
    d = xy_world - first_truth[:2]
    rel = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], 0 * d[:, 0]))
    return compose(first_est, rel)[:, :2]


class ServedMap:
    """The served map.pgm with its map.yaml: where its occupied cells are."""

    def __init__(self, pgm: bytes, yaml_text: str) -> None:
        self.image = read_pgm(pgm)
        self.resolution_m, self.origin_x_m, self.origin_y_m = parse_map_yaml(yaml_text)
        occupied = self.image < 50  # map_server: 0 occupied, 254 free, 205 unknown
        # Within one cell: a wall cell is the one its hits fell in, give or take rounding (the
        # 3 x 3 dilation, rows then columns, not wrapping round the image's edges).
        near = occupied.copy()
        near[1:] |= occupied[:-1]
        near[:-1] |= occupied[1:]
        rows = near.copy()
        near[:, 1:] |= rows[:, :-1]
        near[:, :-1] |= rows[:, 1:]
        self.near_occupied = near

    @property
    def height_px(self) -> int:
        return int(self.image.shape[0])

    @property
    def width_px(self) -> int:
        return int(self.image.shape[1])

    def hits(self, xy_m: np.ndarray) -> int:
        """How many of the (N, 2) map-frame points lie within a cell of an occupied cell."""
        col = np.floor((xy_m[:, 0] - self.origin_x_m) / self.resolution_m).astype(int)
        row = self.height_px - 1 - np.floor((xy_m[:, 1] - self.origin_y_m) / self.resolution_m)
        row = row.astype(int)
        inside = (col >= 0) & (col < self.width_px) & (row >= 0) & (row < self.height_px)
        return int(np.count_nonzero(self.near_occupied[row[inside], col[inside]]))


def wall_hits(world: Any, truth: np.ndarray) -> np.ndarray:
    """(N, 2) world points where the simulated laser, from every 20th of the `truth` poses,
    hits a wall within 6 m (near hits: many cells per metre of wall)."""
    angles = LaserModel.utm30lx().angles_rad()[::4]
    hits = []
    for pose in truth[::20]:
        r = world.raycast(pose, angles, 6.0)
        ok = np.isfinite(r)
        a = angles[ok] + pose[2]
        hits.append(np.column_stack((pose[0] + r[ok] * np.cos(a), pose[1] + r[ok] * np.sin(a))))
    return np.concatenate(hits)


def ground_truth_points(
    poses: list[dict[str, Any]], launch_ns: int, served: ServedMap
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In the map frame: (walls hit by the simulated laser, free points beside the true path,
    the true path), from the building the emulator drives and the served trajectory.

    The map frame is the first estimated pose placed at the true pose of the first scan, whose
    scene time (the emulator's clock, from its start) is not on the wire. It lies between 0
    and the first scan's host stamp less the agent's launch: motion alone does not pin it
    there, since on a straight corridor every stretch moves alike. So the building's walls are
    registered on the served map over that window (one unknown, the time): the map's shape is
    what the shares then judge, and the page's drawing of it.
    """
    world = generate_building(WORLD_SEED)
    motion = RobotMotion(world, WORLD_SEED)
    stamps = np.array([p["stamp_ns"] for p in poses], dtype=np.int64)
    est = np.array([(p["x"], p["y"], p["theta"]) for p in poses])
    dt_s = (stamps - stamps[0]) / 1e9
    window_s = max(0.0, (int(stamps[0]) - launch_ns) / 1e9)

    def placed(offset_s: float) -> tuple[np.ndarray, np.ndarray]:
        truth = motion.poses_at(offset_s + dt_s)
        return truth, world_to_map(est[0], truth[0], wall_hits(world, truth))

    # The most walls on occupied cells wins; the earliest of equals.
    scores = [(placed(o)[1], o) for o in np.arange(0.0, window_s + 0.02, 0.02)]
    best_s = max(scores, key=lambda c: (served.hits(c[0]), -c[1]))[1]
    truth, walls = placed(float(best_s))
    log.info("scene time of the first scan: %.2f s (of a %.2f s window)", best_s, window_s)
    # 0.4 and 0.8 m to either side of the true path, where the building is free 0.2 m around.
    side = np.column_stack((-np.sin(truth[:, 2]), np.cos(truth[:, 2])))
    beside = np.concatenate([truth[:, :2] + d * side for d in (-0.8, -0.4, 0.4, 0.8)])
    beside = beside[world.clearance_ok(beside, 0.2)]
    return (
        walls,
        world_to_map(est[0], truth[0], beside),
        world_to_map(est[0], truth[0], truth[:, :2]),
    )


def canvas_rgba(page: Any) -> np.ndarray:
    url = page.evaluate("() => document.getElementById('map-canvas').toDataURL('image/png')")
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA")).astype(np.int32)


def map_shares(
    rgba: np.ndarray, view: CanvasView, walls: np.ndarray, beside: np.ndarray, avoid: np.ndarray
) -> dict[str, float]:
    """Share of wall points next to a dark pixel, and of free points on white pixels.

    `avoid` (CSS px) are the overlays drawn over the map (robot, start marker): points near
    them are not judged, and neither is the scale bar's corner.
    """
    h, w = rgba.shape[:2]
    lum = (rgba[..., 0] * 299 + rgba[..., 1] * 587 + rgba[..., 2] * 114) // 1000
    dark = (rgba[..., 3] >= 128) & (lum < 140)  # occupied cells: the page's ink colour
    white = (rgba[..., 3] == 255) & (rgba[..., :3].min(axis=-1) >= 235)  # free cells

    def usable(px: np.ndarray) -> np.ndarray:
        inside = (px[:, 0] >= 4) & (px[:, 0] < view.css_w - 4)
        inside &= (px[:, 1] >= 4) & (px[:, 1] < view.css_h - 4)
        scale_bar = (px[:, 0] < 240) & (px[:, 1] > view.css_h - 50)
        near = np.zeros(len(px), dtype=bool)
        for a in avoid:
            near |= np.hypot(*(px - a).T) < 40
        return inside & ~scale_bar & ~near

    def any_near(mask: np.ndarray, px: np.ndarray, radius: int) -> np.ndarray:
        ij = np.rint(px * view.dpr).astype(int)
        found = np.zeros(len(ij), dtype=bool)
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                y = np.clip(ij[:, 1] + dy, 0, h - 1)
                x = np.clip(ij[:, 0] + dx, 0, w - 1)
                found |= mask[y, x]
        return found

    wall_px = view.css(walls)
    wall_px = wall_px[usable(wall_px)]
    free_px = view.css(beside)
    free_px = free_px[usable(free_px)]
    # Wall cells are 5 cm: a wall hit counts when a dark pixel lies within 8 cm (or 2 px), for
    # the estimator's error. The building was placed by registering it on the served map (one
    # unknown: the time); what the map drawn on the canvas may still be off by, the best shift
    # within ±MAX_SHIFT_M, is searched first, and reported.
    radius = max(2, math.ceil(0.08 * view.scale * view.dpr))
    reach = math.ceil(MAX_SHIFT_M * view.scale)
    best = (-1, 0, 0, 0)  # (wall hits, -squared shift: the smallest shift wins ties, sx, sy)
    for sy in range(-reach, reach + 1):
        for sx in range(-reach, reach + 1):
            if sx * sx + sy * sy > reach * reach:
                continue
            shifted = wall_px + np.array((sx, sy), dtype=float)
            hits = int(np.count_nonzero(any_near(dark, shifted, radius)))
            best = max(best, (hits, -(sx * sx + sy * sy), sx, sy))
    shift = np.array(best[2:], dtype=float)
    return {
        "scale_px_per_m": view.scale,
        "shift_m": float(np.hypot(*shift) / view.scale),
        "wall_points": float(len(wall_px)),
        "wall_share": best[0] / max(len(wall_px), 1),
        "wall_share_unshifted": float(np.mean(any_near(dark, wall_px, radius))),
        "free_points": float(len(free_px)),
        "free_share": float(np.mean(any_near(white, free_px + shift, 0))),
        "dark_at_free": float(np.mean(any_near(dark, free_px + shift, 0))),
    }


@pytest.mark.timeout(180)
def wait_map_settled(service: Any, session_id: str) -> None:
    """The back end draws the map in its own thread, up to a second after its last node:
    until it has every node and the map has not changed for longer than that."""
    last: dict[str, Any] = {"pgm": b"", "since": 0.0}

    def settled() -> bool:
        graph = service.json(f"/sessions/{session_id}/graph?nodes=false")
        pgm = service.get(f"/sessions/{session_id}/map.pgm").content
        pgm += service.get(f"/sessions/{session_id}/map.yaml").content  # the origin too
        now = time.monotonic()
        if pgm != last["pgm"]:
            last.update(pgm=pgm, since=now)
        return bool(graph["loop_closures"]["pending"] == 0 and now - last["since"] > 3.0)

    wait_for(settled, 30, "the back end's final map", period_s=0.25)


def test_live_map_page(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> None:
    sync_playwright = require_browser()
    ARTIFACTS.mkdir(exist_ok=True)
    service = shared_service(request.config, tmp_path_factory)
    with ExitStack() as stack:
        client = stack.enter_context(MappingClient(service.url, token=SHARED_TOKEN))
        session = client.create_session(ROBOT)
        agent, launch_ns = stack.enter_context(driving_robot(service, client, session.id))

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
        # Map fetches in order: ("start" | "done", url). Playwright delivers these events only
        # while the test calls into it, hence the `page.evaluate` in the conditions below.
        map_fetches: list[tuple[str, str]] = []
        page.on("request", lambda req: map_fetches.append(("start", req.url)))
        page.on("requestfinished", lambda req: map_fetches.append(("done", req.url)))

        page.goto(f"{service.url}/?session={session.id}")
        page.wait_for_selector("#map-canvas")
        assert page.title().startswith("Live map")

        # The map image arrives; the pose moves with the robot.
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
        assert page.inner_text("#s-robot") == ROBOT
        assert page.locator("#map-empty").is_hidden()

        # The robot stops; the page fetches the final map and draws it.
        wait_for(
            lambda: client.get_session(session.id).poses >= POSES_BEFORE_STOP,
            60,
            f"{POSES_BEFORE_STOP} poses",
            period_s=0.2,
        )
        stop_agent(agent)
        poses_total = wait_until_still(client, session.id)
        wait_map_settled(service, session.id)
        fetched = len(map_fetches)

        def map_refetched() -> bool:
            # A refresh is map.yaml, map.pgm, map.yaml; the image is drawn after the second.
            page.evaluate("0")
            events = map_fetches[fetched:]
            starts = [i for i, (k, u) in enumerate(events) if k == "start" and "/map.pgm" in u]
            return bool(starts) and any(
                k == "done" and "/map.yaml" in u for k, u in events[starts[0] + 1 :]
            )

        wait_for(map_refetched, 30, "the page to fetch the final map")
        api = httpx.Client(base_url=service.url, timeout=10.0)
        stack.callback(api.close)
        served = ServedMap(
            api.get(f"/sessions/{session.id}/map.pgm").content,
            api.get(f"/sessions/{session.id}/map.yaml").text,
        )
        resolution_m, origin_x, origin_y = served.resolution_m, served.origin_x_m, served.origin_y_m
        width_px, height_px = served.width_px, served.height_px
        page.wait_for_function(
            f"document.body.dataset.mapLoaded === '{width_px}x{height_px}'", timeout=30_000
        )
        wait_for(
            lambda: int(page.inner_text("#pose-seq")) == poses_total - 1,
            30,
            "the page to show the last pose",
        )
        # The graph moves the poses after its last closure too: the page loads the trajectory
        # again once the graph has settled at a new revision.
        revision = service.json(f"/sessions/{session.id}/graph?nodes=false")["revision"]
        page.wait_for_function(
            f"document.body.dataset.graphRevision === '{revision}'", timeout=30_000
        )
        page.evaluate(  # two frames: the page draws on requestAnimationFrame
            "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )

        poses = client_trajectory(api, session.id)
        assert len(poses) == poses_total
        est = np.array([(p["x"], p["y"]) for p in poses])
        size = page.evaluate(
            "() => { const c = document.getElementById('map-canvas');"
            " return [c.width, c.height, window.devicePixelRatio]; }"
        )
        dpr = float(size[2])
        map_max = (origin_x + width_px * resolution_m, origin_y + height_px * resolution_m)
        bounds = (
            min(origin_x, float(est[:, 0].min())),
            min(origin_y, float(est[:, 1].min())),
            max(map_max[0], float(est[:, 0].max())),
            max(map_max[1], float(est[:, 1].max())),
        )
        view = CanvasView(size[0] / dpr, size[1] / dpr, dpr, bounds)
        rgba = canvas_rgba(page)
        Image.fromarray(rgba.astype(np.uint8), "RGBA").save(ARTIFACTS / "web-canvas.png")

        # The overlay sits where the page's own transform puts it: the start marker.
        start_px = np.rint(view.css(est[:1])[0] * dpr).astype(int)
        colour = rgba[start_px[1], start_px[0], :3]
        assert np.abs(colour - (222, 74, 44)).max() < 40, colour  # TRAJECTORY_RGB in app.js

        walls, beside, _truth = ground_truth_points(poses, launch_ns, served)
        avoid = view.css(est[[0, -1]])
        shares = map_shares(rgba, view, walls, beside, avoid)
        log.info("canvas against the building: %s", shares)
        print("canvas against the building:", shares)
        assert shares["wall_points"] >= 200, shares
        assert shares["free_points"] >= 200, shares
        assert shares["wall_share"] >= MIN_WALL_SHARE, shares
        assert shares["free_share"] >= MIN_FREE_SHARE, shares
        assert shares["dark_at_free"] <= 0.02, shares

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
    assert (ARTIFACTS / "web.png").stat().st_size > 10_000


def client_trajectory(api: httpx.Client, session_id: str) -> list[dict[str, Any]]:
    r = api.get(f"/sessions/{session_id}/trajectory")
    assert r.status_code == 200, r.text
    poses = r.json()["poses"]
    assert isinstance(poses, list)
    return poses


@pytest.mark.timeout(120)
def test_live_map_page_with_a_read_token(tmp_path: Path) -> None:
    """A service with a read token: the page asks for a token, then takes `?token=` (and
    drops it from the address), draws the map and follows the pose stream over fetch()."""
    sync_playwright = require_browser()
    control, read = "control-token-0123456789", "read-token-0123456789abc"
    service = ServiceProc(tmp_path / "data", token=control, read_token=read)
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
