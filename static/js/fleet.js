// Fleet overview: filters (robot, state, name) and per-robot counts, recomputed from the
// rows whenever htmx swaps in a live update. Filters are kept in the URL for bookmarks.
(function () {
  "use strict";
  // A badge's word: ROS states as they are, the fleet's own statuses in the page's language
  // (as the server's status_word filter writes them).
  function statusWord(status) {
    var words = { waiting: pgettext("node status", "waiting"), lost: pgettext("node status", "lost"),
      unreachable: pgettext("node status", "unreachable"), busy: pgettext("node status", "busy") };
    return words[status] || status;
  }
  var STATES = ["active", "inactive", "unconfigured", "finalized", "busy", "lost", "waiting"];

  function filters() {
    var values = {};
    document.querySelectorAll("[data-filter]").forEach(function (el) {
      values[el.dataset.filter] = el.value.trim().toLowerCase();
    });
    return values;
  }

  // What needs attention (templates/dashboard/_attention.html): its nodes and offline gateways.
  function attention() {
    var strip = document.getElementById("attention");
    var words = function (name) { return strip ? (strip.dataset[name] || "").split(" ").filter(Boolean) : []; };
    var rows = {};
    words("keys").forEach(function (key) { rows["node-" + key.split(".").join("__")] = true; });
    return {
      rows: rows,
      gateways: words("gateways"),
      count: strip ? Number(strip.dataset.count || 0) : 0,
    };
  }
  // Each affected row carries a marker (rows are redrawn by live updates: put back each time).
  function mark(row, on) {
    var cell = row.querySelector("td.name"), marker = cell && cell.querySelector(".attention-mark");
    if (on) row.dataset.attention = "true"; else delete row.dataset.attention;
    if (on && cell && !marker) {
      marker = document.createElement("span");
      marker.className = "attention-mark";
      marker.title = gettext("Needs attention: see the list at the top of the page");
      marker.setAttribute("role", "img");
      marker.setAttribute("aria-label", gettext("needs attention"));
      marker.textContent = "!";
      cell.insertBefore(marker, cell.firstChild);
    } else if (!on && marker) {
      marker.remove();
    }
  }
  // The page's title without the server's "3 need attention · " in front: the words this script
  // puts there for that count, else a number and the words up to the first " · ".
  var baseTitle = null;
  function attentionTitle(count, base) {
    // Translators: the fleet page's title (browser tab); %(title)s is the rest of it ("Fleet · Lifecycle manager").
    return interpolate(ngettext("%(count)s needs attention · %(title)s", "%(count)s need attention · %(title)s", count),
      { count: count, title: base }, true);
  }
  function title(count) {
    if (baseTitle === null) {
      var served = document.title, counted = attentionTitle(count, "");
      baseTitle = count && served.indexOf(counted) === 0 ? served.slice(counted.length) : served.replace(/^\d+ [^·]*· /, "");
    }
    var text = count ? attentionTitle(count, baseTitle) : baseTitle;
    if (document.title !== text) document.title = text;
  }

  function apply() {
    var f = filters();
    var shown = 0, total = 0, collapsed = [];
    var needs = attention();
    title(needs.count);
    document.querySelectorAll("section.robot").forEach(function (section) {
      var robot = section.dataset.robot;
      section.hidden = !!f.robot && f.robot !== robot;
      var counts = {}, alive = 0;
      // A collapsed robot (a large fleet) has no rows: its counts come from the server.
      var summary = section.dataset.collapsed ? section.querySelector(".robot-summary") : null;
      if (summary) {
        alive = Number(summary.dataset.alive || 0);
        total += Number(summary.dataset.total || 0);
        if (!section.hidden) collapsed.push(robot);
      }
      var owner = section.closest("section.gateway");
      var ownerAway = !!owner && needs.gateways.indexOf(owner.dataset.gateway) !== -1;
      section.querySelectorAll("tr.node-row").forEach(function (row) {
        var status = row.dataset.status;
        var attends = ownerAway || needs.rows[row.id] === true;
        mark(row, attends);
        counts[status] = (counts[status] || 0) + 1;
        if (status !== "lost" && status !== "waiting") alive += 1;
        var visible = !section.hidden &&
          (!f.state || (f.state === "attention" ? attends : f.state === status)) &&
          (!f.q || row.dataset.name.toLowerCase().indexOf(f.q) !== -1);
        row.hidden = !visible;
        total += 1;
        if (visible) shown += 1;
      });
      var text = STATES.filter(function (s) { return counts[s]; })
        .map(function (s) { return counts[s] + " " + statusWord(s); }).join(" · ");
      var countsEl = section.querySelector("[data-counts-for]");
      if (countsEl) countsEl.textContent = summary ? "" : (text || gettext("no nodes"));
      var group = section.closest("section.gateway");
      var head = group && group.querySelector("[data-gateway-online]");
      var gatewayDown = !!head && head.dataset.gatewayOnline !== "true";
      // While the robot's gateway is offline or cut off, its group operations cannot be sent
      // (as its rows' transitions): the buttons say so instead of answering with a refusal.
      section.querySelectorAll("form.operations button").forEach(function (button) {
        button.disabled = gatewayDown;
        if (gatewayDown) button.title = gettext("The gateway is offline: no command can be sent.");
        else button.removeAttribute("title");
      });
      // The badge is this script's while it is empty or says what this script put there: the
      // server's words ("disabled", in the page's language) stay.
      var onlineEl = section.querySelector("[data-online-for]");
      var onlineWords = [gettext("online"), gettext("offline")];
      if (onlineEl && (!onlineEl.textContent || onlineWords.indexOf(onlineEl.textContent) !== -1)) {
        var online = alive > 0 && !gatewayDown;
        onlineEl.textContent = online ? onlineWords[0] : onlineWords[1];
        onlineEl.className = "robot-online badge " + (online ? "online" : "offline");
      }
    });
    var totalEl = document.querySelector(".fleet-total");
    var filtering = f.q || f.state || f.robot;
    if (totalEl) {
      var totalText;
      // Translators: the English says "nodes" for one node too; the singular form is for 1.
      if (!filtering) totalText = ngettext("%(total)s nodes", "%(total)s nodes", total);
      // Translators: the English says "nodes" for one node too; the singular form is for 1 (the total).
      else if (!collapsed.length) totalText = ngettext("%(shown)s of %(total)s nodes", "%(shown)s of %(total)s nodes", total);
      // Translators: the English says "nodes" for one node too; the singular form is for 1 (the total).
      else totalText = ngettext("%(shown)s of %(total)s nodes (and matches in collapsed robots)",
        "%(shown)s of %(total)s nodes (and matches in collapsed robots)", total);
      totalEl.textContent = interpolate(totalText, { shown: shown, total: total }, true);
    }
    find(f, collapsed);
  }

  // The name and state filters reach the nodes of collapsed robots through the server
  // (views.fleet_find: at most 50 links), asked a moment after the last keystroke.
  var findTimer = null, lastFind = "";
  function find(f, collapsed) {
    var live = document.getElementById("fleet-live"), box = document.getElementById("fleet-matches");
    if (!live || !box) return;
    var query = (f.q || f.state) && collapsed.length ?
      "?" + new URLSearchParams({ q: f.q || "", state: f.state || "", robots: collapsed.join(",") }).toString() : "";
    if (query === lastFind) return;
    lastFind = query;
    clearTimeout(findTimer);
    if (!query) { box.innerHTML = ""; return; }
    findTimer = setTimeout(function () {
      htmx.ajax("GET", live.dataset.findUrl + query, { target: box, swap: "innerHTML" });
    }, 250);
  }

  // The robots opened beyond their collapsed default: in the URL (a reload keeps them open)
  // and told to the page's socket, which then sends their rows instead of their counts.
  var socket = null, lastOpen = null;
  function openRobots() {
    return Array.prototype.map.call(
      document.querySelectorAll("section.robot[data-collapsible]:not([data-collapsed])"),
      function (section) { return section.dataset.robot; });
  }
  function syncOpen(resync) {
    var open = openRobots().join(",");
    if (open !== lastOpen) {
      var params = new URLSearchParams(window.location.search);
      if (open) params.set("open", open); else params.delete("open");
      var query = params.toString();
      window.history.replaceState(null, "", window.location.pathname + (query ? "?" + query : ""));
    }
    if (socket && (resync || open !== lastOpen)) {
      socket.send(JSON.stringify({ open: open ? open.split(",") : [], resync: !!resync }));
    }
    lastOpen = open;
  }
  function socketState(state) {
    var live = document.getElementById("fleet-live");
    if (live) live.dataset.socket = state;
  }
  document.addEventListener("htmx:wsOpen", function (e) {
    socket = e.detail.socketWrapper;
    syncOpen(true);
    socketState("open");
  });
  document.addEventListener("htmx:wsClose", function () { socket = null; socketState("closed"); });
  document.addEventListener("htmx:afterSettle", function () { syncOpen(false); });

  function rememberFilters() {
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
      el.addEventListener("input", function () { apply(); rememberFilters(); });
    });
    apply();
  });
  document.addEventListener("htmx:oobAfterSwap", apply);
  document.addEventListener("htmx:afterSwap", apply);
  document.addEventListener("htmx:wsAfterMessage", apply);
  document.addEventListener("htmx:afterSettle", apply);  // settling puts back a redrawn row's attributes

  // Keyboard focus stays in a node's row when a live update redraws it, or its button is
  // disabled while its request runs (the browser then drops the focus to the page): the same
  // button if it is still offered, else the row's first button, else its link. Without this,
  // the keyboard was back at the top of the page.
  var refocus = null;  // {row, transition, at}: a row whose button was used (or focused) last
  function focusInRow(rowId, transition) {
    var row = document.getElementById(rowId);
    if (!row) return;
    var same = transition && row.querySelector("button[data-transition='" + transition + "']:not([disabled])");
    var target = same || row.querySelector(".actions button:not([disabled])") || row.querySelector("a");
    if (target) target.focus();
  }
  function restore() {
    var active = document.activeElement;
    if (refocus && (!active || active === document.body) && Date.now() - refocus.at < 60000) {
      focusInRow(refocus.row, refocus.transition);
    }
  }
  function remember(elt) {
    var row = elt && elt.closest && elt.closest("tr.node-row");
    refocus = row ? { row: row.id, transition: elt.dataset.transition, at: Date.now() } : null;
  }
  document.addEventListener("focusin", function (e) { remember(e.target); });
  // A click elsewhere means the user moved on: no focus is brought back to the row then.
  document.addEventListener("pointerdown", function (e) {
    if (!e.target.closest || !e.target.closest("tr.node-row")) refocus = null;
  });
  document.addEventListener("htmx:beforeRequest", function (e) { remember(e.detail.elt); });
  document.addEventListener("htmx:oobAfterSwap", restore);
  // The answer lands in the row's result (kept across redraws); the button that asked may
  // already be gone from the page, so its own events do not reach the document.
  document.addEventListener("htmx:afterSwap", function () { setTimeout(restore, 0); });
  document.addEventListener("htmx:afterRequest", function () { setTimeout(restore, 0); });

  // A row's answer (templates/dashboard/_node_row_result.html) clears itself.
  document.addEventListener("htmx:afterSwap", function (e) {
    var slot = e.detail.target, result = slot && slot.classList.contains("row-result") && slot.firstElementChild;
    if (!result) return;
    setTimeout(function () { result.remove(); }, 1000 * Number(result.dataset.clearAfter || 10));
  });

  // The snapshot a page gets when its socket (re)connects redraws the robots, forms included:
  // the choices made in them (failure policy, timeout, a name being typed) are kept.
  var choices = null;
  function controls(root) {
    return root.querySelectorAll("section.robot form:not([data-local]) [name]:not([type=hidden]):not(button)");
  }
  function choiceKey(el) {
    var section = el.closest("section.robot"), form = el.closest("form");
    return (section ? section.dataset.robot : "") + "|" + (form ? form.className : "") + "|" + el.name;
  }
  document.addEventListener("htmx:oobBeforeSwap", function (e) {
    if (!e.detail.target || e.detail.target.id !== "robots") return;
    choices = {};
    controls(e.detail.target).forEach(function (el) { choices[choiceKey(el)] = el.value; });
  });
  document.addEventListener("htmx:oobAfterSwap", function () {
    if (!choices) return;
    var robots = document.getElementById("robots");
    if (robots) controls(robots).forEach(function (el) {
      var key = choiceKey(el);
      if (Object.prototype.hasOwnProperty.call(choices, key)) el.value = choices[key];
    });
    choices = null;
  });

})();
