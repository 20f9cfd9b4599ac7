// Connection banner for pages with a live WebSocket (htmx ws extension): shown while the
// socket is down; htmx reconnects by itself and the server then re-sends the current state.
(function () {
  "use strict";
  var usual = null;
  function banner(show, reason) {
    var el = document.getElementById("ws-banner");
    if (!el) return;
    if (usual === null) usual = el.textContent;
    el.textContent = show && reason ? reason : usual;
    el.hidden = !show;
  }
  // htmx reconnects by itself after an abnormal close (1006), an error (1011) or a restart
  // (1012), with a random delay that doubles each time; capped here at 10 s, so that a page
  // is live again within seconds of the end of a long outage (htmx's own cap is 64 s).
  function delay(retries) {
    return Math.random() * Math.min(10000, 1000 * Math.pow(2, Math.min(retries, 4)));
  }
  if (window.htmx) window.htmx.config.wsReconnectDelay = delay;
  // 4503: the site has lost its link to Redis (consumers.TRY_AGAIN_LATER). htmx does not retry
  // such a code by itself: the page does, the same way.
  var LINK_LOST = 4503;
  var linkRetries = 0;
  document.addEventListener("htmx:wsClose", function (e) {
    var event = e.detail && e.detail.event;
    var code = event ? event.code : 0;
    // Logged out, deactivated (4401) or no longer allowed to view (4403): the page itself
    // says what now (the login form, or the no-role page).
    if (code === 4401 || code === 4403) { window.location.reload(); return; }
    if (code === LINK_LOST) {
      banner(true, "The site has lost its link to Redis; reconnecting when it is back…");
      var socket = e.detail.socketWrapper;
      if (socket && socket.reconnect) setTimeout(socket.reconnect, delay(linkRetries++));
      return;
    }
    banner(true);
  });
  document.addEventListener("htmx:wsOpen", function () { linkRetries = 0; });
  document.addEventListener("htmx:wsError", function () { banner(true); });
  document.addEventListener("htmx:wsOpen", function () { banner(false); });
  window.lifecycleBanner = banner;
})();
