/* imu-gateway: the credential every page of the gateway sends (docs/dashboard.md,
 * "Logging in").  The dashboard's login form (static/login.js) keeps it in
 * sessionStorage (gone when the tab closes); every page of the tab sends it as
 * "Authorization: Bearer", never in a URL.  EventSource cannot send headers, so with
 * a credential a stream is read with fetch.
 *
 * window.imuAuth: KEY, credential(), headers(), eventSource(url).
 */
"use strict";

(function () {
  const KEY = "imu-gateway.credential";

  /** Server-Sent Events read with fetch, so that the request carries the
   *  Authorization header; what dashboard.js uses of EventSource: addEventListener
   *  ("open", "error", and the events by name), readyState, close(). */
  class FetchEventSource extends EventTarget {
    constructor(url) {
      super();
      this.readyState = 0; // CONNECTING
      this.controller = new AbortController();
      this.run(url).catch(() => { /* ended: "error" below */ }).finally(() => {
        if (this.readyState === 2) return;
        this.readyState = 2; // CLOSED: the caller opens another
        this.dispatchEvent(new Event("error"));
      });
    }

    close() {
      this.readyState = 2;
      this.controller.abort();
    }

    async run(url) {
      const response = await fetch(url, {
        headers: { ...window.imuAuth.headers(), Accept: "text/event-stream" },
        cache: "no-store", signal: this.controller.signal,
      });
      if (!response.ok) throw new Error(String(response.status));
      this.readyState = 1; // OPEN
      this.dispatchEvent(new Event("open"));
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        buffer += value.replace(/\r\n?/g, "\n");
        let end;
        while ((end = buffer.indexOf("\n\n")) >= 0) {
          this.dispatch(buffer.slice(0, end));
          buffer = buffer.slice(end + 2);
        }
      }
    }

    dispatch(block) {
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith(":")) continue; // a keep-alive comment
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (field === "event") name = value;
        else if (field === "data") data.push(value);
      }
      if (data.length) this.dispatchEvent(new MessageEvent(name, { data: data.join("\n") }));
    }
  }

  window.imuAuth = {
    KEY,
    credential: () => sessionStorage.getItem(KEY),
    headers() {
      const token = window.imuAuth.credential();
      return token ? { Authorization: "Bearer " + token } : {};
    },
    eventSource: (url) => (window.imuAuth.credential()
      ? new FetchEventSource(url) : new EventSource(url)),
  };
})();
