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
  // A page on its way elsewhere is not reloaded when its socket closes: Log out posts a form
  // whose answer sends the browser on to the sign-in provider's logout page, and the session's
  // end closes the socket meanwhile; a reload then won over that navigation (the provider's
  // session stayed). Reset after a while, in case the navigation did not happen after all.
  var leaving = false;
  window.addEventListener("beforeunload", function () {
    leaving = true;
    setTimeout(function () { leaving = false; }, 10000);
  });
  document.addEventListener("htmx:wsClose", function (e) {
    var event = e.detail && e.detail.event;
    var code = event ? event.code : 0;
    // Logged out, deactivated (4401) or no longer allowed to view (4403): the page itself
    // says what now (the login form, or the no-role page).
    if (code === 4401 || code === 4403) { if (!leaving) window.location.reload(); return; }
    if (code === LINK_LOST) {
      banner(true, gettext("The site has lost its link to Redis; reconnecting when it is back…"));
      var socket = e.detail.socketWrapper;
      if (socket && socket.reconnect) setTimeout(socket.reconnect, delay(linkRetries++));
      return;
    }
    banner(true);
  });
  document.addEventListener("htmx:wsOpen", function () { linkRetries = 0; });
  // A transition's result on the page as its socket (re)opens is older than the snapshot the server
  // sends now, which may clear it (templates/dashboard/_node_state.html); a result that comes later
  // (a click answered while that snapshot was read) is newer, and stays.
  document.addEventListener("htmx:wsOpen", function () {
    document.querySelectorAll("#transition-result > .result").forEach(function (el) {
      el.setAttribute("data-before-socket", "");
    });
  });
  document.addEventListener("htmx:wsError", function () { banner(true); });
  document.addEventListener("htmx:wsOpen", function () { banner(false); });
  window.lifecycleBanner = banner;

  // "for 12 s" beside a transition under way (data-elapsed-from: when the node entered the state).
  function elapsed(seconds) {
    if (seconds < 120) return interpolate(gettext("%(seconds)s s"), { seconds: seconds }, true);
    if (seconds < 7200) return interpolate(gettext("%(minutes)s min"), { minutes: Math.floor(seconds / 60) }, true);
    if (seconds < 172800) {
      return interpolate(gettext("%(hours)s h %(minutes)s min"),
        { hours: Math.floor(seconds / 3600), minutes: Math.floor(seconds % 3600 / 60) }, true);
    }
    var days = Math.floor(seconds / 86400);
    return interpolate(ngettext("%(count)s day", "%(count)s days", days), { count: days }, true);
  }
  setInterval(function () {
    document.querySelectorAll("[data-elapsed-from]").forEach(function (el) {
      el.textContent = elapsed(Math.max(0, Math.round((Date.now() - Date.parse(el.dataset.elapsedFrom)) / 1000)));
    });
  }, 1000);

  // "3 min ago" beside a last known state (fleet rows, the node page), a gateway's outage (the
  // banner) or a run stays true while the page is open.
  function age(seconds) {
    if (seconds < 60) return interpolate(gettext("%(seconds)s s ago"), { seconds: seconds }, true);
    if (seconds < 3600) return interpolate(gettext("%(minutes)s min ago"), { minutes: Math.floor(seconds / 60) }, true);
    return interpolate(gettext("%(hours)s h ago"), { hours: Math.floor(seconds / 3600) }, true);
  }
  setInterval(function () {
    document.querySelectorAll("[data-age]").forEach(function (el) {
      var when = Date.parse(el.dataset.age);
      if (isNaN(when)) return;  // no time known: the server's text stays
      el.textContent = age(Math.max(0, Math.round((Date.now() - when) / 1000)));
    });
  }, 1000);

  // Run panels (templates/dashboard/_run.html) come wrapped to go into their page's run list. A
  // run already shown is replaced in place, unless the panel shown is further along (data-rank):
  // a push, the database and a request's answer arrive in any order. A new one goes where its
  // start puts it (data-created, newest first), a list keeps at most data-keep (the node page:
  // the latest run), and a run dismissed in this browser is not shown again.
  var MAX_RUNS = 6;
  var DISMISSED_KEY = "lifecycle.dismissedRuns", DISMISSED_MAX = 300;
  function dismissed() {
    try { return JSON.parse(window.localStorage.getItem(DISMISSED_KEY) || "[]"); } catch (e) { return []; }
  }
  function dismiss(id) {
    var ids = dismissed().filter(function (x) { return x !== id; });
    ids.push(id);
    try { window.localStorage.setItem(DISMISSED_KEY, JSON.stringify(ids.slice(-DISMISSED_MAX))); } catch (e) { /* private mode: for this page only */ }
  }
  function isDismissed(panelId) { return dismissed().indexOf(panelId.replace(/^run-/, "")) !== -1; }
  // Finished runs older than the newest finished one are shown muted: a stale red failure does
  // not shout above (or below) a later success.
  function tidy(list) {
    var runs = list.querySelectorAll(":scope > .run");
    var keep = Number(list.dataset.keep || MAX_RUNS), shown = 0, newestDone = false;
    for (var i = 0; i < runs.length; i++) {
      if (isDismissed(runs[i].id)) { runs[i].remove(); continue; }
      if (++shown > keep) { runs[i].remove(); continue; }
      runs[i].classList.toggle("run-earlier", newestDone && !!runs[i].dataset.done);
      if (runs[i].dataset.done) newestDone = true;
    }
  }
  document.addEventListener("htmx:oobBeforeSwap", function (e) {
    var list = e.detail.target;
    if (!list || !list.classList || !list.classList.contains("runs")) return;
    var panel = e.detail.fragment && e.detail.fragment.querySelector(".run[id^='run-']");
    if (!panel) return;
    e.detail.shouldSwap = false;
    if (isDismissed(panel.id)) return;
    var shown = document.getElementById(panel.id);
    if (shown) {
      if (Number(panel.dataset.rank) >= Number(shown.dataset.rank)) shown.replaceWith(panel);
      tidy(list);
      return;
    }
    var created = panel.dataset.created || "9999";  // no start known: the newest
    var before = null;
    list.querySelectorAll(":scope > .run").forEach(function (run) {
      if (!before && (run.dataset.created || "9999") < created) before = run;
    });
    list.insertBefore(panel, before);
    // A refusal shown above the list is about an earlier attempt: a run that came since replaces it.
    var result = document.getElementById(list.id + "-result");
    if (result) result.textContent = "";
    tidy(list);
  });
  document.addEventListener("click", function (e) {
    var button = e.target.closest && e.target.closest("[data-dismiss-run]");
    if (!button) return;
    var panel = button.closest(".run"), list = panel && panel.parentElement;
    dismiss(button.dataset.dismissRun);
    if (panel) panel.remove();
    if (list && list.classList.contains("runs")) tidy(list);
  });
  function tidyAll() { document.querySelectorAll(".runs").forEach(tidy); }
  document.addEventListener("DOMContentLoaded", tidyAll);
  // After a swap (a reconnect's whole fleet list): once htmx has settled, as settling puts back
  // the server's classes of elements with an id (a socket's message is settled at once).
  document.addEventListener("htmx:afterSettle", tidyAll);
  document.addEventListener("htmx:wsAfterMessage", tidyAll);

  // A refusal because a gateway was offline ("nothing was sent") says nothing true once it is
  // back: the banner (templates/dashboard/_gateway_banner.html) names those still offline.
  document.addEventListener("htmx:oobAfterSwap", function (e) {
    var banner = e.detail.target;
    if (!banner || banner.id !== "gateway-banner") banner = document.getElementById("gateway-banner");
    if (!banner) return;
    var offline = (banner.dataset.offline || "").split(" ").filter(Boolean);
    document.querySelectorAll("[data-gateway-refusal]").forEach(function (el) {
      if (offline.indexOf(el.dataset.gatewayRefusal) === -1) el.remove();
    });
  });

  // Sections that fold away on a narrow screen (<details data-fold-narrow open>): closed there
  // when the page loads; after that as the user leaves them (live updates swap what is inside).
  document.addEventListener("DOMContentLoaded", function () {
    if (!window.matchMedia("(max-width: 720px)").matches) return;
    document.querySelectorAll("details[data-fold-narrow]").forEach(function (el) { el.open = false; });
  });
})();
