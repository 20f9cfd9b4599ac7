// Connection banner for pages with a live WebSocket (htmx ws extension): shown while the
// socket is down; htmx reconnects by itself and the server then re-sends the current state.
(function () {
  "use strict";
  function banner(show) {
    var el = document.getElementById("ws-banner");
    if (el) el.hidden = !show;
  }
  document.addEventListener("htmx:wsClose", function (e) {
    var code = e.detail && e.detail.event ? e.detail.event.code : 0;
    // Logged out, deactivated (4401) or no longer allowed to view (4403): the page itself
    // says what now (the login form, or the no-role page).
    if (code === 4401 || code === 4403) { window.location.reload(); return; }
    banner(true);
  });
  document.addEventListener("htmx:wsError", function () { banner(true); });
  document.addEventListener("htmx:wsOpen", function () { banner(false); });
  window.lifecycleBanner = banner;
})();
