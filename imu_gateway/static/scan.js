/* imu-gateway: the scan of a port (docs/dashboard.md, "Scan"), on the Setup page and
 * the traffic page alike: imuScan.mount(container, add) builds its form there.
 *
 * POST /api/v1/scan is an admin's (the dashboard's login: static/auth.js sends it as
 * a header, never in a URL).  A port one of the gateway's buses uses is refused first,
 * with the reason (that bus's polling pauses, for how long), and a button confirms:
 * nothing stops before it is pressed.  Progress and finds come over SSE.  Each sensor
 * found gets an "Add" button that calls add(found, port, button); sensor_config(found,
 * port) is what the config needs for it.
 *
 * Test hooks: the ids scan-port, scan-native, scan-modbus, scan-bauds, scan-first,
 * scan-last, scan-start, scan-confirm, scan-cancel, scan-state, scan-found.
 */
"use strict";

(function () {
  const auth = window.imuAuth;
  const BAUDS = "9600 115200 460800 19200 38400 57600 4800 2400";

  /** What the config needs for a sensor found: its bus and the sensor itself, and the
   *  YAML to paste (the Setup form takes the same objects). */
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

  function element(tag, attributes, ...children) {
    const node = document.createElement(tag);
    for (const [name, value] of Object.entries(attributes || {})) node.setAttribute(name, value);
    node.append(...children);
    return node;
  }

  function form(ports) {
    const list = element("datalist", { id: "scan-ports" });
    for (const port of ports) list.append(element("option", { value: port }));
    return element("form", { class: "scan-form", id: "scan-form" },
      element("label", {}, "Port ", element("input", { id: "scan-port", required: "",
        placeholder: "/dev/ttyUSB0", list: "scan-ports", autocomplete: "off" }), list),
      element("label", {}, element("input", { type: "checkbox", id: "scan-native",
        checked: "" }), " native"),
      element("label", {}, element("input", { type: "checkbox", id: "scan-modbus",
        checked: "" }), " Modbus RTU"),
      element("label", {}, "Baud rates ", element("input", { id: "scan-bauds", value: BAUDS })),
      element("label", {}, "Addresses ", element("input", { id: "scan-first", type: "number",
        min: "0", max: "255", value: "0" }), " to ", element("input", { id: "scan-last",
        type: "number", min: "0", max: "255", value: "255" })),
      element("button", { type: "submit", id: "scan-start" }, "Scan"),
      element("button", { type: "button", id: "scan-confirm", hidden: "" },
        "Pause the bus and scan"),
      element("button", { type: "button", id: "scan-cancel", hidden: "" }, "Cancel"));
  }

  /** The scan's form, state line and list of finds, in ``container``; ``ports``: the
   *  gateway's own ports, offered in the port field. */
  function mount(container, add, ports) {
    const headers = auth.headers();
    container.append(form(ports || []),
      element("output", { class: "scan-state", id: "scan-state" }),
      element("ol", { class: "scan-found", id: "scan-found" }));
    const $ = (id) => document.getElementById(id);
    let scan = null;  // {id, events}

    function body(confirm) {
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
      const li = element("li", { "data-address": String(found.address) },
        `${found.protocol} ${found.baudrate} baud, address ${found.address}, ` +
        `series ${found.series} `);
      const button = element("button", { type: "button", class: "scan-add" }, "Add");
      button.addEventListener("click", () => add(found, port, button));
      li.append(button);
      $("scan-found").append(li);
    }

    async function start(confirm) {
      $("scan-confirm").hidden = true;
      const asked = body(confirm);
      let r;
      try {
        r = await fetch("api/v1/scan", { method: "POST", body: JSON.stringify(asked),
          headers: { ...headers, "Content-Type": "application/json" } });
      } catch (e) { said("the gateway cannot be reached"); return; }
      const answer = await r.json();
      if (r.status === 409 && answer.error.includes("\"confirm\": true")) {
        said(answer.error);  // whose port it is, how long, that its polling pauses
        $("scan-confirm").hidden = false;
        return;
      }
      if (r.status === 401 || r.status === 403) {
        said(`refused: ${answer.error}: scanning is an admin's (log in on the dashboard)`);
        return;
      }
      if (!r.ok) { said(answer.error || `refused (${r.status})`); return; }
      follow(answer, asked.port);
    }

    function follow(answer, port) {
      $("scan-found").textContent = "";
      said(`scanning: about ${Math.ceil(answer.estimate_s)} s if nothing answers` +
           (answer.paused_bus ? `; bus ${answer.paused_bus}'s polling is paused` : ""));
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
      events.addEventListener("found", (e) => showFound(JSON.parse(e.data), port));
      events.addEventListener("done", () => end(`done: ${$("scan-found").children.length} found` +
        (answer.paused_bus ? `; bus ${answer.paused_bus} resumed` : "")));
      events.addEventListener("failed", (e) => end("failed: " + JSON.parse(e.data).error));
      events.addEventListener("cancelled", () => end("cancelled"));
    }

    $("scan-form").addEventListener("submit", (e) => { e.preventDefault(); start(false); });
    $("scan-confirm").addEventListener("click", () => start(true));
    $("scan-cancel").addEventListener("click", () => {
      if (scan) fetch(`api/v1/scan/${scan.id}/cancel`, { method: "POST", headers });
    });
  }

  window.imuScan = { sensor_config: sensor_config, mount: mount };
})();
