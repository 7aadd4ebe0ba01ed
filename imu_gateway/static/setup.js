/* The Setup page (docs/dashboard.md, "Setup"): the gateway's config in the browser.
 *
 * The forms are built from the config's JSON Schema (GET /api/v1/config/schema, made
 * from the same pydantic models as docs/config-reference.md, whose text is each
 * field's help), filled from GET /api/v1/config, and sent back whole with
 * PUT /api/v1/config: first ?dry_run=1 (the problems, or what will change), then for
 * real.  The gateway is the only checker: a problem comes back with its YAML path
 * (buses[0].sensors[1].series: …) and is shown beside that field.  The YAML tab sends
 * its text the same way.  No framework, no build step, nothing from a CDN.
 *
 * The two drafts: the form's (page.config) and the YAML tab's text.  Going to the
 * YAML tab carries the form's changes into the text (the config as YAML, which is
 * what GET ?format=yaml gives too); going back with the text changed cannot carry
 * them (no YAML parser here), so a prompt asks: keep editing the YAML, or discard its
 * changes.  Nothing is lost silently.
 *
 * The scan (static/scan.js): each sensor found has an Add button that puts it into
 * the form's draft, in the bus on that port or in a new bus.
 *
 * The credential: the dashboard's login (static/auth.js, "Authorization: Bearer").
 *
 * Test hooks: <body data-state> (loading, editing, previewed, invalid, applied,
 * refused, failed); every field and list has data-path, its YAML path; a list's add
 * button data-add (its path); an item's remove button .remove; a field's problem
 * .error; the tab prompt #switch-prompt (#keep-yaml, #drop-yaml); a found sensor's
 * Add button .scan-add.
 */
"use strict";

