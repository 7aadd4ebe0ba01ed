/* The dashboard's link to the Setup page (docs/dashboard.md, "Setup"): shown to an
 * admin only, once static/login.js knows who is looking.  The config routes refuse
 * anyone else all the same (403). */
"use strict";

window.imuAuth.ready.then((auth) => {
  document.getElementById("setup-link").hidden = !auth.may("admin");
});
