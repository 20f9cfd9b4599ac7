// Connection banner for pages with a live WebSocket (htmx ws extension): shown while the
// socket is down; htmx reconnects by itself and the server then re-sends the current state.
(function () {
  "use strict";
  function banner(show) {
    var el = document.getElementById("ws-banner");
    if (el) el.hidden = !show;
  }
  document.addEventListener("htmx:wsClose", function () { banner(true); });
  document.addEventListener("htmx:wsError", function () { banner(true); });
  document.addEventListener("htmx:wsOpen", function () { banner(false); });
  window.lifecycleBanner = banner;
})();
