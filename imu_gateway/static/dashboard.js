/* imu-gateway live dashboard: plain JS, no dependencies, nothing from the internet.
 *
 * Data: GET /api/v1/sensors (the list, then every 2 s for status and rates),
 * GET /api/v1/buses (every 2 s) and the Server-Sent Events of GET /api/v1/stream.
 * With ?token=... in the page address every request carries "Authorization: Bearer";
 * EventSource cannot send headers, so the stream gets it as ?access_token= instead.
 *
 * Readings may arrive at hundreds per second: they only update the model and mark the
 * sensor dirty; the DOM and the canvases are redrawn at most once per animation frame.
 *
 * Test hooks: each card has data-sensor=name; the horizon canvas carries data-pitch,
 * data-roll, data-yaw (the values it was last drawn with); value cells have
 * data-field="pitch", "accel_x", "q0", "status", "seq", "age", ... and each bus card
 * has data-bus=name.
 */
"use strict";

(function () {
  // Relative to the page, so the dashboard also works behind a reverse proxy that
  // serves the gateway under a path prefix (/gateway-1/ → /gateway-1/api/v1).
  const API = "api/v1";
  const POLL_MS = 2000; // sensors and buses
  const D2R = Math.PI / 180;

  // The reading JSON's groups, with their units and the digits of the sensors'
  // resolution: filled from GET /api/v1/groups at the start (the gateway's one table).
  const GROUPS = [];
  const LABELS = { quaternion: "quat" }; // shorter than the key where space is short

  function learnGroups(groups) {
    GROUPS.length = 0;
    for (const g of groups) {
      GROUPS.push({
        key: g.group, label: LABELS[g.group] || g.group, unit: g.unit, digits: g.digits,
        // a field's member in the group: accel_x -> x, pitch -> pitch, q0 -> q0
        members: g.fields.map((f) => [f.includes("_") ? f.split("_").pop() : f, f]),
      });
    }
  }

  const token = new URLSearchParams(location.search).get("token");
  const headers = token ? { Authorization: "Bearer " + token } : {};
  const sensors = new Map(); // name -> state
  const down = new Set(); // which links are down: "stream", "api"
  let unauthorised = false;

  const $ = (id) => document.getElementById(id);

  // ------------------------------------------------------------------ fetching

  class HttpError extends Error {
    constructor(status, message) { super(message); this.status = status; }
  }

  async function api(path) {
    const response = await fetch(API + path, { headers, cache: "no-store" });
    if (!response.ok) {
      let message = response.statusText;
      try { message = (await response.json()).error || message; } catch (e) { /* not JSON */ }
      throw new HttpError(response.status, message);
    }
    return response.json();
  }

  function setDown(link, isDown, error) {
    if (error && error.status === 401) unauthorised = true;
    else if (!isDown && link === "api") unauthorised = false;
    if (isDown) down.add(link); else down.delete(link);
    const banner = $("banner");
    if (unauthorised) {
      banner.textContent = token
        ? "unauthorised: the token in the address was refused"
        : "unauthorised: open this page with ?token=… in its address";
    } else {
      banner.textContent = "disconnected: reconnecting…";
    }
    banner.hidden = down.size === 0 && !unauthorised;
    document.body.classList.toggle("is-down", !banner.hidden);
  }

  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  // ------------------------------------------------------------------ sensor cards

  function makeCard(info) {
    const node = $("sensor-card").content.firstElementChild.cloneNode(true);
    node.dataset.sensor = info.name;
    node.querySelector(".name").textContent = info.name;
    node.querySelector(".meta").textContent =
      `${info.series} · ${info.protocol} · bus ${info.bus}`;
    const cells = {};
    for (const el of node.querySelectorAll("[data-field]")) cells[el.dataset.field] = el;
    return {
      name: info.name,
      series: info.series,
      info,
      reading: null, // the latest reading JSON with groups
      status: info.status,
      seq: info.seq,
      ageMs: info.age_ms, // as of ageAt (performance.now())
      ageAt: performance.now(),
      groupsShown: "", // which value groups the card has cells for
      card: node,
      cells,
      horizon: node.querySelector("canvas.horizon"),
      heading: node.querySelector("canvas.heading"),
      noAttitude: node.querySelector(".no-attitude"),
      values: node.querySelector(".values"),
    };
  }

  function buildValues(s, present) {
    s.values.replaceChildren();
    for (const group of GROUPS) {
      for (const [, field] of group.members) delete s.cells[field];
    }
    for (const group of GROUPS) {
      if (!present.includes(group.key)) continue;
      const row = document.createElement("div");
      row.className = "group group-" + group.key;
      const name = document.createElement("div");
      name.className = "gname";
      name.textContent = group.label;
      if (group.unit) {
        const unit = document.createElement("small");
        unit.textContent = group.unit;
        name.append(" ", unit);
      }
      row.append(name);
      for (const [member, field] of group.members) {
        const cell = document.createElement("div");
        cell.className = "v";
        const label = document.createElement("i");
        label.textContent = member;
        const value = document.createElement("b");
        value.dataset.field = field;
        value.textContent = "–";
        cell.append(label, value);
        row.append(cell);
        s.cells[field] = value;
      }
      s.values.append(row);
    }
    s.groupsShown = present.join(",");
  }

  // ------------------------------------------------------------------ the model

  const dirty = new Set();
  let frameRequested = false;

  function markDirty(s) {
    dirty.add(s);
    if (!frameRequested) {
      frameRequested = true;
      requestAnimationFrame(frame);
    }
  }

  function frame() {
    frameRequested = false;
    const now = performance.now();
    for (const s of dirty) render(s, now);
    dirty.clear();
  }

  /** A reading (or status) event, or a polled reading: the reading JSON. */
  function onReading(data) {
    const s = sensors.get(data.sensor);
    if (!s) return;
    const hasGroups = GROUPS.some((g) => data[g.key]);
    if (hasGroups) {
      const last = s.reading;
      if (last && data.seq === last.seq && data.status === last.status) return; // no news
      if (!last || data.seq !== last.seq) {
        s.ageMs = 0;
        s.ageAt = performance.now();
      }
      s.reading = data;
    }
    s.status = data.status;
    s.seq = data.seq;
    markDirty(s);
  }

  /** A row of GET /api/v1/sensors. */
  function onSensorInfo(info) {
    const s = sensors.get(info.name);
    if (!s) return;
    s.info = info;
    s.status = info.status;
    if (info.seq >= s.seq) s.seq = info.seq;
    if (info.age_ms !== null) {
      s.ageMs = info.age_ms;
      s.ageAt = performance.now();
    }
    markDirty(s);
  }

  function fmtAge(ms) {
    if (ms === null || ms === undefined) return "–";
    if (ms < 1000) return Math.round(ms) + " ms";
    if (ms < 60000) return (ms / 1000).toFixed(1) + " s";
    if (ms < 3600000) return Math.round(ms / 60000) + " min";
    return (ms / 3600000).toFixed(1) + " h";
  }

  function showAge(s, now) {
    const age = s.ageMs === null || s.ageMs === undefined ? null : s.ageMs + (now - s.ageAt);
    s.cells.age.textContent = fmtAge(age);
  }

  function render(s, now) {
    const r = s.reading;
    const present = r ? GROUPS.filter((g) => r[g.key]).map((g) => g.key) : [];
    if (r && present.join(",") !== s.groupsShown) buildValues(s, present);
    if (r) {
      for (const group of GROUPS) {
        const values = r[group.key];
        if (!values) continue;
        for (const [member, field] of group.members) {
          s.cells[field].textContent = values[member].toFixed(group.digits);
        }
      }
    }
    // Status and flags.
    const status = s.status || "offline";
    s.card.classList.remove("is-ok", "is-stale", "is-offline");
    s.card.classList.add("is-" + status);
    s.cells.status.textContent = status;
    s.cells.busy.hidden = !s.info.busy;
    s.cells.streaming.hidden = !s.info.streaming;
    s.cells.seq.textContent = String(s.seq);
    s.cells.rate.textContent = s.info.achieved_hz.toFixed(1) + " Hz";
    s.cells.errors.textContent = String(s.info.errors);
    showAge(s, now);
    // Instruments: the series without angles (IMU) has none.
    const attitude = r ? Boolean(r.angles) : s.series !== "IMU";
    s.horizon.hidden = !attitude;
    s.heading.hidden = !attitude;
    s.noAttitude.hidden = attitude;
    if (attitude) {
      const a = r && r.angles ? r.angles : null;
      drawHorizon(s.horizon, a);
      drawHeading(s.heading, a ? a.yaw : null);
    }
  }

  // ------------------------------------------------------------------ drawing

  /** The canvas's 2-D context, its backing store matched to its CSS size. */
  function prepare(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const bw = Math.max(1, Math.round(w * dpr)), bh = Math.max(1, Math.round(h * dpr));
    if (canvas.width !== bw || canvas.height !== bh) {
      canvas.width = bw;
      canvas.height = bh;
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    return { ctx, w, h };
  }

  function drawHorizon(canvas, angles) {
    const { ctx, w } = prepare(canvas);
    const pitch = angles ? angles.pitch : 0, roll = angles ? angles.roll : 0;
    const S = w, R = S / 2;
    const ppd = S / 50; // pixels per degree of pitch: ±25° from the centre to the rim
    ctx.save();
    ctx.translate(R, R);
    // The ball: clipped to a circle, rotated by -roll, shifted by pitch.
    ctx.save();
    ctx.beginPath();
    ctx.arc(0, 0, R - 1, 0, 2 * Math.PI);
    ctx.clip();
    ctx.rotate(-roll * D2R);
    const y0 = pitch * ppd;
    const sky = ctx.createLinearGradient(0, y0 - R * 1.4, 0, y0);
    sky.addColorStop(0, "#0f4c8a");
    sky.addColorStop(1, "#4a9be0");
    ctx.fillStyle = sky;
    ctx.fillRect(-2 * S, y0 - 3 * S, 4 * S, 3 * S);
    const ground = ctx.createLinearGradient(0, y0, 0, y0 + R * 1.4);
    ground.addColorStop(0, "#9a6531");
    ground.addColorStop(1, "#4d2f14");
    ctx.fillStyle = ground;
    ctx.fillRect(-2 * S, y0, 4 * S, 3 * S);
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(-2 * S, y0);
    ctx.lineTo(2 * S, y0);
    ctx.stroke();
    // Pitch ladder: every 5°, labelled every 10°.
    ctx.lineWidth = 1.5;
    ctx.fillStyle = "#fff";
    ctx.font = `600 ${Math.max(9, Math.round(S / 24))}px system-ui, sans-serif`;
    ctx.textBaseline = "middle";
    const first = Math.ceil((pitch - 30) / 5) * 5;
    for (let d = first; d <= pitch + 30; d += 5) {
      if (d === 0 || d < -90 || d > 90) continue;
      const y = y0 - d * ppd;
      if (Math.abs(y) > R * 0.7) continue; // clear of the roll scale
      const half = d % 10 === 0 ? S * 0.14 : S * 0.07;
      ctx.beginPath();
      ctx.moveTo(-half, y);
      ctx.lineTo(half, y);
      ctx.stroke();
      if (d % 10 === 0) {
        ctx.textAlign = "right";
        ctx.fillText(String(Math.abs(d)), -half - 4, y);
        ctx.textAlign = "left";
        ctx.fillText(String(Math.abs(d)), half + 4, y);
      }
    }
    ctx.restore();
    // Roll scale (fixed) with the sky pointer (turns with the horizon).
    const rr = R * 0.86;
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    ctx.arc(0, 0, rr, (-90 - 60) * D2R, (-90 + 60) * D2R);
    ctx.stroke();
    for (const t of [-60, -45, -30, -20, -10, 10, 20, 30, 45, 60]) {
      const len = Math.abs(t) % 30 === 0 ? R * 0.09 : R * 0.05;
      const a = (t - 90) * D2R;
      ctx.beginPath();
      ctx.moveTo(Math.cos(a) * rr, Math.sin(a) * rr);
      ctx.lineTo(Math.cos(a) * (rr + len), Math.sin(a) * (rr + len));
      ctx.stroke();
    }
    const tri = R * 0.06;
    ctx.beginPath(); // the zero index, fixed, outside the arc
    ctx.moveTo(0, -rr - 1);
    ctx.lineTo(-tri, -rr - tri * 1.6);
    ctx.lineTo(tri, -rr - tri * 1.6);
    ctx.closePath();
    ctx.stroke();
    ctx.save();
    ctx.rotate(-roll * D2R);
    ctx.fillStyle = "#ffd21f";
    ctx.beginPath(); // the sky pointer, inside the arc
    ctx.moveTo(0, -rr + 1);
    ctx.lineTo(-tri, -rr + tri * 1.6);
    ctx.lineTo(tri, -rr + tri * 1.6);
    ctx.closePath();
    ctx.fill();
    ctx.restore();
    // The aircraft symbol, fixed.
    const wing = S * 0.2, gap = S * 0.07, bar = Math.max(3, S * 0.018);
    ctx.fillStyle = "#ffd21f";
    ctx.strokeStyle = "#000";
    ctx.lineWidth = 1;
    for (const side of [-1, 1]) {
      ctx.beginPath();
      const x0 = side * gap, x1 = side * (gap + wing);
      ctx.moveTo(x0, -bar / 2);
      ctx.lineTo(x1, -bar / 2);
      ctx.lineTo(x1, bar / 2);
      ctx.lineTo(x0 + side * bar, bar / 2);
      ctx.lineTo(x0 + side * bar, bar * 2.5);
      ctx.lineTo(x0, bar * 2.5);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
    }
    ctx.fillRect(-bar / 2, -bar / 2, bar, bar);
    ctx.strokeRect(-bar / 2, -bar / 2, bar, bar);
    // The bezel.
    ctx.strokeStyle = "#2b3340";
    ctx.lineWidth = 3;
    ctx.beginPath();
    ctx.arc(0, 0, R - 1.5, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.restore();
    if (angles) {
      canvas.dataset.pitch = String(angles.pitch);
      canvas.dataset.roll = String(angles.roll);
      canvas.dataset.yaw = String(angles.yaw);
    }
  }

  const CARDINAL = { 0: "N", 90: "E", 180: "S", 270: "W" };

  function drawHeading(canvas, yaw) {
    const { ctx, w, h } = prepare(canvas);
    const cx = w / 2, ppd = w / 100; // ±50° across the tape
    ctx.fillStyle = "#10151d";
    ctx.fillRect(0, 0, w, h);
    const y = yaw === null ? 0 : yaw;
    ctx.strokeStyle = "#c9d3e0";
    ctx.fillStyle = "#c9d3e0";
    ctx.lineWidth = 1;
    ctx.textAlign = "center";
    ctx.textBaseline = "top";
    const font = Math.max(9, Math.round(h / 4));
    for (let d = Math.ceil((y - 55) / 5) * 5; d <= y + 55; d += 5) {
      const x = cx + (d - y) * ppd;
      const deg = ((d % 360) + 360) % 360;
      const major = deg % 10 === 0;
      ctx.beginPath();
      ctx.moveTo(x, h);
      ctx.lineTo(x, h - (major ? h * 0.28 : h * 0.15));
      ctx.stroke();
      if (deg % 30 === 0 && Math.abs(x - cx) > h * 0.9) { // clear of the readout
        const label = CARDINAL[deg] || String(deg / 10);
        ctx.font = `${CARDINAL[deg] ? 700 : 500} ${font}px system-ui, sans-serif`;
        ctx.fillText(label, x, h * 0.32);
      }
    }
    // The lubber line and the readout.
    ctx.strokeStyle = "#ffd21f";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(cx, h * 0.3);
    ctx.lineTo(cx, h);
    ctx.stroke();
    const text = yaw === null ? "---" : String(Math.round(y) % 360).padStart(3, "0") + "°";
    ctx.font = `700 ${font}px ui-monospace, monospace`;
    const bw = ctx.measureText("000°").width + 10, bh = font + 6;
    ctx.fillStyle = "#000";
    ctx.strokeStyle = "#ffd21f";
    ctx.lineWidth = 1.5;
    ctx.fillRect(cx - bw / 2, 1, bw, bh);
    ctx.strokeRect(cx - bw / 2, 1, bw, bh);
    ctx.fillStyle = "#fff";
    ctx.fillText(text, cx, 4);
  }

  // ------------------------------------------------------------------ buses

  function busCard(bus) {
    let node = document.querySelector(`[data-bus="${CSS.escape(bus.name)}"]`);
    if (!node) {
      node = document.createElement("article");
      node.className = "bus";
      node.dataset.bus = bus.name;
      node.innerHTML = `<header class="card-head"><div class="title"><h3 class="name"></h3>
        <span class="meta" data-field="port"></span></div>
        <div class="badges"><span class="badge" data-field="port_open"></span></div></header>
        <dl class="stats">
          <div><dt>baud</dt><dd data-field="baudrate"></dd></div>
          <div><dt>protocol</dt><dd data-field="protocol"></dd></div>
          <div><dt>transactions/s</dt><dd data-field="transactions_per_s"></dd></div>
          <div><dt>utilisation</dt><dd data-field="utilisation"></dd></div>
          <div><dt>queue</dt><dd data-field="queue_depth"></dd></div>
          <div><dt>errors</dt><dd data-field="errors"></dd></div>
          <div class="wide"><dt>errors by kind</dt><dd data-field="error_kinds"></dd></div>
          <div class="wide"><dt>sensors</dt><dd data-field="sensors"></dd></div>
        </dl>`;
      node.querySelector(".name").textContent = bus.name;
      $("buses").append(node);
    }
    return node;
  }

  function showBuses(buses) {
    for (const bus of buses) {
      const node = busCard(bus);
      const set = (field, text) => {
        node.querySelector(`[data-field="${field}"]`).textContent = text;
      };
      set("port", bus.port);
      set("port_open", bus.port_open ? "port open" : "port closed");
      node.classList.toggle("is-ok", bus.port_open);
      node.classList.toggle("is-offline", !bus.port_open);
      set("baudrate", String(bus.baudrate));
      set("protocol", bus.protocol);
      set("transactions_per_s", bus.transactions_per_s.toFixed(1));
      set("utilisation", (bus.utilisation * 100).toFixed(1) + " %");
      const kinds = Object.entries(bus.errors).filter(([, n]) => n > 0);
      const total = kinds.reduce((sum, [, n]) => sum + n, 0);
      set("errors", String(total));
      set("error_kinds", kinds.map(([k, n]) => `${k} ${n}`).join(", ") || "–");
      set("queue_depth", String(bus.queue_depth));
      set("sensors", bus.sensors.join(", ") || "–");
    }
  }

  // ------------------------------------------------------------------ live data

  function openStream() {
    const query = token ? "?access_token=" + encodeURIComponent(token) : "";
    const stream = new EventSource(API + "/stream" + query);
    stream.addEventListener("open", () => setDown("stream", false));
    stream.addEventListener("reading", (e) => onReading(JSON.parse(e.data)));
    stream.addEventListener("status", (e) => onReading(JSON.parse(e.data)));
    stream.addEventListener("error", () => {
      setDown("stream", true);
      if (stream.readyState === EventSource.CLOSED) { // it gave up: try again ourselves
        stream.close();
        setTimeout(openStream, 3000);
      }
    });
  }

  async function pollStatus() {
    for (;;) {
      try {
        const [list, buses] = await Promise.all([api("/sensors"), api("/buses")]);
        for (const info of list) onSensorInfo(info);
        showBuses(buses);
        setDown("api", false);
      } catch (error) {
        setDown("api", true, error);
      }
      await sleep(POLL_MS);
    }
  }

  async function start() {
    $("mode").textContent = token ? "live (token)" : "live";
    let list;
    for (;;) {
      try {
        const [sensorList, groups] = await Promise.all([api("/sensors"), api("/groups")]);
        list = sensorList;
        learnGroups(groups);
        setDown("api", false);
        break;
      } catch (error) {
        setDown("api", true, error);
        await sleep(POLL_MS);
      }
    }
    const container = $("sensors");
    container.replaceChildren();
    if (list.length === 0) container.innerHTML = '<p class="empty">No sensors configured.</p>';
    for (const info of list) {
      const s = makeCard(info);
      sensors.set(info.name, s);
      container.append(s.card);
      markDirty(s);
    }
    api("/health").then((health) => {
      $("mode").textContent = `${health.gateway_id} · v${health.version} · ` +
        (token ? "live (token)" : "live");
    }, () => { /* shown by the banner */ });
    pollStatus();
    openStream();
    // The age keeps growing between readings.
    setInterval(() => {
      const now = performance.now();
      for (const s of sensors.values()) showAge(s, now);
    }, 250);
    // The canvases follow the layout (rotation of a phone, a resized window).
    window.addEventListener("resize", () => { for (const s of sensors.values()) markDirty(s); });
  }

  start();
})();
