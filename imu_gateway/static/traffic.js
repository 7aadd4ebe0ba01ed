/* imu-gateway: the traffic monitor and the scan (traffic.html, docs/dashboard.md).
 *
 * Traffic: GET /api/v1/buses/{bus}/traffic as Server-Sent Events, filtered by the
 * gateway (?sensor=, ?errors=true) so its 50 frames a second go to what is asked.
 * Pause keeps the stream and counts what it did not show.
 * Scan: static/scan.js's form; each sensor found gets an "Add" button that fills a
 * YAML snippet (imuScan.sensor_config).
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
  // (static/scan.js) Add fills a YAML snippet to paste into the config; the Setup
  // page's Add puts the sensor into its form instead.
  window.imuScan.mount($("scan"), (found, port) => {
    $("scan-snippet").value = window.imuScan.sensor_config(found, port).yaml;
    $("scan-snippet-label").hidden = false;
  });
})();