(() => {
  const API = "api/v1";
  const auth = window.imuAuth;
  const $ = (id) => document.getElementById(id);
  const page = { schema: null, config: null, tab: "form", previewed: null,
                 changed: { form: false, yaml: false }, yamlBase: "", scan: false };

  // ------------------------------------------------------------------ the gateway

  async function call(method, path, body, type) {
    const init = { method, headers: { ...auth.headers() }, cache: "no-store" };
    if (body !== undefined) {
      init.headers["Content-Type"] = type;
      init.body = body;
    }
    const response = await fetch(path, init);
    const text = await response.text();
    let data = null;
    try { data = JSON.parse(text); } catch (e) { /* YAML, or no body */ }
    return { status: response.status, ok: response.ok, data, text };
  }

  function refused(answer) {
    const why = (answer.data && answer.data.error) || `HTTP ${answer.status}`;
    if (answer.status !== 401 && answer.status !== 403) return why;
    return `${why}: the Setup page is an admin's; log in as an admin on the dashboard, ` +
      "then open Setup from it";
  }

  async function load() {
    document.body.dataset.state = "loading";
    const [schema, config, yaml] = await Promise.all([
      call("GET", `${API}/config/schema`), call("GET", `${API}/config`),
      call("GET", `${API}/config?format=yaml`)]);
    const failed = [schema, config, yaml].find((a) => !a.ok);
    if (failed) {
      banner(refused(failed));
      document.body.dataset.state = "refused";
      return;
    }
    page.schema = schema.data;
    page.config = config.data.config;
    $("yaml").value = page.yamlBase = yaml.text;
    page.changed = { form: false, yaml: false };
    $("switch-prompt").hidden = true;
    render();
    edited();
    if (!page.scan) {
      page.scan = true;
      window.imuScan.mount($("scan"), addFound, (page.config.buses || []).map((b) => b.port));
    }
  }

  function banner(text) {
    $("banner").textContent = text;
    $("banner").hidden = !text;
  }

  // ------------------------------------------------------------------ the schema

  /** A property's schema with its $ref followed and an "X or null" taken as X. */
  function resolve(node) {
    let out = node;
    if (out.$ref) out = { ...page.schema.$defs[out.$ref.split("/").pop()], ...out, $ref: undefined };
    if (out.anyOf) {
      const kinds = out.anyOf.filter((k) => k.type !== "null");
      if (kinds.length === 1) out = { ...out, ...resolve(kinds[0]), anyOf: undefined };
    }
    return out;
  }

  /** How a property is edited here: a list of forms, a field, or in the YAML tab. */
  function kind(field) {
    if (field.type === "array") {
      const items = field.items ? resolve(field.items) : {};
      return items.properties ? "list" : "yaml";
    }
    if (field.type === "object" || field.properties || field.anyOf) return "yaml";
    if (field.enum) return "choice";
    return { boolean: "bool", integer: "int", number: "number" }[field.type] || "text";
  }

  /** What the field holds when left empty: the reference's wording where it has one. */
  function fallback(field) {
    if (field.shown_default !== undefined) return `default: ${field.shown_default}`;
    if (field.default === undefined || field.default === null) return "";
    return `default: ${String(field.default)}`;
  }

  /** The typed text as the config's value: a number where it reads as one, else the
   *  text itself (the gateway then says what is wrong with it, beside the field). */
  function parsed(how, text) {
    const value = text.trim();
    if (value === "") return undefined;
    if (how === "bool") return value === "true";
    if (how === "int" && /^[+-]?\d+$/.test(value)) return Number(value);
    if (how === "number" && Number.isFinite(Number(value))) return Number(value);
    return how === "text" || how === "choice" ? text : value;
  }

  // ------------------------------------------------------------------ the forms

  function element(tag, attributes, ...children) {
    const node = document.createElement(tag);
    for (const [name, value] of Object.entries(attributes || {})) {
      if (value !== undefined && value !== null) node.setAttribute(name, value);
    }
    node.append(...children);
    return node;
  }

  /** The reference's text, its `code` as code (no HTML is ever parsed). */
  function help(text) {
    const out = element("small", { class: "help" });
    const plain = (text || "").replace(/\[([^\]]+)\]\([^)]*\)/g, "$1"); // [a.md](a.md): a.md
    plain.split("`").forEach((part, i) => out.append(i % 2 ? element("code", {}, part) : part));
    return out;
  }

  function render() {
    const lists = $("buses");
    lists.replaceChildren(list(resolve(page.schema.properties.buses), page.config, "buses", "buses"));
  }

  function object(schema, data, path) {
    const out = document.createDocumentFragment();
    const required = schema.required || [];
    for (const [key, property] of Object.entries(schema.properties)) {
      const field = resolve(property);
      const how = kind(field);
      const here = `${path}.${key}`;
      if (how === "list") out.append(list(field, data, key, here));
      else if (how === "yaml") {
        if (data[key] !== undefined) out.append(element("p", { class: "hint", "data-path": here },
          `${key}: in the YAML tab`, element("span", { class: "error" })));
      } else out.append(input(field, how, data, key, here, required.includes(key)));
    }
    return out;
  }

  function input(field, how, data, key, path, required) {
    const value = data[key];
    let control;
    if (how === "bool" || how === "choice") {
      control = element("select", {}, element("option", { value: "" }, fallback(field) || "—"));
      for (const option of how === "bool" ? [true, false] : field.enum) {
        control.append(element("option", { value: String(option) }, String(option)));
      }
      control.value = value === undefined ? "" : String(value);
    } else {
      control = element("input", { type: "text", placeholder: fallback(field),
        inputmode: how === "text" ? undefined : "decimal", autocomplete: "off" });
      control.value = value === undefined || value === null ? "" : String(value);
    }
    control.addEventListener(how === "bool" || how === "choice" ? "change" : "input", () => {
      const next = parsed(how, control.value);
      if (next === undefined) delete data[key];
      else data[key] = next;
      edited("form");
    });
    return element("label", { class: "field", "data-path": path },
      element("span", { class: "key" }, key + (required ? " *" : "")), control,
      help(field.description), element("span", { class: "error" }));
  }

  function list(field, data, key, path) {
    const items = resolve(field.items);
    const one = key.endsWith("ses") ? key.slice(0, -2) : key.replace(/s$/, "");
    const rows = Array.isArray(data[key]) ? data[key] : [];
    const out = element("fieldset", { class: "list", "data-path": path },
      element("legend", {}, key), help(field.description), element("span", { class: "error" }));
    rows.forEach((row, i) => {
      const remove = element("button", { type: "button", class: "remove" }, `Remove this ${one}`);
      remove.addEventListener("click", () => { rows.splice(i, 1); render(); edited("form"); });
      out.append(element("fieldset", { class: "item", "data-path": `${path}[${i}]` },
        element("legend", {}, `${one} ${row.name || "(new)"}`), remove,
        element("span", { class: "error" }), object(items, row, `${path}[${i}]`)));
    });
    const article = /^[aeiou]/.test(one) ? "an" : "a";
    const add = element("button", { type: "button", class: "add", "data-add": path },
      `Add ${article} ${one}`);
    add.addEventListener("click", () => {
      data[key] = [...rows, {}];
      render();
      edited("form");
      const added = CSS.escape(`${path}[${rows.length}]`);
      const first = document.querySelector(`[data-path="${added}"] input`);
      if (first) first.focus();
    });
    out.append(add);
    return out;
  }

  // ------------------------------------------------------------------ the YAML tab

  /** A plain scalar where YAML reads it back as the same string, else JSON's quoted
   *  form (which YAML reads too): "***", "${VAR}", "9600" stay strings. */
  function scalar(value) {
    if (value === null || value === undefined) return "null";
    if (typeof value !== "string") return String(value);
    const plain = /^[A-Za-z_/][\w./:-]*$/.test(value) &&
      !/^(true|false|null|yes|no|on|off|y|n)$/i.test(value);
    return plain ? value : JSON.stringify(value);
  }

  /** ``value`` as the text after "key:" (the key at ``indent``), in block style as the
   *  gateway writes it: a mapping's keys 2 further in, a list's items at the key's. */
  function block(value, indent) {
    if (Array.isArray(value) && value.length) {
      return "\n" + value.map((item) => `${indent}-${listItem(item, `${indent}  `)}`).join("");
    }
    if (value && typeof value === "object" && Object.keys(value).length) {
      return "\n" + Object.entries(value)
        .map(([k, v]) => `${indent}  ${scalar(k)}:${block(v, `${indent}  `)}`).join("");
    }
    if (Array.isArray(value)) return " []\n";
    return value && typeof value === "object" ? " {}\n" : ` ${scalar(value)}\n`;
  }

  function listItem(item, indent) {
    if (Array.isArray(item)) return ` ${JSON.stringify(item)}\n`;  // (JSON is YAML)
    if (!item || typeof item !== "object" || !Object.keys(item).length) return block(item, indent);
    return Object.entries(item).map(([k, v], i) =>
      `${i ? indent : " "}${scalar(k)}:${block(v, indent)}`).join("");
  }

  /** The config as YAML text, as GET /api/v1/config?format=yaml writes it. */
  function toYaml(config) {
    return Object.entries(config).map(([k, v]) => `${scalar(k)}:${block(v, "")}`).join("");
  }

  // ------------------------------------------------------------------ the scan

  /** A sensor the scan found, into the form's draft: the bus on its port, or a new bus
   *  at the rate and protocol it answered at. */
  function addFound(found, port, button) {
    const made = window.imuScan.sensor_config(found, port);
    const buses = page.config.buses = page.config.buses || [];
    const names = new Set(buses.flatMap((b) => (b.sensors || []).map((s) => s.name)));
    let bus = buses.find((b) => b.port === port);
    const here = bus ? (bus.sensors || []).find((s) => addressOf(s, bus) === found.address) : null;
    if (here) {
      say(`address ${found.address} on ${port} is in the config already: ${here.name}`, true);
      return;
    }
    const sensor = { ...made.sensor, name: unique(made.sensor.name, names) };
    let note = "";
    if (!bus) {
      const taken = new Set(buses.map((b) => b.name));
      bus = { name: unique(`line-${sensor.name}`, taken), ...made.bus, sensors: [] };
      buses.push(bus);
      note = ` (a new bus, ${bus.name}, on ${port})`;
    } else if ((bus.baudrate || 9600) !== found.baudrate || bus.protocol !== found.protocol) {
      note = `; bus ${bus.name} runs ${bus.protocol} at ${bus.baudrate || 9600} baud, the ` +
        `sensor answered ${found.protocol} at ${found.baudrate}: change one of them`;
    }
    bus.sensors = [...(bus.sensors || []), sensor];
    render();
    edited("form");
    button.disabled = true;
    button.textContent = `added as ${sensor.name}`;
    say(`${sensor.name} added to bus ${bus.name}${note}: Preview the change, then Apply`, !note.startsWith(";"));
  }

  /** A sensor's address on its bus, its default where the config has none. */
  function addressOf(sensor, bus) {
    if (sensor.address !== undefined) return sensor.address;
    return bus.protocol === "modbus" ? 1 : 0;
  }

  function unique(name, taken) {
    let out = name;
    for (let n = 2; taken.has(out); n += 1) out = `${name}-${n}`;
    return out;
  }

  // ------------------------------------------------------------------ check, apply

  /** What is sent: the form's config as JSON, or the YAML tab's text. */
  function body() {
    return page.tab === "form"
      ? [JSON.stringify(page.config), "application/json"]
      : [$("yaml").value, "application/yaml"];
  }

  /** Any edit (of the form's or the YAML's draft, ``which``): the preview shown is of
   *  something else now. */
  function edited(which) {
    if (which) page.changed[which] = true;
    page.previewed = null;
    $("apply").disabled = true;
    $("diff").hidden = true;
    document.body.dataset.state = "editing";
  }

  function clearProblems() {
    $("problems").replaceChildren();
    for (const node of document.querySelectorAll(".has-error")) node.classList.remove("has-error");
    for (const node of document.querySelectorAll(".error")) node.textContent = "";
  }

  /** Each problem beside the field of its YAML path (or the nearest part of the form
   *  that has one); those with no place in the form, in the list under the buttons. */
  function showProblems(problems) {
    for (const problem of problems) {
      const match = /^([\w.[\]-]+): ([\s\S]*)$/.exec(problem);
      const place = page.tab === "form" && match ? placeOf(match[1]) : null;
      if (!place) {
        $("problems").append(element("li", {}, problem));
        continue;
      }
      place.classList.add("has-error");
      const error = place.querySelector(":scope > .error");
      const where = place.dataset.path === match[1] ? "" : `${match[1]}: `;
      error.textContent += (error.textContent ? "; " : "") + where + match[2];
    }
  }

  function placeOf(path) {
    for (let at = path; at;) {
      const place = document.querySelector(`[data-path="${CSS.escape(at)}"]`);
      if (place) return place;
      const shorter = at.replace(/(\.[\w-]+|\[\d+\])$/, "");
      if (shorter === at) return null;
      at = shorter;
    }
    return null;
  }

  function say(text, ok) {
    $("result").textContent = text;
    $("result").dataset.ok = ok ? "1" : "";
  }

  async function preview() {
    const [text, type] = body();
    clearProblems();
    say("checking…", true);
    const answer = await call("PUT", `${API}/config?dry_run=1`, text, type);
    if (answer.status === 422 && answer.data && answer.data.problems) {
      showProblems(answer.data.problems);
      say(answer.data.error, false);
      document.body.dataset.state = "invalid";
      return;
    }
    if (!answer.ok) {
      say(refused(answer), false);
      document.body.dataset.state = "failed";
      return;
    }
    showDiff(answer.data.diff);
    page.previewed = [text, type];
    document.body.dataset.state = "previewed";
  }

  function showDiff(diff) {
    const lines = [];
    const moves = (items) => items.map((m) => `${m.sensor} on ${m.bus}`).join(", ");
    const changes = (items) => items.map((c) => `${c.name} (${c.changes.join(", ")})`).join("; ");
    if (diff.sensors.added.length) lines.push(["sensors added", moves(diff.sensors.added)]);
    if (diff.sensors.removed.length) lines.push(["sensors removed", moves(diff.sensors.removed)]);
    if (diff.sensors.changed.length) lines.push(["sensors changed", changes(diff.sensors.changed)]);
    if (diff.buses.added.length) lines.push(["buses added", diff.buses.added.join(", ")]);
    if (diff.buses.removed.length) lines.push(["buses removed", diff.buses.removed.join(", ")]);
    if (diff.buses.restarted.length) {
      lines.push(["buses restarted (their port closed and opened again)", diff.buses.restarted.join(", ")]);
    }
    if (diff.buses.rescheduled.length) {
      lines.push(["buses rescheduled (their port kept open)", diff.buses.rescheduled.join(", ")]);
    }
    if (diff.frontends.changed.length) lines.push(["restarted", changes(diff.frontends.changed)]);
    if (diff.needs_restart.length) {
      lines.push(["needs a restart (kept as it is until then)", changes(diff.needs_restart)]);
    }
    if (diff.buses.unchanged.length) lines.push(["unchanged buses", diff.buses.unchanged.join(", ")]);
    $("diff-summary").textContent = diff.summary;
    $("diff-list").replaceChildren(...lines.map(([what, which]) => element("li",
      { "data-kind": what.split(" (")[0] }, element("b", {}, `${what}: `), which)));
    $("diff").hidden = false;
    const nothing = lines.every(([what]) => what === "unchanged buses");
    $("apply").disabled = nothing;
    say(nothing ? "nothing to apply: the config is the same" : "checked: Apply to make it so", true);
  }

  async function apply() {
    if (!page.previewed) return;
    const [text, type] = page.previewed;
    $("apply").disabled = true;
    say("applying…", true);
    const answer = await call("PUT", `${API}/config`, text, type);
    if (!answer.ok) {
      if (answer.data && answer.data.problems) showProblems(answer.data.problems);
      say(answer.data && answer.data.problems ? answer.data.error : refused(answer), false);
      document.body.dataset.state = answer.status === 422 ? "invalid" : "failed";
      return;
    }
    const done = answer.data;
    await load();
    const restart = done.needs_restart.length
      ? `; needs a restart: ${done.needs_restart.join("; ")}` : "";
    say(`applied: ${done.diff.summary.replace(/^reload: /, "")}; ` +
        `${done.saved ? "" : "not saved: "}${done.note}${restart}`, done.saved);
    document.body.dataset.state = "applied";
  }

  function showTab(tab) {
    if (tab === page.tab) return;
    if (tab === "form" && page.changed.yaml) {
      $("switch-prompt").hidden = false;  // (the YAML tab stays shown until answered)
      $("keep-yaml").focus();
      return;
    }
    if (tab === "yaml" && page.changed.form) {
      // The form's draft, carried over: the text is the config the form holds.
      $("yaml").value = page.yamlBase = toYaml(page.config);
    }
    page.tab = tab;
    $("tab-form").setAttribute("aria-selected", String(tab === "form"));
    $("tab-yaml").setAttribute("aria-selected", String(tab === "yaml"));
    $("form-view").hidden = tab !== "form";
    $("yaml-view").hidden = tab !== "yaml";
    clearProblems();
    say("", true);
    edited();
  }

  $("tab-form").addEventListener("click", () => showTab("form"));
  $("tab-yaml").addEventListener("click", () => showTab("yaml"));
  $("yaml").addEventListener("input", () => edited("yaml"));
  $("keep-yaml").addEventListener("click", () => {
    $("switch-prompt").hidden = true;
    $("yaml").focus();
  });
  $("drop-yaml").addEventListener("click", () => {
    $("switch-prompt").hidden = true;
    $("yaml").value = page.yamlBase;  // the form's draft as it was when last shown here
    page.changed.yaml = false;
    showTab("form");
  });
  $("preview").addEventListener("click", () => preview().catch((e) => say(e.message, false)));
  $("apply").addEventListener("click", () => apply().catch((e) => say(e.message, false)));
  $("reload").addEventListener("click", () => { clearProblems(); say("", true); load(); });
  load().catch((e) => {
    banner(`cannot reach the gateway: ${e.message}`);
    document.body.dataset.state = "failed";
  });
})();
