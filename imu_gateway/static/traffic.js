/* imu-gateway: the traffic monitor and the scan (traffic.html, docs/dashboard.md).
 *
 * Traffic: GET /api/v1/buses/{bus}/traffic as Server-Sent Events, filtered by the
 * gateway (?sensor=, ?errors=true) so its 50 frames a second go to what is asked.
 * Pause keeps the stream and counts what it did not show.
 * Scan: POST /api/v1/scan, an admin's (the dashboard's login: static/auth.js sends
 * it as a header, never in a URL); a port one of the gateway's buses uses is refused first, with the
 * reason, and a button confirms.  Each sensor found gets an "Add" button that fills a
 * YAML snippet (sensor_config).
 */
"use strict";

(function () {
  const MAX_ROWS = 500;
  const auth = window.imuAuth;
  const headers = auth.headers();
  const $ = (id) => document.getElementById(id);

  // ---------------------------------------------------------------- traffic
  let source = null;
  let paused = false;
  let unseen = 0;
  let buses = [];

  function cell(row, text) {
    const td = document.createElement("td");
    td.textContent = text;
    row.appendChild(td);
  }

  function addRow(values, className) {
    const body = $("frames");
    const scroll = $("traffic-scroll");
    const atEnd = scroll.scrollTop + scroll.clientHeight >= scroll.scrollHeight - 4;
    const row = document.createElement("tr");
    if (className) row.className = className;
    values.forEach((v) => cell(row, v));
    body.appendChild(row);
    while (body.rows.length > MAX_ROWS) body.deleteRow(0);
    if (atEnd) scroll.scrollTop = scroll.scrollHeight;  // follows unless scrolled up
  }

  /** A long frame as the log shows it: its first 10 bytes, "…", its last 2. */
  function shortHex(hex) {
    const bytes = hex.split(" ");
    return bytes.length <= 12 ? hex : `${bytes.slice(0, 10).join(" ")} … ${bytes.slice(-2).join(" ")}`;
  }

  function showFrame(f) {
    addRow([f.time.slice(11, 23), f.sensor, shortHex(f.tx), f.rx ? shortHex(f.rx) : "(nothing)",
            String(f.took_ms), f.outcome, f.placed], f.error ? "error" : "");
    const row = $("frames").lastElementChild;
    row.cells[2].title = f.tx;  // the whole frames, on hover
    row.cells[3].title = f.rx;
  }

  function connect() {
    if (source) source.close();
    const bus = $("bus").value;
    if (!bus) return;
    const query = [];
    if ($("sensor").value) query.push("sensor=" + encodeURIComponent($("sensor").value));
    if ($("errors").checked) query.push("errors=true");
    source = auth.eventSource(`api/v1/buses/${encodeURIComponent(bus)}/traffic` +
                              (query.length ? "?" + query.join("&") : ""));
    // (addEventListener: a stream read with fetch, static/auth.js, has no on… handlers)
    source.addEventListener("open", () => {
      $("traffic-state").textContent = paused ? "paused" : "live";
    });
    source.addEventListener("error", () => {
      $("traffic-state").textContent = "disconnected: retrying";
    });
    source.addEventListener("frame", (e) => {
      if (paused) { unseen += 1; $("traffic-state").textContent = `paused (${unseen} not shown)`; return; }
      showFrame(JSON.parse(e.data));
    });
    source.addEventListener("skipped", (e) => {
      const d = JSON.parse(e.data);
      if (!paused) addRow(["", "", `${d.skipped} frames not sent (over ${d.limit_per_s} a second)`,
                           "", "", "", ""], "skipped");
    });
  }

  function fillSensors() {
    const select = $("sensor");
    const bus = buses.find((b) => b.name === $("bus").value);
    select.length = 1;
    for (const name of bus ? bus.sensors : []) select.add(new Option(name, name));
  }

  $("bus").addEventListener("change", () => { fillSensors(); connect(); });
  $("sensor").addEventListener("change", connect);
  $("errors").addEventListener("change", connect);
  $("clear").addEventListener("click", () => { $("frames").textContent = ""; });
  $("pause").addEventListener("click", () => {
    paused = !paused;
    $("pause").textContent = paused ? "Resume" : "Pause";
    if (!paused && unseen) {
      addRow(["", "", `${unseen} frames came while paused`, "", "", "", ""], "skipped");
    }
    unseen = 0;
    $("traffic-state").textContent = paused ? "paused" : "live";
  });

  fetch("api/v1/buses", { headers }).then((r) => r.ok ? r.json() : Promise.reject(r.status))
    .then((list) => {
      buses = list;
      for (const b of list) $("bus").add(new Option(`${b.name} (${b.port})`, b.name));
      const wanted = new URLSearchParams(location.search).get("bus");
      if (wanted) $("bus").value = wanted;
      fillSensors();
      connect();
    })
    .catch((status) => { $("traffic-state").textContent = `cannot list the buses (${status})`; });

  // ---------------------------------------------------------------- scan
  let scan = null;  // {id, events: EventSource}

  /** What the config needs for a sensor found: its bus and the sensor itself, and the
   *  YAML to paste (the Setup form takes the same object). */
  function sensor_config(found, port) {
    const series = found.series.split(" ")[0];  // "VG or MINS": VG, the closer reading
    const name = `${series.toLowerCase()}${found.address}`;
    const bus = { port: port, baudrate: found.baudrate, protocol: found.protocol };
    const sensor = { name: name, series: series, address: found.address };
    const yaml = ["buses:", `  - name: line-${name}`, `    port: ${port}`,
                  `    baudrate: ${found.baudrate}`, `    protocol: ${found.protocol}`,
                  "    sensors:", `      - name: ${name}`, `        series: ${series}`,
                  `        address: ${found.address}`].join("\n") + "\n";
    return { bus: bus, sensor: sensor, yaml: yaml };
  }
  window.imuScan = { sensor_config: sensor_config };

  function scanBody(confirm) {
    const protocols = [];
    if ($("scan-native").checked) protocols.push("native");
    if ($("scan-modbus").checked) protocols.push("modbus");
    return { port: $("scan-port").value.trim(), protocols: protocols,
             bauds: $("scan-bauds").value.trim().split(/[\s,]+/).map(Number),
             first_address: Number($("scan-first").value),
             last_address: Number($("scan-last").value), confirm: confirm };
  }

  function said(text) { $("scan-state").textContent = text; }

  function showFound(found, port) {
    const li = document.createElement("li");
    li.textContent = `${found.protocol} ${found.baudrate} baud, address ${found.address}, ` +
                     `series ${found.series} `;
    const add = document.createElement("button");
    add.type = "button";
    add.textContent = "Add";
    add.addEventListener("click", () => {
      $("scan-snippet").value = sensor_config(found, port).yaml;
      $("scan-snippet-label").hidden = false;
    });
    li.appendChild(add);
    $("scan-found").appendChild(li);
  }

  async function startScan(confirm) {
    $("scan-confirm").hidden = true;
    const body = scanBody(confirm);
    let r;
    try {
      r = await fetch("api/v1/scan", { method: "POST", body: JSON.stringify(body),
        headers: { ...headers, "Content-Type": "application/json" } });
    } catch (e) { said("the gateway cannot be reached"); return; }
    const answer = await r.json();
    if (r.status === 409 && answer.error.includes("\"confirm\": true")) {
      said(answer.error);
      $("scan-confirm").hidden = false;
      return;
    }
    if (r.status === 401 || r.status === 403) {
      said(`refused: ${answer.error}: scanning is an admin's (log in on the dashboard)`);
      return;
    }
    if (!r.ok) { said(answer.error || `refused (${r.status})`); return; }
    $("scan-found").textContent = "";
    said(`scanning: about ${Math.ceil(answer.estimate_s)} s if nothing answers` +
         (answer.paused_bus ? `; bus ${answer.paused_bus} is paused` : ""));
    const events = auth.eventSource(answer.events);
    scan = { id: answer.id, events: events };
    $("scan-cancel").hidden = false;
    $("scan-start").disabled = true;
    const end = (text) => {
      events.close();
      scan = null;
      $("scan-cancel").hidden = true;
      $("scan-start").disabled = false;
      said(text);
    };
    events.addEventListener("progress", (e) => said(JSON.parse(e.data).text));
    events.addEventListener("found", (e) => showFound(JSON.parse(e.data), body.port));
    events.addEventListener("done", () => end(`done: ${$("scan-found").children.length} found` +
      (answer.paused_bus ? `; bus ${answer.paused_bus} resumed` : "")));
    events.addEventListener("failed", (e) => end("failed: " + JSON.parse(e.data).error));
    events.addEventListener("cancelled", () => end("cancelled"));
  }

  $("scan-form").addEventListener("submit", (e) => { e.preventDefault(); startScan(false); });
  $("scan-confirm").addEventListener("click", () => startScan(true));
  $("scan-cancel").addEventListener("click", () => {
    if (scan) fetch(`api/v1/scan/${scan.id}/cancel`, { method: "POST", headers });
  });
})();
