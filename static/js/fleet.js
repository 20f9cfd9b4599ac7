// Fleet overview: filters (robot, state, name) and per-robot counts, recomputed from the
// rows whenever htmx swaps in a live update. Filters are kept in the URL for bookmarks.
(function () {
  "use strict";
  var STATES = ["active", "inactive", "unconfigured", "finalized", "busy", "lost", "waiting"];

  function filters() {
    var values = {};
    document.querySelectorAll("[data-filter]").forEach(function (el) {
      values[el.dataset.filter] = el.value.trim().toLowerCase();
    });
    return values;
  }

  function apply() {
    var f = filters();
    var shown = 0, total = 0;
    document.querySelectorAll("section.robot").forEach(function (section) {
      var robot = section.dataset.robot;
      section.hidden = !!f.robot && f.robot !== robot;
      var counts = {}, alive = 0;
      section.querySelectorAll("tr.node-row").forEach(function (row) {
        var status = row.dataset.status;
        counts[status] = (counts[status] || 0) + 1;
        if (status !== "lost" && status !== "waiting") alive += 1;
        var visible = !section.hidden &&
          (!f.state || f.state === status) &&
          (!f.q || row.dataset.name.toLowerCase().indexOf(f.q) !== -1);
        row.hidden = !visible;
        total += 1;
        if (visible) shown += 1;
      });
      var summary = STATES.filter(function (s) { return counts[s]; })
        .map(function (s) { return counts[s] + " " + s; }).join(" · ");
      var countsEl = section.querySelector("[data-counts-for]");
      if (countsEl) countsEl.textContent = summary || "no nodes";
      var onlineEl = section.querySelector("[data-online-for]");
      if (onlineEl && onlineEl.textContent !== "disabled") {
        var group = section.closest("section.gateway");
        var head = group && group.querySelector("[data-gateway-online]");
        var gatewayDown = !!head && head.dataset.gatewayOnline !== "true";
        var online = alive > 0 && !gatewayDown;
        onlineEl.textContent = online ? "online" : "offline";
        onlineEl.className = "robot-online badge " + (online ? "online" : "offline");
      }
    });
    var totalEl = document.querySelector(".fleet-total");
    if (totalEl) totalEl.textContent = shown === total ? total + " nodes" : shown + " of " + total + " nodes";
  }

  function remember() {
    var params = new URLSearchParams(window.location.search);
    var f = filters();
    Object.keys(f).forEach(function (k) { if (f[k]) params.set(k, f[k]); else params.delete(k); });
    var query = params.toString();
    window.history.replaceState(null, "", window.location.pathname + (query ? "?" + query : ""));
  }

  document.addEventListener("DOMContentLoaded", function () {
    // The filters apply in the page: Enter in the name field must not reload it.
    document.querySelectorAll("form[data-local]").forEach(function (form) {
      form.addEventListener("submit", function (event) { event.preventDefault(); });
    });
    document.querySelectorAll("[data-filter]").forEach(function (el) {
      el.addEventListener("input", function () { apply(); remember(); });
    });
    apply();
  });
  document.addEventListener("htmx:oobAfterSwap", apply);
  document.addEventListener("htmx:afterSwap", apply);
  document.addEventListener("htmx:wsAfterMessage", apply);
})();
