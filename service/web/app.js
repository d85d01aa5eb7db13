// Live map page: session picker, controls, the map with trajectory and robot, pose panel.
// Plain browser JavaScript, no dependencies, no build step. Talks only to this origin:
//   GET  /sessions, /sessions/{id}, /sessions/{id}/trajectory (paged), /sessions/{id}/map.yaml,
//        /sessions/{id}/map.png?trajectory=false&robot=false   (we draw those ourselves)
//        /sessions/{id}/graph?nodes=false   (accepted loop closures, drawn as lines)
//   SSE  /sessions/{id}/pose/stream   (event: pose, data: PoseView JSON), read with fetch()
//   POST /sessions, /sessions/{id}/stop|reset|save
// Every request carries `Authorization: Bearer <token>` when a token is set: the Token field,
// or `?token=` in the page's address (kept in this browser, then removed from the address).
// The pose stream is read with fetch() rather than EventSource, which cannot send that header
// (a token in the stream's URL would end up in logs).
"use strict";

(() => {
  const TOKEN_KEY = "mapping.token";
  const SESSIONS_PERIOD_MS = 2000;
  const MAP_PERIOD_MS = 1500;
  const MAX_TRAJ_POINTS = 200000;
  const MIN_TRAJ_STEP_M = 0.01; // skip points closer than this to the previous one

  const $ = (id) => document.getElementById(id);
  const el = {
    select: $("session-select"),
    stop: $("btn-stop"),
    save: $("btn-save"),
    reset: $("btn-reset"),
    startForm: $("start-form"),
    robotInput: $("robot-input"),
    token: $("token-input"),
    canvas: $("map-canvas"),
    wrap: $("map-wrap"),
    empty: $("map-empty"),
    emptyTitle: $("map-empty-title"),
    emptyText: $("map-empty-text"),
    follow: $("btn-follow"),
    fit: $("btn-fit"),
    poseX: $("pose-x"),
    poseY: $("pose-y"),
    poseTheta: $("pose-theta"),
    poseQuality: $("pose-quality"),
    qualityBar: $("quality-bar"),
    poseFlags: $("pose-flags"),
    poseSeq: $("pose-seq"),
    poseAge: $("pose-age"),
    sRobot: $("s-robot"),
    sState: $("s-state"),
    sScans: $("s-scans"),
    sRate: $("s-rate"),
    sPoses: $("s-poses"),
    sRes: $("s-res"),
    sSize: $("s-size"),
    savedCard: $("saved-card"),
    savedText: $("saved-text"),
    conn: $("conn"),
    connText: $("conn-text"),
    statusLine: $("status-line"),
    message: $("message"),
  };
  const ctx = el.canvas.getContext("2d");

  // The colours of map.png (service/mapio.py _TRAJECTORY_RGB, _ROBOT_RGB): the page and the
  // downloaded image draw the trajectory and the robot alike.
  const TRAJECTORY_RGB = [222, 74, 44];
  const ROBOT_RGB = [18, 140, 96];
  // Accepted loop closures (GET /sessions/{id}/graph), the Foxglove view's colour.
  const CLOSURE_RGB = [38, 99, 235];
  const rgb = (c, a = 1) => `rgba(${c[0]}, ${c[1]}, ${c[2]}, ${a})`;

  const state = {
    closures: [], // accepted loop closures: [[x0, y0], [x1, y1]] at the optimised poses
    closuresKey: null, // "session:accepted" of the trajectory loaded last
    graphRevision: null, // the graph's revision when the trajectory was last loaded for it
    nextGraphReloadAt: 0, // performance.now() before which the graph's moves wait
    sessions: [],
    sessionId: null,
    session: null,
    map: null, // {bitmap, width, height, info: {resolution, originX, originY}}
    mapKey: null, // session id the map belongs to
    traj: [], // [[x, y], ...] in metres
    trajLoaded: false, // the session's trajectory so far came from the server (not the stream only)
    trajLoading: false,
    lastSeq: -1,
    pose: null,
    es: null,
    rate: null, // scans per second
    prevScans: null, // {count, t}
    view: { scale: 40, cx: 0, cy: 0 }, // pixels per metre, world point at the canvas centre
    autoFit: true,
    follow: false,
    dirty: true,
    mapBusy: false,
    mapTried: false, // the first map request of this session has answered
    missing: null, // the ?session= id that does not exist on this service
    nextMapAt: 0,
    drag: null,
  };

  // ------------------------------------------------------------------------------------------
  // HTTP

  class ApiError extends Error {
    constructor(status, detail) {
      super(`${status}: ${detail}`);
      this.status = status;
      this.detail = detail;
    }
  }

  // A token handed over in the address (`/?token=...`): keep it, and take it out of the
  // address bar and the history entry.
  (() => {
    const url = new URL(location.href);
    const given = url.searchParams.get("token");
    if (given === null) return;
    if (given.trim()) localStorage.setItem(TOKEN_KEY, given.trim());
    url.searchParams.delete("token");
    history.replaceState(null, "", url);
  })();

  async function api(method, path, body, extra = {}) {
    const headers = { Accept: extra.accept || "application/json" };
    const token = localStorage.getItem(TOKEN_KEY);
    if (token) headers.Authorization = `Bearer ${token}`;
    const init = { method, headers, cache: "no-store", signal: extra.signal };
    if (body !== undefined) {
      headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    let response;
    try {
      response = await fetch(path, init);
    } catch (err) {
      throw new ApiError(0, "cannot reach the service");
    }
    if (!response.ok) {
      let detail = response.statusText || "error";
      try {
        const j = await response.json();
        if (j && j.detail !== undefined) {
          detail = typeof j.detail === "string" ? j.detail : JSON.stringify(j.detail);
        }
      } catch (_) {
        /* not JSON: keep the status text */
      }
      throw new ApiError(response.status, detail);
    }
    return response;
  }

  const sessionPath = (id, rest = "") =>
    `/sessions/${encodeURIComponent(id)}${rest ? "/" + rest : ""}`;

  function explain(err) {
    if (err instanceof ApiError) {
      if (err.status === 401 || err.status === 403) {
        return `Not allowed (${err.status}): ${err.detail}. Enter the service token in the Token field.`;
      }
      if (err.status === 0) return "Cannot reach the service.";
      return `${err.detail} (HTTP ${err.status})`;
    }
    return String(err);
  }

  let messageTimer = null;
  function say(text, kind = "ok") {
    el.message.textContent = text;
    el.message.className = `message ${kind}`;
    clearTimeout(messageTimer);
    messageTimer = setTimeout(() => {
      el.message.textContent = "";
    }, kind === "error" ? 12000 : 6000);
  }

  // ------------------------------------------------------------------------------------------
  // Sessions

  let askedForToken = false;
  function askForToken(err) {
    setConn("down", "token needed");
    document.body.dataset.needsToken = "1";
    if (askedForToken) return;
    askedForToken = true;
    say(`${explain(err)} This service needs a token to read.`, "error");
    el.token.focus();
  }

  async function refreshSessions() {
    let list;
    try {
      const r = await api("GET", "/sessions");
      list = (await r.json()).sessions || [];
    } catch (err) {
      if (err instanceof ApiError && (err.status === 401 || err.status === 403)) askForToken(err);
      else setConn("down", "service unreachable");
      return;
    }
    askedForToken = false;
    delete document.body.dataset.needsToken;
    state.sessions = list;
    renderPicker();
    if (state.sessionId === null) {
      if (state.missing) {
        renderSession(); // keep saying so until the user picks a session
        return;
      }
      const wanted = new URLSearchParams(location.search).get("session");
      if (wanted && !list.some((s) => s.id === wanted)) {
        // Never silently show another session than the one the address names.
        state.missing = wanted;
        say(`Session ${wanted} does not exist on this service.`, "error");
        renderSession();
        return;
      }
      const pick =
        list.find((s) => s.id === wanted) ||
        [...list].filter((s) => s.state === "active").sort((a, b) => b.created_ns - a.created_ns)[0] ||
        list[0];
      if (pick) selectSession(pick.id);
      else renderSession();
      return;
    }
    const current = list.find((s) => s.id === state.sessionId);
    if (!current) {
      say(`Session ${state.sessionId} is gone.`, "error");
      selectSession(null);
      return;
    }
    updateSession(current);
  }

  function renderPicker() {
    const sel = el.select;
    const keep = state.sessionId;
    const options = [new Option("— no session —", "")];
    for (const s of [...state.sessions].sort((a, b) => b.created_ns - a.created_ns)) {
      const mark = s.state === "active" ? "●" : "○";
      options.push(new Option(`${mark} ${s.robot_id} · ${s.id}`, s.id));
    }
    const same =
      sel.options.length === options.length &&
      options.every((o, i) => sel.options[i].value === o.value && sel.options[i].text === o.text);
    if (!same) {
      sel.replaceChildren(...options);
    }
    sel.value = keep || "";
  }

  function selectSession(id) {
    if (state.es) {
      state.es.close();
      state.es = null;
    }
    state.sessionId = id;
    if (id) state.missing = null;
    state.session = null;
    state.map = null;
    state.mapTried = false;
    state.mapKey = null;
    state.nextMapAt = 0;
    state.closures = [];
    state.closuresKey = null;
    state.graphRevision = null;
    state.traj = [];
    state.trajLoaded = false;
    state.lastSeq = -1;
    state.pose = null;
    state.rate = null;
    state.prevScans = null;
    state.autoFit = true;
    state.dirty = true;
    el.savedCard.hidden = true;
    const url = new URL(location.href);
    if (id) url.searchParams.set("session", id);
    else url.searchParams.delete("session");
    history.replaceState(null, "", url);
    el.select.value = id || "";
    renderPose();
    if (!id) {
      renderSession();
      setConn("idle", "idle");
      return;
    }
    const s = state.sessions.find((x) => x.id === id);
    if (s) updateSession(s);
    loadTrajectory(id);
    refreshMap();
  }

  function updateSession(s) {
    const now = performance.now();
    if (state.prevScans && now > state.prevScans.t) {
      const dt = (now - state.prevScans.t) / 1000;
      if (dt > 0.5) {
        state.rate = Math.max(0, (s.scans_accepted - state.prevScans.count) / dt);
        state.prevScans = { count: s.scans_accepted, t: now };
      }
    } else {
      state.prevScans = { count: s.scans_accepted, t: now };
    }
    const wasActive = state.session && state.session.state === "active";
    state.session = s;
    if (s.state === "active" && !state.es) openStream(s.id);
    if (s.state !== "active" && state.es) {
      state.es.close();
      state.es = null;
    }
    if (s.state !== "active") {
      state.rate = 0;
      setConn("idle", "stopped");
    }
    if (wasActive && s.state !== "active") refreshMap();
    if (!state.pose && s.last_pose) acceptPose(s.last_pose);
    renderSession();
  }

  function renderSession() {
    const s = state.session;
    const has = !!s;
    el.stop.disabled = !has || s.state !== "active";
    el.save.disabled = !has;
    el.reset.disabled = !has || s.state !== "active";
    el.sRobot.textContent = has ? s.robot_id : "–";
    el.sState.textContent = has ? s.state : "–";
    el.sState.className = `badge ${has ? s.state : ""}`;
    el.sScans.textContent = has ? s.scans_accepted.toLocaleString() : "–";
    el.sRate.textContent = has && state.rate !== null ? state.rate.toFixed(1) : "–";
    el.sPoses.textContent = has ? s.poses.toLocaleString() : "–";
    el.sRes.textContent = has ? `${(s.resolution_m * 100).toFixed(1)} cm` : "–";
    const m = state.map;
    el.sSize.textContent = m
      ? `${(m.width * m.info.resolution).toFixed(1)} × ${(m.height * m.info.resolution).toFixed(1)} m`
      : "–";
    let title = "No map yet";
    if (state.missing && !state.sessionId) {
      title = "No such session";
      el.emptyText.textContent = `Session ${state.missing} does not exist on this service. Pick one above.`;
    } else if (!state.sessionId) {
      el.emptyText.textContent = state.sessions.length
        ? "Pick a session above."
        : "No sessions yet: enter a robot id and press Start.";
    } else if (!state.mapTried) {
      title = "Loading…";
      el.emptyText.textContent = "Loading the map of this session…";
    } else {
      el.emptyText.textContent = "Waiting for the first scans of this robot…";
    }
    el.emptyTitle.textContent = title;
    el.empty.hidden = !!state.map;
    renderStatus();
  }

  // ------------------------------------------------------------------------------------------
  // Poses

  // The pose stream over fetch(): Server-Sent Events parsed here, reconnecting with backoff
  // like EventSource would. `state.es` is {close()} so the callers need not know.
  function openStream(id) {
    const controller = new AbortController();
    const es = { close: () => controller.abort() };
    state.es = es;
    setConn("wait", "connecting");
    (async () => {
      let delayMs = 1000;
      while (state.es === es) {
        try {
          const r = await api("GET", sessionPath(id, "pose/stream"), undefined, {
            signal: controller.signal,
            accept: "text/event-stream",
          });
          setConn("live", "live");
          delayMs = 1000;
          await readEvents(r, (event, data) => {
            if (state.es !== es || event !== "pose") return;
            let p;
            try {
              p = JSON.parse(data);
            } catch (_) {
              return;
            }
            setConn("live", "live");
            acceptPose(p);
          });
        } catch (err) {
          if (controller.signal.aborted) return;
          if (err instanceof ApiError && (err.status === 401 || err.status === 403)) {
            askForToken(err);
          }
        }
        if (state.es !== es) return;
        setConn("wait", "reconnecting");
        await new Promise((resolve) => setTimeout(resolve, delayMs));
        delayMs = Math.min(2 * delayMs, 15000);
      }
    })();
  }

  async function readEvents(response, onEvent) {
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buffer += value.replace(/\r\n?/g, "\n");
      let end;
      while ((end = buffer.indexOf("\n\n")) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end + 2);
        let event = "message";
        const data = [];
        for (const line of block.split("\n")) {
          if (line.startsWith(":")) continue; // keep-alive comment
          const colon = line.indexOf(":");
          const field = colon < 0 ? line : line.slice(0, colon);
          const text = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
          if (field === "event") event = text;
          else if (field === "data") data.push(text);
        }
        if (data.length) onEvent(event, data.join("\n"));
      }
    }
  }

  // The trajectory comes in pages (the server's default is 1,000 poses); a long one is
  // decimated (`every`) so that the page keeps at most about MAX_TRAJ_POINTS points.
  const TRAJ_PAGE = 5000;

  async function trajectoryPage(id, since, every) {
    const q = `?since_seq=${since}&limit=${TRAJ_PAGE}&every=${every}`;
    const r = await api("GET", sessionPath(id, "trajectory") + q);
    return r.json();
  }

  // Resolves true when it loaded the trajectory (false: a load was already running, or failed).
  async function loadTrajectory(id) {
    if (state.trajLoading) return false;
    state.trajLoading = true;
    try {
      let body = await trajectoryPage(id, 0, 1);
      const total = body.total || 0;
      const every = Math.max(1, Math.ceil(total / MAX_TRAJ_POINTS));
      if (every > 1) body = await trajectoryPage(id, 0, every);
      const pts = [];
      let last = -1;
      for (;;) {
        if (state.sessionId !== id) return false;
        for (const p of body.poses || []) {
          pushPoint(pts, p.x, p.y, p.sequence);
          last = Math.max(last, p.sequence);
        }
        if (body.next_seq === null || body.next_seq === undefined) break;
        body = await trajectoryPage(id, body.next_seq, every);
      }
      if (state.sessionId !== id) return false;
      // Poses that arrived on the stream while the trajectory was loading go after it.
      for (const [x, y, seq] of state.traj) if (seq > last) pushPoint(pts, x, y, seq);
      state.traj = pts;
      state.trajLoaded = true;
      state.lastSeq = Math.max(state.lastSeq, last);
      state.dirty = true;
      return true;
    } catch (err) {
      /* a fresh or restoring session has no trajectory yet: loaded again at the next pose */
      return false;
    } finally {
      state.trajLoading = false;
    }
  }

  function pushPoint(pts, x, y, seq) {
    const n = pts.length;
    if (n > 0) {
      const [px, py] = pts[n - 1];
      if (Math.hypot(x - px, y - py) < MIN_TRAJ_STEP_M) return;
    }
    pts.push([x, y, seq]);
    if (pts.length > MAX_TRAJ_POINTS) pts.splice(0, pts.length - MAX_TRAJ_POINTS);
  }

  function acceptPose(p) {
    if (p.session_id && state.sessionId && p.session_id !== state.sessionId) return;
    if (typeof p.sequence === "number" && p.sequence < state.lastSeq) {
      // The session was reset: sequence numbers start again.
      state.traj = [];
    }
    state.lastSeq = p.sequence;
    state.pose = p;
    pushPoint(state.traj, p.x, p.y, p.sequence);
    // Poses from before the stream connected are the server's: fetch them once it has some.
    if (!state.trajLoaded && state.sessionId && p.sequence > 0) loadTrajectory(state.sessionId);
    if (state.follow) {
      state.view.cx = p.x;
      state.view.cy = p.y;
    }
    state.dirty = true;
    renderPose();
  }

  function renderPose() {
    const p = state.pose;
    if (!p) {
      el.poseX.textContent = el.poseY.textContent = el.poseTheta.textContent = "–";
      el.poseQuality.textContent = "–";
      el.qualityBar.style.width = "0";
      el.poseFlags.replaceChildren(flagChip("no pose yet", "flag flag-none"));
      el.poseSeq.textContent = "–";
      el.poseAge.textContent = "–";
      renderStatus();
      return;
    }
    el.poseX.textContent = p.x.toFixed(2);
    el.poseY.textContent = p.y.toFixed(2);
    el.poseTheta.textContent = ((p.theta * 180) / Math.PI).toFixed(1);
    el.poseQuality.textContent = p.quality.toFixed(2);
    el.qualityBar.style.width = `${Math.round(Math.max(0, Math.min(1, p.quality)) * 100)}%`;
    el.qualityBar.className = `meter-fill ${p.quality >= 0.6 ? "" : p.quality >= 0.3 ? "mid" : "low"}`;
    const flags = p.flags || [];
    el.poseFlags.replaceChildren(
      ...(flags.length
        ? flags.map((f) =>
            flagChip(f.replaceAll("_", " ").toLowerCase(), `flag ${/DEGENERATE|NO_DOMINANT/.test(f) ? "flag-bad" : ""}`),
          )
        : [flagChip("no flags", "flag flag-none")]),
    );
    el.poseSeq.textContent = String(p.sequence);
    renderAge();
    renderStatus();
  }

  function flagChip(text, cls) {
    const span = document.createElement("span");
    span.className = cls;
    span.textContent = text;
    return span;
  }

  function renderAge() {
    const p = state.pose;
    if (!p) return;
    const age = Math.max(0, Date.now() / 1000 - p.stamp);
    el.poseAge.textContent = age < 1 ? "just now" : age < 120 ? `${age.toFixed(0)} s ago` : `${(age / 60).toFixed(0)} min ago`;
  }

  function renderStatus() {
    const parts = [];
    const s = state.session;
    const p = state.pose;
    if (!state.sessionId) {
      el.statusLine.textContent = "No session selected.";
      return;
    }
    if (s) parts.push(`${s.robot_id} (${s.state})`);
    if (p) {
      parts.push(`quality ${p.quality.toFixed(2)}`);
      parts.push(p.flags && p.flags.length ? `flags ${p.flags.join(", ")}` : "no flags");
    }
    if (state.rate !== null) parts.push(`${state.rate.toFixed(1)} scans/s`);
    if (state.map) parts.push(`map ${state.map.width}×${state.map.height} px`);
    el.statusLine.textContent = parts.join(" · ");
  }

  function setConn(kind, text) {
    el.conn.className = `conn conn-${kind}`;
    el.connText.textContent = text;
  }

  // ------------------------------------------------------------------------------------------
  // Map image

  function parseMapYaml(text) {
    const fields = {};
    for (const raw of text.split("\n")) {
      const line = raw.split("#")[0].trim();
      const i = line.indexOf(":");
      if (i > 0) fields[line.slice(0, i).trim()] = line.slice(i + 1).trim();
    }
    const origin = (fields.origin || "").replace(/[[\]]/g, "").split(",").map(Number);
    const resolution = Number(fields.resolution);
    if (!(resolution > 0) || origin.length < 2 || origin.some((v) => !Number.isFinite(v))) {
      throw new Error("unreadable map.yaml");
    }
    return { resolution, originX: origin[0], originY: origin[1] };
  }

  // The map comes as the ROS map_server pair (map.pgm + map.yaml): one pixel per cell, first
  // row = highest y, origin = lower-left corner of cell (0, last row). That pair is exact by
  // definition, unlike the decorated map.png (margins, scaling, scale bar) meant for people.
  async function refreshMap() {
    const id = state.sessionId;
    if (!id || state.mapBusy || document.hidden) return;
    if (state.map && state.mapKey === id && state.session && state.session.state !== "active") return;
    if (performance.now() < state.nextMapAt) return;
    state.mapBusy = true;
    const t0 = performance.now();
    try {
      // The map can grow between the requests; read its metadata before and after the image
      // and retry once if it moved, so the overlay never sits on a shifted image.
      for (let attempt = 0; attempt < 2; attempt++) {
        const before = await (await api("GET", sessionPath(id, "map.yaml"))).text();
        const pgm = await (await api("GET", sessionPath(id, "map.pgm"))).arrayBuffer();
        const after = await (await api("GET", sessionPath(id, "map.yaml"))).text();
        if (before !== after && attempt === 0) continue;
        if (state.sessionId !== id) return;
        const image = pgmToCanvas(pgm);
        state.map = { bitmap: image, width: image.width, height: image.height, info: parseMapYaml(after) };
        state.mapKey = id;
        state.dirty = true;
        document.body.dataset.mapLoaded = `${image.width}x${image.height}`;
        renderSession();
        break;
      }
      await refreshClosures(id);
    } catch (err) {
      // 404 until the first scan: keep the placeholder.
    } finally {
      state.mapBusy = false;
      if (state.sessionId === id && !state.mapTried) {
        state.mapTried = true;
        renderSession();
      }
      // Big maps on slow links: never spend more than a quarter of the time downloading.
      state.nextMapAt = performance.now() + 3 * (performance.now() - t0);
    }
  }

  // The accepted loop closures, drawn as lines; a new one moved the whole trajectory (the
  // server corrects every pose by the pose graph), so the trajectory is loaded again.
  async function refreshClosures(id) {
    const g = await (await api("GET", sessionPath(id, "graph") + "?nodes=false")).json();
    if (state.sessionId !== id) return;
    const accepted = (g.closures || []).filter((c) => c.accepted);
    state.closures = accepted.map((c) => [[c.from_x, c.from_y], [c.to_x, c.to_y]]);
    const key = `${id}:${g.loop_closures ? g.loop_closures.accepted : 0}`;
    // The graph also moves the poses after a closure (later nodes relax it): at a new
    // revision, once its queue is empty, the trajectory is loaded again, at most every 10 s.
    const now = performance.now();
    const settled = g.loop_closures && g.loop_closures.pending === 0;
    const moved = settled && state.graphRevision !== g.revision && now >= state.nextGraphReloadAt;
    const closed = state.closuresKey !== null && state.closuresKey !== key;
    if (closed || (moved && state.closuresKey !== null)) {
      const revision = g.revision;
      state.graphRevision = revision;
      state.nextGraphReloadAt = now + 10_000;
      loadTrajectory(id).then((loaded) => {
        if (!loaded) Object.assign(state, { graphRevision: -1, nextGraphReloadAt: 0 }); // again
        else if (state.graphRevision === revision) document.body.dataset.graphRevision = String(revision);
      });
    } else if (state.graphRevision === null) {
      state.graphRevision = g.revision;
      document.body.dataset.graphRevision = String(g.revision);
    }
    state.closuresKey = key;
    document.body.dataset.loopClosures = String(accepted.length);
    state.dirty = true;
  }

  // Binary PGM (P5, maxval < 256) to a canvas in the page's colours: map_server greys
  // 254 free -> white, 0 occupied -> ink, 205 unknown -> transparent (the page background shows
  // "not yet seen"), anything in between blended.
  const UNKNOWN_GREY = 205;
  const INK = [28, 36, 48];
  function pgmToCanvas(buffer) {
    const bytes = new Uint8Array(buffer);
    let pos = 0;
    const token = () => {
      for (;;) {
        while (pos < bytes.length && /\s/.test(String.fromCharCode(bytes[pos]))) pos++;
        if (bytes[pos] === 35 /* # */) {
          while (pos < bytes.length && bytes[pos] !== 10) pos++;
          continue;
        }
        break;
      }
      const start = pos;
      while (pos < bytes.length && !/\s/.test(String.fromCharCode(bytes[pos]))) pos++;
      return String.fromCharCode(...bytes.subarray(start, pos));
    };
    const magic = token();
    const width = Number(token());
    const height = Number(token());
    const maxval = Number(token());
    pos += 1; // the single whitespace byte before the raster
    if (magic !== "P5" || !(width > 0) || !(height > 0) || !(maxval > 0 && maxval < 256)) {
      throw new Error("unsupported PGM");
    }
    if (bytes.length - pos < width * height) throw new Error("truncated PGM");
    const c = document.createElement("canvas");
    c.width = width;
    c.height = height;
    const g = c.getContext("2d");
    const img = g.createImageData(width, height);
    const d = img.data;
    const lut = new Uint8ClampedArray(256 * 4);
    for (let v = 0; v < 256; v++) {
      const k = Math.min(1, v / Math.min(254, maxval));
      lut[v * 4] = INK[0] + (255 - INK[0]) * k;
      lut[v * 4 + 1] = INK[1] + (255 - INK[1]) * k;
      lut[v * 4 + 2] = INK[2] + (255 - INK[2]) * k;
      lut[v * 4 + 3] = v === UNKNOWN_GREY ? 0 : 255;
    }
    for (let i = 0, j = 0; i < width * height; i++, j += 4) {
      const v = bytes[pos + i] * 4;
      d[j] = lut[v];
      d[j + 1] = lut[v + 1];
      d[j + 2] = lut[v + 2];
      d[j + 3] = lut[v + 3];
    }
    g.putImageData(img, 0, 0);
    return c;
  }

  // ------------------------------------------------------------------------------------------
  // Drawing

  function resizeCanvas() {
    const dpr = window.devicePixelRatio || 1;
    const w = el.wrap.clientWidth;
    const h = el.wrap.clientHeight;
    if (el.canvas.width !== Math.round(w * dpr) || el.canvas.height !== Math.round(h * dpr)) {
      el.canvas.width = Math.round(w * dpr);
      el.canvas.height = Math.round(h * dpr);
      state.dirty = true;
    }
    return { w, h, dpr };
  }

  function worldBounds() {
    let minX = Infinity, minY = Infinity, maxX = -Infinity, maxY = -Infinity;
    const m = state.map;
    if (m) {
      minX = m.info.originX;
      minY = m.info.originY;
      maxX = minX + m.width * m.info.resolution;
      maxY = minY + m.height * m.info.resolution;
    }
    for (const [x, y] of state.traj) {
      if (x < minX) minX = x;
      if (y < minY) minY = y;
      if (x > maxX) maxX = x;
      if (y > maxY) maxY = y;
    }
    if (!Number.isFinite(minX)) return null;
    return { minX, minY, maxX, maxY };
  }

  function fitView(w, h) {
    const b = worldBounds();
    if (!b) return;
    const bw = Math.max(b.maxX - b.minX, 4);
    const bh = Math.max(b.maxY - b.minY, 4);
    state.view.scale = Math.min((w - 48) / bw, (h - 48) / bh);
    state.view.cx = (b.minX + b.maxX) / 2;
    state.view.cy = (b.minY + b.maxY) / 2;
  }

  function draw() {
    const { w, h, dpr } = resizeCanvas();
    if (!state.dirty) return;
    state.dirty = false;
    if (state.autoFit && !state.follow) fitView(w, h);
    const v = state.view;
    const sx = (x) => w / 2 + (x - v.cx) * v.scale;
    const sy = (y) => h / 2 - (y - v.cy) * v.scale;

    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    drawGrid(w, h, sx, sy);

    const m = state.map;
    if (m) {
      const res = m.info.resolution;
      const left = sx(m.info.originX);
      const top = sy(m.info.originY + m.height * res);
      ctx.imageSmoothingEnabled = v.scale * res < 2; // crisp cells when zoomed in
      ctx.drawImage(m.bitmap, left, top, m.width * res * v.scale, m.height * res * v.scale);
    }

    const traj = state.traj;
    if (traj.length > 1) {
      ctx.lineJoin = "round";
      ctx.lineCap = "round";
      ctx.strokeStyle = "rgba(255,255,255,0.85)";
      ctx.lineWidth = 5;
      tracePath(traj, sx, sy);
      ctx.stroke();
      ctx.strokeStyle = rgb(TRAJECTORY_RGB);
      ctx.lineWidth = 2.5;
      tracePath(traj, sx, sy);
      ctx.stroke();
      const [x0, y0] = traj[0];
      ctx.fillStyle = rgb(TRAJECTORY_RGB);
      ctx.strokeStyle = "#fff";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(sx(x0), sy(y0), 5, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
    }

    if (state.closures.length) {
      ctx.strokeStyle = rgb(CLOSURE_RGB);
      ctx.lineWidth = 1.5;
      ctx.setLineDash([4, 3]);
      ctx.beginPath();
      for (const [[x0, y0], [x1, y1]] of state.closures) {
        ctx.moveTo(sx(x0), sy(y0));
        ctx.lineTo(sx(x1), sy(y1));
      }
      ctx.stroke();
      ctx.setLineDash([]);
    }

    const p = state.pose;
    if (p) drawRobot(sx(p.x), sy(p.y), p.theta, p.quality);
    drawScaleBar(w, h);
  }

  // Light metre grid (or coarser when zoomed out) behind the map, for reading distances.
  function drawGrid(w, h, sx, sy) {
    const v = state.view;
    let step = 1;
    while (step * v.scale < 24) step *= step === 1 ? 5 : 2;
    const x0 = v.cx - w / 2 / v.scale, x1 = v.cx + w / 2 / v.scale;
    const y0 = v.cy - h / 2 / v.scale, y1 = v.cy + h / 2 / v.scale;
    ctx.strokeStyle = "rgba(28, 36, 48, 0.07)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      const px = Math.round(sx(x)) + 0.5;
      ctx.moveTo(px, 0);
      ctx.lineTo(px, h);
    }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      const py = Math.round(sy(y)) + 0.5;
      ctx.moveTo(0, py);
      ctx.lineTo(w, py);
    }
    ctx.stroke();
  }

  function tracePath(pts, sx, sy) {
    ctx.beginPath();
    // Skip points that land on the same screen pixel: long trajectories stay cheap.
    let lx = NaN, ly = NaN;
    for (let i = 0; i < pts.length; i++) {
      const x = sx(pts[i][0]);
      const y = sy(pts[i][1]);
      if (i === 0) ctx.moveTo(x, y);
      else if (Math.abs(x - lx) >= 1 || Math.abs(y - ly) >= 1 || i === pts.length - 1) ctx.lineTo(x, y);
      else continue;
      lx = x;
      ly = y;
    }
  }

  function drawRobot(x, y, theta, quality) {
    const r = Math.max(9, Math.min(22, 0.3 * state.view.scale));
    // Halo whose size grows as quality drops: a quick visual of uncertainty.
    const halo = r * (1.6 + 1.4 * (1 - Math.max(0, Math.min(1, quality))));
    ctx.fillStyle = rgb(ROBOT_RGB, 0.16);
    ctx.beginPath();
    ctx.arc(x, y, halo, 0, 2 * Math.PI);
    ctx.fill();
    ctx.save();
    ctx.translate(x, y);
    ctx.rotate(-theta); // screen y points down
    ctx.beginPath();
    ctx.moveTo(r * 1.25, 0);
    ctx.lineTo(-r * 0.8, r * 0.75);
    ctx.lineTo(-r * 0.4, 0);
    ctx.lineTo(-r * 0.8, -r * 0.75);
    ctx.closePath();
    ctx.fillStyle = rgb(ROBOT_RGB);
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 2;
    ctx.fill();
    ctx.stroke();
    ctx.restore();
  }

  function drawScaleBar(w, h) {
    const target = 110; // pixels
    const metres = target / state.view.scale;
    const pow = Math.pow(10, Math.floor(Math.log10(metres)));
    const nice = [1, 2, 5, 10].map((k) => k * pow).filter((v) => v <= metres).pop() || pow;
    const px = nice * state.view.scale;
    const x0 = 16, y0 = h - 18;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(x0 - 8, y0 - 22, px + 16 + 40, 32);
    ctx.strokeStyle = "#1c2430";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x0, y0 - 6);
    ctx.lineTo(x0, y0);
    ctx.lineTo(x0 + px, y0);
    ctx.lineTo(x0 + px, y0 - 6);
    ctx.stroke();
    ctx.fillStyle = "#1c2430";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textBaseline = "bottom";
    const label = nice >= 1 ? `${nice} m` : `${Math.round(nice * 100)} cm`;
    ctx.fillText(label, x0 + px + 8, y0 + 2);
  }

  function frame() {
    draw();
    requestAnimationFrame(frame);
  }

  // ------------------------------------------------------------------------------------------
  // Interaction

  el.canvas.addEventListener(
    "wheel",
    (ev) => {
      ev.preventDefault();
      const rect = el.canvas.getBoundingClientRect();
      const mx = ev.clientX - rect.left, my = ev.clientY - rect.top;
      const v = state.view;
      const wx = v.cx + (mx - rect.width / 2) / v.scale;
      const wy = v.cy - (my - rect.height / 2) / v.scale;
      const k = Math.exp(-ev.deltaY * 0.0015);
      v.scale = Math.max(2, Math.min(2000, v.scale * k));
      // Keep the world point under the cursor fixed.
      v.cx = wx - (mx - rect.width / 2) / v.scale;
      v.cy = wy + (my - rect.height / 2) / v.scale;
      state.autoFit = false;
      state.dirty = true;
    },
    { passive: false },
  );
  el.canvas.addEventListener("pointerdown", (ev) => {
    state.drag = { x: ev.clientX, y: ev.clientY, cx: state.view.cx, cy: state.view.cy };
    el.canvas.setPointerCapture(ev.pointerId);
    el.canvas.classList.add("dragging");
  });
  el.canvas.addEventListener("pointermove", (ev) => {
    const d = state.drag;
    if (!d) return;
    state.view.cx = d.cx - (ev.clientX - d.x) / state.view.scale;
    state.view.cy = d.cy + (ev.clientY - d.y) / state.view.scale;
    state.autoFit = false;
    setFollow(false);
    state.dirty = true;
  });
  const endDrag = () => {
    state.drag = null;
    el.canvas.classList.remove("dragging");
  };
  el.canvas.addEventListener("pointerup", endDrag);
  el.canvas.addEventListener("pointercancel", endDrag);
  el.canvas.addEventListener("dblclick", () => {
    state.autoFit = true;
    setFollow(false);
    state.dirty = true;
  });
  el.fit.addEventListener("click", () => {
    state.autoFit = true;
    setFollow(false);
    state.dirty = true;
  });
  function setFollow(on) {
    state.follow = on;
    el.follow.setAttribute("aria-pressed", String(on));
    if (on && state.pose) {
      state.view.cx = state.pose.x;
      state.view.cy = state.pose.y;
    }
    state.dirty = true;
  }
  el.follow.addEventListener("click", () => setFollow(!state.follow));
  window.addEventListener("resize", () => (state.dirty = true));

  el.select.addEventListener("change", () => selectSession(el.select.value || null));

  el.token.value = localStorage.getItem(TOKEN_KEY) || "";
  el.token.addEventListener("change", () => {
    const t = el.token.value.trim();
    if (t) localStorage.setItem(TOKEN_KEY, t);
    else localStorage.removeItem(TOKEN_KEY);
    say(t ? "Token saved in this browser." : "Token cleared.");
    // Reconnect with the new token: the stream, the session list and the map.
    askedForToken = false;
    if (state.es) {
      state.es.close();
      state.es = null;
    }
    state.nextMapAt = 0;
    refreshSessions().then(() => {
      if (state.sessionId && !state.traj.length) loadTrajectory(state.sessionId);
      refreshMap();
    });
  });

  async function control(action, button) {
    const id = state.sessionId;
    if (!id) return;
    button.disabled = true;
    try {
      const r = await api("POST", sessionPath(id, action));
      const body = await r.json();
      if (action === "save") {
        showSaved(body);
        say(`Saved map ${body.map_id} (version ${body.version}).`);
      } else {
        if (action === "reset") {
          state.traj = [];
          state.pose = null;
          state.lastSeq = -1;
          state.map = null;
          state.autoFit = true;
          renderPose();
        }
        updateSession(body);
        say(action === "stop" ? `Session ${id} stopped.` : `Session ${id} reset.`);
        refreshMap();
      }
    } catch (err) {
      say(explain(err), "error");
    } finally {
      renderSession();
    }
  }

  // Saved files are fetched with the token (a plain link could not send it) and handed to
  // the browser as a download.
  function savedLink(url, text, filename) {
    const a = document.createElement("a");
    a.href = url;
    a.textContent = text;
    a.addEventListener("click", async (ev) => {
      ev.preventDefault();
      try {
        const blob = await (await api("GET", url)).blob();
        const local = document.createElement("a");
        local.href = URL.createObjectURL(blob);
        local.download = filename;
        local.click();
        setTimeout(() => URL.revokeObjectURL(local.href), 60000);
      } catch (err) {
        say(explain(err), "error");
      }
    });
    return a;
  }

  function showSaved(saved) {
    el.savedCard.hidden = false;
    const base = `${saved.map_id}-v${saved.version}`;
    const png = savedLink(saved.urls.png, `${saved.map_id} · v${saved.version}`, `${base}.png`);
    const links = ["pgm", "yaml"].map((k) => savedLink(saved.urls[k], k, `${base}.${k}`));
    el.savedText.replaceChildren(png, " (png) · ", links[0], " · ", links[1]);
  }

  el.stop.addEventListener("click", () => control("stop", el.stop));
  el.save.addEventListener("click", () => control("save", el.save));
  el.reset.addEventListener("click", () => {
    if (confirm("Clear this session's map and trajectory?")) control("reset", el.reset);
  });

  el.startForm.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const robot = el.robotInput.value.trim();
    if (!robot) return;
    try {
      const r = await api("POST", "/sessions", { robot_id: robot });
      const s = await r.json();
      state.sessions.push(s);
      renderPicker();
      selectSession(s.id);
      el.robotInput.value = "";
      say(`Started session ${s.id} for ${robot}.`);
    } catch (err) {
      say(explain(err), "error");
    }
  });

  // ------------------------------------------------------------------------------------------
  // Main loop

  refreshSessions();
  setInterval(refreshSessions, SESSIONS_PERIOD_MS);
  setInterval(refreshMap, MAP_PERIOD_MS);
  setInterval(renderAge, 1000);
  requestAnimationFrame(frame);
})();
