/* imu-gateway dashboard: who is looking (docs/dashboard.md, "Logging in").
 *
 * The credential (a session token from POST /api/v1/login, or a token of http.tokens)
 * is kept in sessionStorage (gone when the tab closes) and sent as
 * "Authorization: Bearer" only: never in a URL (addresses end up in logs, histories
 * and Referer headers).  A ?token= in the page address is dropped and ignored.
 * EventSource cannot send headers, so with a credential the stream is read with
 * fetch (imuAuth.eventSource, static/auth.js, which every page of the gateway loads).
 *
 * Adds to window.imuAuth: may(role), user, role, ready (a promise:
 * resolved once the page knows who is looking; the login form is shown until then
 * when the gateway's reads need a credential), eventSource(url).
 * Test hooks: #login (the form: #login-user, #login-password, #login-result),
 * #who (data-user, data-role), #login-open, #logout.
 */
"use strict";

(function () {
  const API = "api/v1";
  const KEY = window.imuAuth.KEY;
  const RANK = { viewer: 1, operator: 2, admin: 3 };
  const $ = (id) => document.getElementById(id);

  const auth = window.imuAuth; // static/auth.js: the credential, its header, streams
  auth.user = "anonymous";
  auth.role = "viewer";
  auth.may = (role) => (RANK[auth.role] || 0) >= RANK[role];

  // A token in the address is not a credential any more: out of the address bar (and
  // the history) at once, and the page says how to log in instead.
  const params = new URLSearchParams(location.search);
  const droppedToken = params.has("token");
  if (droppedToken) {
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", location.pathname + (rest ? "?" + rest : "") + location.hash);
  }

  async function whoAmI() {
    const response = await fetch(API + "/me", { headers: auth.headers(), cache: "no-store" });
    if (response.status === 401) return null;
    if (!response.ok) throw new Error(response.statusText);
    return response.json();
  }

  function showWho() {
    const who = $("who");
    who.dataset.user = auth.user;
    who.dataset.role = auth.role;
    who.textContent = auth.credential() ? `${auth.user} · ${auth.role}` : "";
    $("logout").hidden = !auth.credential();
    $("login-open").hidden = Boolean(auth.credential());
  }

  /** The form, until a login succeeds; the page is then loaded again with the new
   *  credential (every part of it starts as that role). */
  function showForm(message) {
    const form = $("login");
    form.hidden = false;
    $("login-result").textContent = message || "";
    $("login-user").focus();
  }

  async function logIn(event) {
    event.preventDefault();
    const user = $("login-user").value.trim();
    const password = $("login-password").value;
    // No user name: the password field holds a token of http.tokens.
    const body = user ? { user, password } : { token: password };
    const out = $("login-result");
    out.textContent = "logging in…";
    try {
      const response = await fetch(API + "/login", {
        method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify(body), cache: "no-store",
      });
      const answer = await response.json().catch(() => ({}));
      if (!response.ok) {
        const wait = response.headers.get("Retry-After");
        out.textContent = response.status === 429
          ? `too many attempts: try again in ${wait} s`
          : `refused: ${answer.error || response.statusText}`;
        out.dataset.ok = "false";
        return;
      }
      sessionStorage.setItem(KEY, answer.token);
      location.reload();
    } catch (error) {
      out.textContent = error.message;
      out.dataset.ok = "false";
    }
  }

  async function logOut() {
    try {
      await fetch(API + "/logout", { method: "POST", headers: auth.headers(), cache: "no-store" });
    } finally {
      sessionStorage.removeItem(KEY);
      location.reload();
    }
  }

  auth.ready = (async function () {
    $("login").addEventListener("submit", logIn);
    $("logout").addEventListener("click", logOut);
    $("login-open").addEventListener("click", () => showForm());
    for (;;) {
      let who;
      try {
        who = await whoAmI();
      } catch (error) { // the gateway is not there yet: the banner of dashboard.js tells
        await new Promise((resolve) => setTimeout(resolve, 2000));
        continue;
      }
      if (who) {
        auth.user = who.user;
        auth.role = who.role;
        showWho();
        if (droppedToken && !auth.credential()) {
          showForm("a token in the page address is not used: log in here");
        }
        return auth;
      }
      const stale = Boolean(auth.credential());
      sessionStorage.removeItem(KEY);
      showWho();
      showForm(stale ? "the session ended: log in again"
        : droppedToken ? "a token in the page address is not used: log in here"
          : "this gateway's readings need a login");
      await new Promise(() => { /* the form reloads the page once logged in */ });
    }
  })();

})();
