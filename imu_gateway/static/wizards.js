/* The calibration and setup wizards (docs/wizards.md): each is a REST procedure,
 * POST /api/v1/sensors/{name}/procedures/{procedure}, followed over its own
 * Server-Sent Events until it ends.  No framework, no build step, nothing from a CDN.
 *
 * Test hooks: <body data-state> is the procedure's state (running, done, failed,
 * cancelled), data-step its step; #coverage the circle's coverage in percent;
 * #change-checks the address and baud change's checks, each <li data-ok>.
 *
 * The credential: the dashboard's login (static/auth.js, sent as "Authorization:
 * Bearer"; never in a URL): log in on the dashboard, then open this page from it.
 */
"use strict";

(() => {
  const API = "/api/v1";
  const auth = window.imuAuth;
  const $ = (id) => document.getElementById(id);
  let current = null; // {sensor, path, source, state}
  let ticking = null; // the local countdown's timer
  let sensors = []; // GET /api/v1/sensors: each one's bus, protocol and live address
  let rates = {}; // each bus's baud rate (GET /api/v1/buses)

  async function call(method, path, body) {
    const init = { method, headers: auth.headers(), cache: "no-store" };
    if (body !== undefined) {
      init.headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    const response = await fetch(path, init);
    let data = null;
    try { data = await response.json(); } catch (e) { /* no body */ }
    if (!response.ok) {
      const why = (data && data.error) || response.statusText;
      const error = new Error(response.status === 401 && !auth.credential()
        ? `${why}: log in on the dashboard first, then open this page from it` : why);
      error.status = response.status;
      throw error;
    }
    return { data, response };
  }

  function say(text, ok) {
    const out = $("result");
    out.textContent = text;
    out.dataset.ok = ok ? "1" : "";
  }

  // ------------------------------------------------------------------ choosing

  async function loadSensors() {
    try {
      const { data } = await call("GET", `${API}/sensors`);
      sensors = data;
      try {
        rates = Object.fromEntries((await call("GET", `${API}/buses`)).data
          .map((b) => [b.name, b.baudrate]));
      } catch (e) { rates = {}; }
      const select = $("sensor");
      for (const s of data) {
        const option = document.createElement("option");
        option.value = s.name;
        option.textContent = `${s.name} (${s.series}, ${s.protocol})`;
        option.dataset.series = s.series;
        select.append(option);
      }
      if (data.length) await chooseSensor();
      else $("choices-note").textContent = "This gateway has no sensors.";
    } catch (e) {
      $("banner").textContent = `cannot list the sensors: ${e.message}`;
      $("banner").hidden = false;
    }
  }

  async function chooseSensor() {
    const select = $("sensor");
    const name = select.value;
    const series = select.selectedOptions[0].dataset.series;
    $("heading-label").hidden = series !== "MINS";
    const { data } = await call("GET", `${API}/sensors/${encodeURIComponent(name)}/procedures`);
    for (const button of document.querySelectorAll("[data-procedure]")) {
      button.disabled = !data.available.includes(button.dataset.procedure);
      button.dataset.unavailable = button.disabled ? "1" : "";
    }
    $("choices-note").textContent = data.available.includes("mag_calibration") ? ""
      : "Magnetic calibration is for an AH sensor on the native protocol.";
    checkChange();
    const running = data.runs.find((r) => r.state === "running");
    if (running) follow(name, `${API}/sensors/${encodeURIComponent(name)}/procedures/` +
                        `${running.procedure}/${running.id}`, running);
  }

  function argumentsOf(procedure) {
    if (procedure === "change_address") return { address: Number($("new-address").value) };
    if (procedure === "change_baudrate") return { baudrate: Number($("new-baud").value) };
    if (procedure !== "zero") return {};
    const args = { type: $("zero-type").value };
    const heading = $("zero-heading").value;
    if (!$("heading-label").hidden && heading !== "") args.relative_heading = Number(heading);
    return args;
  }

  async function start(procedure) {
    const sensor = $("sensor").value;
    say("", true);
    try {
      const { data, response } = await call(
        "POST", `${API}/sensors/${encodeURIComponent(sensor)}/procedures/${procedure}`,
        argumentsOf(procedure));
      follow(sensor, response.headers.get("Location"), data);
    } catch (e) {
      say(`refused: ${e.message}`, false);
    }
  }

  // The address and baud change's checks, as the gateway makes them again when it is
  // started (docs/wizards.md): shown before, so nobody has to be refused to learn them.
  function checkChange() {
    const me = sensors.find((s) => s.name === $("sensor").value);
    const list = $("change-checks");
    list.replaceChildren();
    if (!me) return;
    const others = sensors.filter((s) => s.bus === me.bus && s.name !== me.name);
    const [low, high] = me.protocol === "modbus" ? [1, 247] : [0, 255];
    const raw = $("new-address").value;
    const address = Number(raw);
    const taken = others.filter((s) => s.address === address).map((s) => s.name);
    let addressOk = raw !== "" && Number.isInteger(address) && address >= low &&
      address <= high && address !== me.address && taken.length === 0;
    const addressSays = raw === "" ? `${me.name} is at address ${me.address}: give the new one`
      : !Number.isInteger(address) || address < low || address > high
        ? `a ${me.protocol} address is ${low}-${high}`
        : address === me.address ? `${me.name} is at address ${address} already`
          : taken.length ? `address ${address} is taken on bus ${me.bus} by ${taken.join(", ")}`
            : `address ${address} is free on bus ${me.bus}`;
    const baud = Number($("new-baud").value);
    const rate = rates[me.bus];
    const baudOk = others.length === 0 && baud !== rate;
    const baudSays = others.length
      ? `bus ${me.bus} has other sensors (${others.map((s) => s.name).join(", ")}): the ` +
        "baud rate wizard changes a bus of one sensor only"
      : baud === rate ? `bus ${me.bus} runs at ${baud} baud already`
        : `bus ${me.bus} has ${me.name} alone: ${rate || "?"} → ${baud} baud`;
    for (const [ok, text, what] of [[addressOk, addressSays, "address"],
                                    [baudOk, baudSays, "baud"]]) {
      const li = document.createElement("li");
      li.textContent = text;
      li.dataset.ok = ok ? "1" : "";
      li.dataset.check = what;
      list.append(li);
    }
    const button = (name) => document.querySelector(`[data-procedure="${name}"]`);
    addressOk = addressOk && !button("change_address").dataset.unavailable;
    button("change_address").disabled = !addressOk;
    button("change_baudrate").disabled = !baudOk || !!button("change_baudrate").dataset.unavailable;
  }

  // ------------------------------------------------------------------ following

  function follow(sensor, path, state) {
    if (current && current.source) current.source.close();
    current = { sensor, path, source: null, state };
    render(state);
    const source = auth.eventSource(`${path}/events`);
    current.source = source;
    const take = (event) => render(JSON.parse(event.data));
    source.addEventListener("progress", take);
    source.addEventListener("end", (event) => { take(event); source.close(); });
    source.addEventListener("error", () => {
      // A stream that ends is reconnected by the browser; one that cannot be had is
      // asked once more by GET, so the page still shows the end.
      if (source.readyState === 2) refresh(); // CLOSED
    });
  }

  async function refreshSensors() {
    // the address or rate the wizard changed, for the next checks
    try {
      sensors = (await call("GET", `${API}/sensors`)).data;
      rates = Object.fromEntries((await call("GET", `${API}/buses`)).data
        .map((b) => [b.name, b.baudrate]));
    } catch (e) { /* the checks keep what they had */ }
    checkChange();
  }

  async function refresh() {
    if (!current) return;
    try { render((await call("GET", current.path)).data); } catch (e) { say(e.message, false); }
  }

  function render(state) {
    if (current) current.state = state;
    $("run").hidden = false;
    document.body.dataset.state = state.state;
    document.body.dataset.step = state.step || "";
    $("run-title").textContent = `${state.procedure.replace("_", " ")} on ${state.sensor}`;
    $("prompt").textContent = state.error && state.state === "failed"
      ? `failed: ${state.error}` : state.prompt;
    renderSteps(state);
    renderCountdown(state.countdown_s);
    renderCircle(state);
    renderAngles(state.angles || {});
    $("answers").textContent = Object.entries(state.answers || {})
      .map(([k, v]) => `${k}: ${JSON.stringify(v)}`).join("\n");
    $("cancel").hidden = state.state !== "running";
    const config = (state.answers || {}).config;
    if (config && state.state === "done") {
      say(`the config follows: ${config.note}`, config.saved);
      refreshSensors();
    }
    $("save").hidden = !(state.state === "done" && (state.offers || []).includes("save"));
  }

  function renderSteps(state) {
    const list = $("steps");
    list.replaceChildren();
    const at = state.steps.indexOf(state.step);
    state.steps.forEach((step, i) => {
      if (step === null) return;
      const li = document.createElement("li");
      li.textContent = step.replaceAll("_", " ");
      const past = state.state === "done" || (at >= 0 && i < at);
      li.classList.toggle("is-past", past);
      li.classList.toggle("is-current", i === at && state.state === "running");
      list.append(li);
    });
  }

  function renderCountdown(seconds) {
    clearInterval(ticking);
    const el = $("countdown");
    el.hidden = seconds === null || seconds === undefined;
    if (el.hidden) return;
    const ends = performance.now() + seconds * 1000;
    const show = () => {
      el.textContent = Math.max(0, (ends - performance.now()) / 1000).toFixed(1) + " s";
    };
    show();
    ticking = setInterval(show, 100);
  }

  function renderCircle(state) {
    const circle = state.coverage_percent !== null && state.coverage_percent !== undefined;
    $("circle").hidden = !circle;
    if (!circle) return;
    $("coverage").textContent = String(state.coverage_percent);
    $("finish").hidden = state.step !== "circle";
    const q = state.quality;
    $("quality").textContent = q ? `centre offset ${q.centre_offset_percent} % of the radius, ` +
      `ellipse ratio ${q.ellipse_ratio}` : "quality: once the circle is whole";
    plot(state.points || []);
  }

  function plot(points) {
    const canvas = $("plot");
    const g = canvas.getContext("2d");
    const w = canvas.width, h = canvas.height;
    g.clearRect(0, 0, w, h);
    g.strokeStyle = "#2a3441";
    g.beginPath(); g.moveTo(w / 2, 0); g.lineTo(w / 2, h); g.moveTo(0, h / 2); g.lineTo(w, h / 2);
    g.stroke();
    const reach = Math.max(1e-6, ...points.map(([x, y]) => Math.max(Math.abs(x), Math.abs(y))));
    const scale = (w / 2 - 10) / reach;
    g.fillStyle = "#ffd21f";
    for (const [x, y] of points) {
      g.fillRect(w / 2 + x * scale - 2, h / 2 - y * scale - 2, 4, 4);
    }
    canvas.dataset.points = String(points.length);
  }

  function renderAngles(angles) {
    const table = $("angles");
    const rows = ["before", "after"].filter((k) => angles[k]);
    table.hidden = rows.length === 0;
    table.tBodies[0].replaceChildren(...rows.map((k) => {
      const tr = document.createElement("tr");
      tr.dataset.when = k;
      for (const text of [k, ...["pitch", "roll", "yaw"].map((f) => angles[k][f].toFixed(2))]) {
        const td = document.createElement("td");
        td.textContent = text;
        tr.append(td);
      }
      return tr;
    }));
  }

  // ------------------------------------------------------------------ the buttons

  async function act(method, suffix, what) {
    if (!current) return;
    try {
      render((await call(method, current.path + suffix)).data);
    } catch (e) {
      say(`${what} refused: ${e.message}`, false);
    }
  }

  async function save() {
    try {
      const { data } = await call(
        "POST", `${API}/sensors/${encodeURIComponent(current.sensor)}/commands/save`);
      say(data.ok ? "saved: the sensor is busy for a few seconds" : data.error, data.ok);
    } catch (e) {
      say(`save refused: ${e.message}`, false);
    }
  }

  for (const button of document.querySelectorAll("[data-procedure]")) {
    button.addEventListener("click", () => start(button.dataset.procedure));
  }
  $("sensor").addEventListener("change", chooseSensor);
  $("new-address").addEventListener("input", checkChange);
  $("new-baud").addEventListener("change", checkChange);
  $("cancel").addEventListener("click", () => act("DELETE", "", "cancel"));
  $("finish").addEventListener("click", () => act("POST", "/finish", "finish"));
  $("save").addEventListener("click", save);
  $("back").href = "./" + location.search;
  loadSensors();
})();
