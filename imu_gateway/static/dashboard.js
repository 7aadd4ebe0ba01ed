/* imu-gateway live dashboard: plain JS, no dependencies, nothing from the internet.
 *
 * Data: GET /api/v1/sensors (the list, then every 2 s for status and rates),
 * GET /api/v1/buses and GET /api/v1/alarms (every 2 s), GET /api/v1/alarms/journal
 * (whenever the stream opens), GET /api/v1/captures (every 2 s, when GET /api/v1/health
 * says capture is on) and the Server-Sent Events of GET /api/v1/stream.
 * Who is looking comes from login.js (window.imuAuth): with a credential every request
 * carries "Authorization: Bearer", never a token in a URL; a viewer gets no command,
 * acknowledge or capture buttons.
 *
 * Readings may arrive at hundreds per second: they only update the model and mark the
 * sensor dirty; the DOM and the canvases are redrawn at most once per animation frame.
 *
 * Test hooks: each card has data-sensor=name; the horizon canvas carries data-pitch,
 * data-roll, data-yaw (the values it was last drawn with); value cells have
 * data-field="pitch", "accel_x", "q0", "status", "seq", "age", ... and each bus card
 * has data-bus=name.  Alarms: #alarm-banner has data-critical, data-warning, data-info
 * (active alarms) and data-unacked; a card's alarm lines (ul.alarms li) data-alarm and
 * data-state; a trend canvas data-marks (the transitions marked on it); each line of
 * the journal (#journal li) data-alarm="sensor/alarm", data-from and data-to.
 * Captures: #captures-section has data-capture ("on" or "off"); each line of the list
 * (#captures li) data-capture (its id), data-trigger, data-alarm, data-time, data-size,
 * and its download link a.download; #capture-result data-ok and data-capture.
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
  // "G" beside "g" is misread at a glance: the long name where the symbol is ambiguous
  const UNIT_SHOWN = { G: "gauss" };
  const TREND_S = 600; // the trends' window (the gateway keeps as much)
  const ERROR_WINDOW_MS = 60000; // errors are shown as a rate over the last minute
  const DOWNLOAD_MS = 120000; // a capture's download given up after this long

  function learnGroups(groups) {
    GROUPS.length = 0;
    for (const g of groups) {
      GROUPS.push({
        key: g.group, label: LABELS[g.group] || g.group, unit: UNIT_SHOWN[g.unit] || g.unit,
        digits: g.digits,
        // a field's member in the group (the gateway says: accel_x -> x, tilt -> tilt,
        // tilt_direction -> tilt_direction)
        members: g.fields.map((f, i) => [g.members[i], f]),
      });
    }
  }

  const auth = window.imuAuth;
  const token = auth.credential();
  const headers = auth.headers();
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
      banner.textContent = token ? "unauthorised: the session ended: log in again"
        : "unauthorised: log in";
    } else {
      banner.textContent = "disconnected: reconnecting…";
    }
    banner.hidden = down.size === 0 && !unauthorised;
    const wasDown = document.body.classList.contains("is-down");
    document.body.classList.toggle("is-down", !banner.hidden);
    if (wasDown !== !banner.hidden) {
      for (const s of sensors.values()) markDirty(s);
      markAlarms();
    }
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
      trends: node.querySelector(".trends"),
      trend: { t: [], fields: {} }, // one-second buckets: t, and per field min/max/last
      errorSamples: [], // [time, errors] of the last minute's polls
      alarmsShown: null, // what the card's alarm lines show (skip redrawing the same)
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
    requestFrame();
  }

  function requestFrame() {
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
    if (alarmsDirty) renderAlarms();
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
      addToTrend(s, data);
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
    const now = performance.now();
    s.errorSamples.push([now, info.errors]);
    while (s.errorSamples.length > 2 && now - s.errorSamples[0][0] > ERROR_WINDOW_MS) {
      s.errorSamples.shift();
    }
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
          // null: no value now (a derived one: the vibration before a second of samples)
          const v = values[member];
          s.cells[field].textContent = v === null || v === undefined ? "–" : v.toFixed(group.digits);
        }
      }
    }
    showStatus(s);
    s.cells.busy.hidden = !s.info.busy;
    s.cells.streaming.hidden = !s.info.streaming;
    s.cells.seq.textContent = String(s.seq);
    showRate(s);
    showErrors(s);
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

  function clock(ts) {
    return ts ? new Date(ts).toLocaleTimeString() : null;
  }

  /** The status, honestly: a card never looks fresh when it is not. Without a
   *  connection nothing is known (grey, "unknown"); before the first reading the card
   *  says so; stale and offline say since when. */
  function showStatus(s) {
    const status = s.status || "offline";
    const unknown = document.body.classList.contains("is-down");
    // nothing yet, and nothing failed yet: the first answer is still to come
    const waiting = !s.reading && !s.info.ts && s.info.errors === 0;
    s.card.classList.remove("is-ok", "is-stale", "is-offline", "is-waiting", "is-unknown");
    s.card.classList.add(unknown ? "is-unknown" : waiting ? "is-waiting" : "is-" + status);
    s.cells.status.textContent = status;
    const last = clock((s.reading && s.reading.ts) || s.info.ts);
    let reason = "";
    if (unknown) reason = "no connection to the gateway: what is shown may be old";
    else if (waiting) reason = "waiting for the first reading";
    else if (status === "offline") reason = last ? `offline · last reading ${last}`
      : "offline · never answered";
    else if (status === "stale") reason = `stale · last reading ${last || "–"}`;
    s.cells.reason.textContent = reason;
    s.cells.reason.hidden = !reason;
  }

  /** Achieved against requested, flagged when short by more than a tenth. */
  function showRate(s) {
    const achieved = s.info.achieved_hz;
    const requested = s.info.requested_hz;
    s.cells.rate.textContent = requested > 0
      ? `${achieved.toFixed(1)} / ${requested.toFixed(1)} Hz` : `${achieved.toFixed(1)} Hz`;
    s.cells.rate.classList.toggle("short", requested > 0 && achieved < 0.9 * requested);
  }

  /** Errors as a rate over the last minute, with the lifetime total beside it. */
  function showErrors(s) {
    const first = s.errorSamples[0];
    const last = s.errorSamples[s.errorSamples.length - 1];
    const span = first && last ? last[0] - first[0] : 0;
    const perMin = span >= 5000 ? ((last[1] - first[1]) * 60000) / span : null;
    s.cells.errors.textContent = (perMin === null ? "–" : perMin.toFixed(1)) +
      `/min · ${s.info.errors}`;
    s.cells.errors.classList.toggle("short", perMin !== null && perMin > 0);
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
    const labelY = font + 8; // under the readout, so no label hides behind it
    for (let d = Math.ceil((y - 55) / 5) * 5; d <= y + 55; d += 5) {
      const x = cx + (d - y) * ppd;
      const deg = ((d % 360) + 360) % 360;
      const major = deg % 10 === 0;
      ctx.beginPath();
      ctx.moveTo(x, h);
      ctx.lineTo(x, h - (major ? h * 0.28 : h * 0.15));
      ctx.stroke();
      if (deg % 30 === 0) {
        const label = CARDINAL[deg] || String(deg / 10);
        ctx.font = `${CARDINAL[deg] ? 700 : 500} ${font}px system-ui, sans-serif`;
        const half = ctx.measureText(label).width / 2;
        if (x - half >= 0 && x + half <= w) ctx.fillText(label, x, labelY); // whole, or not
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

  // ------------------------------------------------------------------ trends

  /** A reading into its second's bucket (lowest, highest, last of each field). */
  function addToTrend(s, data) {
    const second = Math.floor(Date.parse(data.ts) / 1000);
    if (!Number.isFinite(second)) return;
    const trend = s.trend;
    const n = trend.t.length;
    if (n && second < trend.t[n - 1]) return; // older than what we have
    const fresh = !n || second > trend.t[n - 1];
    if (fresh) trend.t.push(second);
    for (const group of GROUPS) {
      const values = data[group.key];
      if (!values) continue;
      for (const [member, field] of group.members) {
        const v = values[member];
        const f = trend.fields[field] || (trend.fields[field] = { min: [], max: [], last: [] });
        while (f.last.length < trend.t.length - 1) { // a gap: this field had no value
          f.min.push(null); f.max.push(null); f.last.push(null);
        }
        if (f.last.length < trend.t.length) { f.min.push(v); f.max.push(v); f.last.push(v); continue; }
        const i = f.last.length - 1;
        if (v !== null) {
          f.min[i] = f.min[i] === null ? v : Math.min(f.min[i], v);
          f.max[i] = f.max[i] === null ? v : Math.max(f.max[i], v);
          f.last[i] = v;
        }
      }
    }
    const cut = trend.t.findIndex((t) => t > second - TREND_S);
    if (cut > 0) {
      trend.t.splice(0, cut);
      for (const f of Object.values(trend.fields)) {
        f.min.splice(0, cut); f.max.splice(0, cut); f.last.splice(0, cut);
      }
    }
  }

  /** The gateway's record of the last minutes, then kept live from the stream. */
  async function loadTrend(s) {
    try {
      const past = await api(`/sensors/${encodeURIComponent(s.name)}/history?seconds=${TREND_S}`);
      s.trend = { t: past.t, fields: past.fields };
    } catch (error) { /* the stream fills it from now on */ }
  }

  const COLOURS = ["#2f7fd1", "#d1462f", "#2f9d5a", "#8a5a2b"];
  const HEAD = 13; // the band above a chart's plot: its name and its colour legend
  const AXIS = 52; // the gutter left of the plot: its highest and lowest value ("-0.851519")
  // Directions, 0-360 with a wrap: on a shared axis they flatten the other fields
  // (pitch and roll beside yaw) to lines, so each has a chart of its own.
  const DIRECTIONS = new Set(["yaw", "tilt_direction"]);

  /** The charts of a value group: one, and one more per direction in it. */
  function chartsOf(g) {
    const rest = g.members.filter(([, f]) => !DIRECTIONS.has(f));
    const apart = g.members.filter(([, f]) => DIRECTIONS.has(f));
    return [
      ...(rest.length ? [{ key: g.key, label: g.label, group: g, members: rest }] : []),
      ...apart.map((m) => ({ key: m[1], label: m[1].replace(/_/g, " "), group: g, members: [m] })),
    ];
  }

  /** One small chart per value group (angles: two): each field's band (lowest to highest
   *  of each second) and its line (the last value), over the last TREND_S seconds, with
   *  its own axis and a legend of its colours.  Test hooks: data-legend (the fields in
   *  colour order), data-axis ("lowest highest" as labelled). */
  function drawTrends(s) {
    const trend = s.trend;
    const charts = GROUPS.flatMap(chartsOf)
      .filter((c) => c.members.some(([, f]) => trend.fields[f]));
    const keys = charts.map((c) => c.key).join(",");
    if (s.trends.dataset.groups !== keys) {
      s.trends.replaceChildren(...charts.map((c) => {
        const canvas = document.createElement("canvas");
        canvas.className = "trend";
        canvas.dataset.group = c.key;
        canvas.setAttribute("aria-label", `${c.label} over the last ${TREND_S / 60} minutes`);
        return canvas;
      }));
      s.trends.dataset.groups = keys;
    }
    const now = Date.now() / 1000;
    for (const canvas of s.trends.querySelectorAll("canvas")) {
      const chart = charts.find((c) => c.key === canvas.dataset.group);
      drawTrend(canvas, chart, trend, now, marksFor(s, chart, now - TREND_S));
    }
  }

  function drawTrend(canvas, chart, trend, now, marks) {
    const { ctx, w, h } = prepare(canvas);
    const shown = chart.members.filter(([, f]) => trend.fields[f]);
    const fields = shown.map(([, f]) => trend.fields[f]);
    let lo = Infinity;
    let hi = -Infinity;
    for (const f of fields) {
      for (const v of f.min) if (v !== null) lo = Math.min(lo, v);
      for (const v of f.max) if (v !== null) hi = Math.max(hi, v);
    }
    ctx.clearRect(0, 0, w, h);
    canvas.dataset.points = String(trend.t.length);
    canvas.dataset.seconds = String(trend.t.length ? trend.t[trend.t.length - 1] - trend.t[0] : 0);
    canvas.dataset.marks = String(marks.length);
    canvas.dataset.legend = shown.map(([m]) => m).join(",");
    canvas.setAttribute("aria-label", `${chart.label} over the last ${TREND_S / 60} minutes` +
      (marks.length ? `, ${marks.length} alarm transition${marks.length === 1 ? "" : "s"}` : ""));
    const x = (t) => AXIS + ((t - (now - TREND_S)) / TREND_S) * (w - AXIS);
    drawChartFrame(ctx, chart, shown, w, h);
    if (!Number.isFinite(lo)) {
      canvas.dataset.axis = "";
      drawMarks(ctx, marks, x, h);
      return;
    }
    if (hi - lo < 1e-9) { hi += 0.5; lo -= 0.5; }
    const y = (v) => h - 2 - ((v - lo) / (hi - lo)) * (h - HEAD - 4);
    fields.forEach((f, k) => {
      ctx.fillStyle = COLOURS[k % COLOURS.length] + "33";
      ctx.strokeStyle = COLOURS[k % COLOURS.length];
      for (let i = 0; i < trend.t.length; i++) {
        if (f.min[i] === null) continue;
        ctx.fillRect(x(trend.t[i]), y(f.max[i]), Math.max(1, w / TREND_S), y(f.min[i]) - y(f.max[i]) + 1);
      }
      ctx.beginPath();
      let pen = false;
      for (let i = 0; i < trend.t.length; i++) {
        if (f.last[i] === null) { pen = false; continue; }
        if (pen) ctx.lineTo(x(trend.t[i]), y(f.last[i])); else ctx.moveTo(x(trend.t[i]), y(f.last[i]));
        pen = true;
      }
      ctx.stroke();
    });
    drawMarks(ctx, marks, x, h); // over the values: a transition is what the eye looks for
    // the axis: its highest value at the top of the plot, its lowest at the bottom, both
    // in this chart's own gutter (never on the next chart's name)
    const digits = chart.group.digits;
    ctx.fillStyle = "#888";
    ctx.font = "10px sans-serif";
    ctx.textAlign = "right";
    ctx.textBaseline = "top";
    ctx.fillText(hi.toFixed(digits), AXIS - 4, HEAD + 1);
    ctx.textBaseline = "bottom";
    ctx.fillText(lo.toFixed(digits), AXIS - 4, h - 1);
    ctx.textAlign = "left";
    ctx.textBaseline = "alphabetic";
    canvas.dataset.axis = `${lo.toFixed(digits)} ${hi.toFixed(digits)}`;
  }

  /** The chart's name and unit, a legend of its colours, and the axis line. */
  function drawChartFrame(ctx, chart, shown, w, h) {
    ctx.font = "10px sans-serif";
    ctx.fillStyle = "#888";
    const unit = chart.group.unit ? ` (${chart.group.unit})` : "";
    ctx.fillText(chart.label + unit, 2, 10);
    let at = Math.max(AXIS, ctx.measureText(chart.label + unit).width + 10);
    shown.forEach(([member], k) => {
      ctx.fillStyle = COLOURS[k % COLOURS.length];
      ctx.fillRect(at, 3, 8, 8);
      ctx.fillStyle = "#888";
      ctx.fillText(member, at + 11, 10);
      at += ctx.measureText(member).width + 20;
    });
    ctx.strokeStyle = "#8884";
    ctx.beginPath();
    ctx.moveTo(AXIS + 0.5, HEAD);
    ctx.lineTo(AXIS + 0.5, h);
    ctx.stroke();
  }

  // ------------------------------------------------------------------ commands

  /** For an operator, a button for each of the sensor's commands that takes no
   *  arguments (the OpenAPI document says which); the result is shown inline. */
  function showCommands(s, noArguments) {
    if (!auth.may("operator")) return;
    const names = s.info.commands.filter((c) => noArguments.has(c));
    s.card.querySelector(".commands").replaceChildren(...names.map((name) => {
      const button = document.createElement("button");
      button.type = "button";
      button.dataset.command = name;
      button.textContent = name.replace(/_/g, " ");
      button.addEventListener("click", () => runCommand(s, name, button));
      return button;
    }));
    s.card.querySelector(".commands").hidden = names.length === 0;
  }

  async function runCommand(s, name, button) {
    const out = s.cells.command_result;
    button.disabled = true;
    out.textContent = `${name}…`;
    try {
      const response = await fetch(`${API}/sensors/${encodeURIComponent(s.name)}/commands/${name}`,
        { method: "POST", headers: { ...headers, "Content-Type": "application/json" }, body: "{}" });
      const result = await response.json();
      out.textContent = result.ok ? `${name}: ok ${JSON.stringify(result.answer)}`
        : `${name}: ${result.kind || response.status}: ${result.error}`;
      out.dataset.ok = String(Boolean(result.ok));
    } catch (error) {
      out.textContent = `${name}: ${error.message}`;
      out.dataset.ok = "false";
    } finally {
      button.disabled = false;
    }
  }

  async function commandsWithoutArguments() {
    const document_ = await (await fetch("openapi.json", { cache: "no-store" })).json();
    const names = new Set();
    for (const [path, item] of Object.entries(document_.paths)) {
      const match = path.match(/\/commands\/([a-z_]+)$/);
      if (match && item.post && !(item.post.requestBody || {}).required) names.add(match[1]);
    }
    return names;
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

  // ------------------------------------------------------------------ alarms

  // Every alarm's state (GET /api/v1/alarms's rows, by "sensor/alarm"), kept live by the
  // stream's "alarm" events and the 2 s poll; the journal's transitions, oldest first.
  // Alarms change rarely: nothing here runs per reading.
  const SEVERITIES = ["critical", "warning", "info"]; // worst first
  const STATE_WORDS = {
    normal: "normal", active_unacked: "active, unacknowledged",
    active_acked: "active, acknowledged", rtn_unacked: "back to normal, unacknowledged",
  };
  const JOURNAL_KEPT = 1000; // as many as the gateway keeps
  const JOURNAL_SHOWN = 200; // the newest, in the list
  const alarms = new Map();
  const journal = [];
  const journalKeys = new Set(); // the same transition from the journal and the stream
  let alarmsLoaded = false;
  let alarmsDirty = false;
  let journalShown = null; // what the journal list shows (skip redrawing the same)

  const alarmKey = (sensor, alarm) => sensor + "/" + alarm;
  const epoch = (ts) => (ts ? Date.parse(ts) : -Infinity);

  function markAlarms() {
    alarmsDirty = true;
    requestFrame();
  }

  /** An alarm's state (a row of GET /api/v1/alarms, an ack's answer or a stream
   *  event); an older one than we have is ignored. True if it changed anything. */
  function onAlarmState(state) {
    const key = alarmKey(state.sensor, state.alarm);
    const known = alarms.get(key);
    if (known && (epoch(known.since) > epoch(state.since) ||
        (known.since === state.since && known.state === state.state))) return false;
    alarms.set(key, state);
    markAlarms();
    return true;
  }

  /** A transition (a journal row), once, in time order. */
  function addTransition(t) {
    const key = [t.sensor, t.alarm, t.ts, t.from, t.to].join("/");
    if (journalKeys.has(key)) return;
    journalKeys.add(key);
    let i = journal.length;
    while (i > 0 && epoch(journal[i - 1].ts) > epoch(t.ts)) i--;
    journal.splice(i, 0, t);
    while (journal.length > JOURNAL_KEPT) {
      const old = journal.shift();
      journalKeys.delete([old.sensor, old.alarm, old.ts, old.from, old.to].join("/"));
    }
    markAlarms();
  }

  /** The stream's "alarm" event: the state after a transition, with "from" and "by". */
  function onAlarmEvent(data) {
    onAlarmState(data);
    addTransition({ sensor: data.sensor, alarm: data.alarm, ts: data.since, from: data.from,
      to: data.state, value: data.value, limit: data.limit, severity: data.severity,
      by: data.by });
  }

  /** Every alarm and the journal (since the newest transition we have): at the start and
   *  whenever the stream (re)opens, as events may have been missed meanwhile. */
  async function loadAlarms() {
    const last = journal.length ? journal[journal.length - 1].ts : null;
    const query = last ? "?since=" + encodeURIComponent(last) : "";
    const [states, transitions] = await Promise.all([api("/alarms"), api("/alarms/journal" + query)]);
    for (const state of states) onAlarmState(state);
    for (const t of transitions) addTransition(t);
    alarmsLoaded = true;
    markAlarms();
  }

  /** The poll's states: one that changed without its event (the stream skipped it)
   *  brings the journal's missing lines too. */
  function onAlarmPoll(states) {
    let news = false;
    for (const state of states) news = onAlarmState(state) || news;
    if (news) loadAlarms().catch(() => { /* the next poll tries again */ });
  }

  /** "tilt 7.50 (limit 5.00)", at the field's resolution. */
  function valueText(field, value, limit) {
    if (value === null || value === undefined) return "";
    const group = GROUPS.find((g) => g.members.some(([, f]) => f === field));
    const fmt = (v) => (group ? v.toFixed(group.digits) : String(v));
    return `${field || "value"} ${fmt(value)}` + (limit === null ? "" : ` (limit ${fmt(limit)})`);
  }

  function renderAlarms() {
    alarmsDirty = false;
    if (!alarmsLoaded) return;
    showAlarmBanner();
    for (const s of sensors.values()) showCardAlarms(s);
    showJournal();
  }

  /** The count of active alarms by severity, in words (not colour alone). */
  function showAlarmBanner() {
    const counts = { critical: 0, warning: 0, info: 0 };
    let unacked = 0;
    for (const a of alarms.values()) {
      if (a.active) counts[a.severity] += 1;
      if (!a.acked) unacked += 1;
    }
    const banner = $("alarm-banner");
    const active = SEVERITIES.reduce((n, sev) => n + counts[sev], 0);
    const worst = SEVERITIES.find((sev) => counts[sev] > 0) || "none";
    const parts = SEVERITIES.map((sev) => {
      banner.dataset[sev] = String(counts[sev]);
      return `${counts[sev]} ${sev}`;
    });
    banner.dataset.unacked = String(unacked);
    let text = active === 0 ? "no active alarm" : `active alarms: ${parts.join(" · ")}`;
    if (unacked > 0) text += ` · ${unacked} to acknowledge`;
    if (document.body.classList.contains("is-down")) text += " (may be old: no connection)";
    banner.textContent = text;
    banner.className = "alarm-banner worst-" + worst;
    banner.hidden = false;
  }

  /** The card's badge (its active alarms, worst severity) and a line for each alarm
   *  that needs a person (active or unacknowledged), with an acknowledge button for
   *  each unacknowledged one. */
  function showCardAlarms(s) {
    const own = [...alarms.values()].filter((a) => a.sensor === s.name);
    const active = own.filter((a) => a.active);
    const worst = SEVERITIES.find((sev) => active.some((a) => a.severity === sev));
    const badge = s.cells.alarm_badge;
    badge.hidden = !worst;
    badge.textContent = worst
      ? `${active.length} alarm${active.length === 1 ? "" : "s"} · ${worst}` : "";
    badge.className = "badge alarm" + (worst ? " sev-" + worst : "");
    const shown = own.filter((a) => a.active || !a.acked);
    // Rebuilt only when they changed: a button replaced under the pointer loses its click.
    const signature = JSON.stringify(shown);
    if (signature === s.alarmsShown) return;
    s.alarmsShown = signature;
    const list = s.card.querySelector("ul.alarms");
    list.replaceChildren(...shown.map((a) => alarmLine(s, a)));
    list.hidden = shown.length === 0;
  }

  function alarmLine(s, a) {
    const li = document.createElement("li");
    li.dataset.alarm = a.alarm;
    li.dataset.state = a.state;
    li.className = "sev-" + a.severity;
    const name = document.createElement("b");
    name.textContent = a.alarm;
    const since = a.since ? ` · since ${clock(a.since)}` : "";
    const value = valueText(a.field, a.value, a.limit);
    li.append(name, ` ${a.severity} · ${STATE_WORDS[a.state] || a.state}` +
      (value ? ` · ${value}` : "") + since);
    if (!a.acked && auth.may("operator")) {
      const button = document.createElement("button");
      button.type = "button";
      button.className = "ack";
      button.textContent = "acknowledge";
      button.setAttribute("aria-label", `acknowledge ${a.alarm} of ${s.name}`);
      button.addEventListener("click", () => acknowledge(s, a.alarm, button));
      li.append(" ", button);
    }
    return li;
  }

  /** POST .../ack with the credential; the refusal, if any, is shown as the gateway gave it,
   *  with what to do. */
  async function acknowledge(s, alarm, button) {
    const out = s.cells.alarm_result;
    button.disabled = true;
    out.textContent = `${alarm}: acknowledging…`;
    try {
      const path = `${API}/alarms/${encodeURIComponent(s.name)}/${encodeURIComponent(alarm)}/ack`;
      const response = await fetch(path + "?by=dashboard",
        { method: "POST", headers, cache: "no-store" });
      let body = {};
      try { body = await response.json(); } catch (e) { /* not JSON */ }
      if (response.ok) {
        onAlarmState(body);
        out.textContent = `${alarm}: acknowledged`;
      } else {
        out.textContent = `${alarm}: refused: ${refusal(response, body, "acknowledging")}`;
      }
      out.dataset.ok = String(response.ok);
    } catch (error) {
      out.textContent = `${alarm}: ${error.message}`;
      out.dataset.ok = "false";
    } finally {
      button.disabled = false;
    }
  }

  /** Why the gateway refused an operator's action ("acknowledging", "taking a
   *  capture"), in words, with what to do. */
  function refusal(response, body, action) {
    if (response.status === 401) {
      return token ? "unauthorised: the session ended: log in again"
        : `unauthorised: ${action} needs an operator: log in`;
    }
    return `${body.kind || response.status}: ${body.error || response.statusText}`;
  }

  /** The journal, newest first. */
  function showJournal() {
    const list = $("journal");
    const newest = journal.length ? JSON.stringify(journal[journal.length - 1]) : "";
    const shown = journal.length + newest;
    if (shown === journalShown) return; // unchanged
    journalShown = shown;
    $("journal-empty").hidden = journal.length > 0;
    const rows = journal.slice(-JOURNAL_SHOWN).reverse().map((t) => {
      const li = document.createElement("li");
      li.className = "sev-" + t.severity;
      li.dataset.alarm = alarmKey(t.sensor, t.alarm);
      li.dataset.from = t.from;
      li.dataset.to = t.to;
      const time = document.createElement("time");
      time.dateTime = t.ts;
      time.textContent = clock(t.ts);
      const name = document.createElement("b");
      name.textContent = `${t.sensor} / ${t.alarm}`;
      const a = alarms.get(alarmKey(t.sensor, t.alarm));
      const value = valueText(a ? a.field : null, t.value, t.limit);
      li.append(time, " ", name, ` ${t.severity} · ${STATE_WORDS[t.from] || t.from} → ` +
        `${STATE_WORDS[t.to] || t.to}` + (value ? ` · ${value}` : "") +
        (t.by ? ` · by ${t.by}` : ""));
      return li;
    });
    list.replaceChildren(...rows);
  }

  /** The transitions of sensor ``s`` to mark on the chart of ``group`` (an alarm on one
   *  of its fields; the communication alarm, with no field, on every chart) since
   *  ``from`` (epoch seconds). */
  function marksFor(s, group, from) {
    return journal.filter((t) => {
      if (t.sensor !== s.name || epoch(t.ts) / 1000 < from) return false;
      const a = alarms.get(alarmKey(t.sensor, t.alarm));
      return !a || !a.field || group.members.some(([, f]) => f === a.field);
    });
  }

  const SEVERITY_COLOURS = { critical: "#f85149", warning: "#d29922", info: "#58a6ff" };

  /** A vertical line at each transition: solid into an active state, dashed out of it. */
  function drawMarks(ctx, marks, x, h) {
    ctx.save();
    ctx.lineWidth = 1.5;
    for (const t of marks) {
      const at = x(epoch(t.ts) / 1000);
      ctx.strokeStyle = SEVERITY_COLOURS[t.severity] || "#888";
      ctx.setLineDash(t.to.startsWith("active") ? [] : [3, 3]);
      ctx.beginPath();
      ctx.moveTo(at, 0);
      ctx.lineTo(at, h);
      ctx.stroke();
    }
    ctx.restore();
  }

  // ------------------------------------------------------------------ captures

  // The captures the gateway keeps (GET /api/v1/captures, newest first), polled with the
  // status: a capture is written post_s after its trigger, and listed from then on, so
  // the page shows it at most one poll (2 s) later.  Whether capture is on comes from
  // GET /api/v1/health, not from asking the list: without a capture: section the list
  // answers 404, which a browser logs as an error on every poll.
  let capturesOn = null; // null: not known yet
  let capturesShown = null; // what the list shows (skip redrawing the same)
  let captureAwaited = null; // the capture the button took, until it is listed

  /** On or off (health's "capture"): the list and the button, or the note that the
   *  gateway's config has no capture: section. */
  function showCaptureMode(on) {
    capturesOn = on;
    const section = $("captures-section");
    section.dataset.capture = on ? "on" : "off";
    section.hidden = false;
    $("captures-off").hidden = on;
    $("captures-on").hidden = !on;
    if (on) loadCaptures();
  }

  async function loadCaptures() {
    if (!capturesOn) return;
    try {
      showCaptures(await api("/captures"));
    } catch (error) {
      // 404: capture is off after all (a gateway restarted without it); anything else
      // (the connection, a refused token) the banner tells, and the next poll retries.
      if (error.status === 404) showCaptureMode(false);
    }
  }

  function showCaptures(list) {
    const signature = JSON.stringify(list);
    if (signature !== capturesShown) { // rebuilt only when changed: a link keeps its click
      capturesShown = signature;
      $("captures-empty").hidden = list.length > 0;
      $("captures").replaceChildren(...list.map(captureLine));
    }
    if (captureAwaited && list.some((c) => c.id === captureAwaited)) {
      showCaptureResult(`capture ${captureAwaited}: written, in the list below`, true,
        captureAwaited);
      captureAwaited = null;
    }
  }

  /** "2026-11-22 04:40:00 · alarm boom/boom_lean · 412 KiB · download". */
  function captureLine(c) {
    const li = document.createElement("li");
    li.dataset.capture = c.id;
    li.dataset.trigger = c.trigger;
    li.dataset.alarm = c.alarm || "";
    li.dataset.time = c.time;
    li.dataset.size = String(c.size);
    const time = document.createElement("time");
    time.dateTime = c.time;
    time.textContent = new Date(c.time).toLocaleString();
    const trigger = document.createElement("b");
    trigger.textContent = c.alarm ? `${c.trigger} ${c.alarm}` : c.trigger;
    const link = document.createElement("a");
    link.className = "download";
    link.href = `${API}/captures/${encodeURIComponent(c.id)}`;
    link.download = `imu-gateway-capture-${c.id}.zip`;
    link.textContent = "download";
    link.setAttribute("aria-label", `download the capture of ${time.textContent}`);
    // With a credential the link fetches with it (a plain link cannot send a header,
    // and a gateway may need one to read).
    if (token) link.addEventListener("click", (e) => { e.preventDefault(); download(link); });
    li.append(time, " ", trigger, ` · ${bytes(c.size)} · `, link);
    return li;
  }

  function bytes(n) {
    if (n < 1024) return `${n} B`;
    if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KiB`;
    return `${(n / 1024 / 1024).toFixed(1)} MiB`;
  }

  /** The ZIP with the credential, saved under the link's file name.  A capture can be
   *  megabytes: the link says "downloading…" until the browser has it (on the link, so
   *  that the captures' result keeps what the button said); a download that has not
   *  come within DOWNLOAD_MS is given up, and says so. */
  async function download(link) {
    if (link.getAttribute("aria-busy") === "true") return; // (one at a time per link)
    const label = link.textContent;
    link.setAttribute("aria-busy", "true");
    link.textContent = "downloading…";
    try {
      const response = await fetch(link.href, {
        headers, cache: "no-store", signal: AbortSignal.timeout(DOWNLOAD_MS),
      });
      if (!response.ok) throw new HttpError(response.status, response.statusText);
      const url = URL.createObjectURL(await response.blob());
      const save = document.createElement("a");
      save.href = url;
      save.download = link.download;
      save.click();
      setTimeout(() => URL.revokeObjectURL(url), 60000);
    } catch (error) {
      showCaptureResult(`download: ${error.status || ""} ${error.message}`.trim(), false);
    } finally {
      link.removeAttribute("aria-busy");
      link.textContent = label;
    }
  }

  function showCaptureResult(text, ok, id) {
    const out = $("capture-result");
    out.textContent = text;
    out.dataset.ok = String(ok);
    out.dataset.capture = id || "";
  }

  /** POST /api/v1/captures (an operator's, with http.allow_commands): pre_s
   *  before now to post_s after; the list is fetched again when it is written. */
  async function takeCapture(button) {
    button.disabled = true;
    showCaptureResult("taking a capture…", true);
    try {
      const response = await fetch(API + "/captures", { method: "POST", headers, cache: "no-store" });
      let body = {};
      try { body = await response.json(); } catch (e) { /* not JSON */ }
      if (response.ok) {
        captureAwaited = body.id;
        showCaptureResult(`capture ${body.id}: recording, written in ` +
          `${body.ready_in_s.toFixed(1)} s`, true, body.id);
        setTimeout(loadCaptures, body.ready_in_s * 1000 + 250);
      } else {
        showCaptureResult(`refused: ${refusal(response, body, "taking a capture")}`, false);
      }
    } catch (error) {
      showCaptureResult(error.message, false);
    } finally {
      button.disabled = false;
    }
  }

  /** The gateway's id and version in the header, and whether capture is on: at the
   *  start and whenever the stream opens (a gateway restarted may have a new config). */
  async function loadHealth() {
    const health = await api("/health");
    $("mode").textContent = `${health.gateway_id} · v${health.version} · live`;
    if (health.capture !== capturesOn) showCaptureMode(Boolean(health.capture));
  }

  // ------------------------------------------------------------------ live data

  function openStream() {
    const stream = auth.eventSource(API + "/stream");
    stream.addEventListener("open", () => {
      setDown("stream", false);
      loadAlarms().catch(() => { /* the poll brings the states */ });
      loadHealth().catch(() => { /* shown by the banner */ });
    });
    stream.addEventListener("alarm", (e) => onAlarmEvent(JSON.parse(e.data)));
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
        const [list, buses, states] = await Promise.all([api("/sensors"), api("/buses"),
          api("/alarms")]);
        for (const info of list) onSensorInfo(info);
        showBuses(buses);
        onAlarmPoll(states);
        setDown("api", false);
        loadCaptures();
      } catch (error) {
        setDown("api", true, error);
      }
      await sleep(POLL_MS);
    }
  }

  async function start() {
    await auth.ready; // (the login form, if reads need one)
    $("mode").textContent = "live";
    $("capture-take").hidden = !auth.may("operator");
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
      loadTrend(s);
    }
    if (auth.may("operator")) {
      commandsWithoutArguments().then((names) => {
        for (const s of sensors.values()) showCommands(s, names);
      }, () => { /* no buttons: the API answers commands all the same */ });
    }
    loadHealth().catch(() => { /* shown by the banner */ });
    $("capture-take").addEventListener("click", (e) => takeCapture(e.currentTarget));
    pollStatus();
    openStream();
    // The age keeps growing between readings.
    setInterval(() => {
      const now = performance.now();
      for (const s of sensors.values()) showAge(s, now);
    }, 250);
    // The trends move once a second (their buckets are seconds).
    setInterval(() => { for (const s of sensors.values()) drawTrends(s); }, 1000);
    // The canvases follow the layout (rotation of a phone, a resized window).
    window.addEventListener("resize", () => { for (const s of sensors.values()) markDirty(s); });
  }

  start();
})();
