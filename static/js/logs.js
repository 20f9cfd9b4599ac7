// Log console: live /rosout lines over a WebSocket (JSON), with a bounded number of lines
// in the page, filters (level, text, not, nodes to keep or hide, optionally as regular
// expressions), pause/resume, clear, follow-tail and download. The filters live in the page's
// address, so a reload or a shared link shows the same lines.
//
// Regular expressions run here, in the user's own browser, on at most MAX_LINES lines (and on
// a download the user asked for): never on the server, where one pattern that backtracks
// badly would hold up everyone. They are limited to MAX_PATTERN characters and one that does
// not compile is named, with the browser's reason, and ignored until it is fixed.
(function () {
  "use strict";
  var MAX_LINES = 1000;       // lines kept in the page; older ones drop off
  var MAX_PAUSED = 5000;      // lines held back while paused
  var MAX_PATTERN = 200;      // characters of a filter (log_views.MAX_FILTER_CHARS)
  var LEVELS = { DEBUG: 10, INFO: 20, WARN: 30, ERROR: 40, FATAL: 50 };
  // The filter fields: query parameter, data-log name, and the field's label (as on the page).
  var TEXT_FIELDS = [["q", "text", pgettext("log filter", "Text")], ["not", "not", pgettext("log filter", "Not")],
                     ["node", "node", pgettext("log filter", "Nodes")], ["xnode", "xnode", pgettext("log filter", "Hide nodes")]];

  var root = document.getElementById("log-console");
  if (!root) return;
  var q = function (name) { return root.querySelector('[data-log="' + name + '"]'); };
  var lines = q("lines"), levelEl = q("level"), pauseEl = q("pause"), regexEl = q("regex"),
      followEl = q("follow"), statusEl = q("status"), downloadEl = q("download"), errorEl = q("error");
  var downloadBase = downloadEl.getAttribute("href");
  var paused = false, held = [], heldDropped = 0, lastId = 0;
  var match = compile();

  // -- filters ------------------------------------------------------------------------
  function fieldValue(param) {
    var field = TEXT_FIELDS.filter(function (f) { return f[0] === param; })[0];
    var el = field && q(field[1]);
    return el ? el.value.trim() : "";
  }

  function plainTest(param, value) {
    var needles = value.toLowerCase();
    if (param === "node" || param === "xnode") {
      var names = needles.split(",").map(function (n) { return n.trim(); }).filter(Boolean);
      return function (text) { return names.some(function (n) { return text.indexOf(n) !== -1; }); };
    }
    return function (text) { return text.indexOf(needles) !== -1; };
  }

  // One test per filled-in field; the problems of those that cannot be used, in words.
  function compile() {
    var tests = {}, problems = [];
    TEXT_FIELDS.forEach(function (field) {
      var value = fieldValue(field[0]);
      if (!value) return;
      if (!regexEl.checked) { tests[field[0]] = plainTest(field[0], value); return; }
      if (value.length > MAX_PATTERN) {
        problems.push(interpolate(gettext("%(field)s: the expression is longer than %(max)s characters; it is ignored."),
          { field: field[2], max: MAX_PATTERN }, true));
        return;
      }
      try {
        var pattern = new RegExp(value, "i");
        tests[field[0]] = function (text) { return pattern.test(text); };
      } catch (error) {
        problems.push(interpolate(gettext("%(field)s: not a valid regular expression (%(reason)s); it is ignored until it is fixed."),
          { field: field[2], reason: error.message }, true));
      }
    });
    errorEl.textContent = problems.join(" ");
    errorEl.hidden = !problems.length;
    return tests;
  }

  // Text and Not look at the message and at the logger (node) name, each on its own, so that
  // ^ and $ mean the start and end of either.
  function visible(record) {
    if (LEVELS[record.level] < LEVELS[levelEl.value]) return false;
    var message = regexEl.checked ? record.message : record.message.toLowerCase();
    var logger = regexEl.checked ? record.logger : record.logger.toLowerCase();
    var either = function (test) { return test(message) || test(logger); };
    if (match.q && !either(match.q)) return false;
    if (match.not && either(match.not)) return false;
    if (match.node && !match.node(logger)) return false;
    if (match.xnode && match.xnode(logger)) return false;
    return true;
  }

  function params() {
    var found = new URLSearchParams();
    if (levelEl.value !== "DEBUG") found.set("level", levelEl.value);
    TEXT_FIELDS.forEach(function (field) { if (fieldValue(field[0])) found.set(field[0], fieldValue(field[0])); });
    if (regexEl.checked) found.set("re", "1");
    return found;
  }

  // -- lines --------------------------------------------------------------------------
  function when(stamp) {
    var moment = new Date(stamp);
    return isNaN(moment.getTime()) ? stamp : moment.toISOString().replace("T", " ").replace("Z", " UTC");
  }

  function lineFor(record) {
    var div = document.createElement("div");
    div.className = "log-line level-" + record.level.toLowerCase();
    div.record = record;
    [[when(record.stamp), "t"], [record.level, "lvl"], [record.logger, "logger"], [record.message, "msg"]].forEach(function (part) {
      var span = document.createElement("span");
      span.className = part[1];
      span.textContent = part[0];
      div.appendChild(span);
    });
    div.hidden = !visible(record);
    return div;
  }

  function append(records) {
    if (!records.length) return;
    var fragment = document.createDocumentFragment();
    records.forEach(function (r) {
      if (r.id <= lastId) return;   // already shown (history and live overlap)
      lastId = r.id;
      fragment.appendChild(lineFor(r));
    });
    lines.appendChild(fragment);
    while (lines.childElementCount > MAX_LINES) lines.removeChild(lines.firstElementChild);
    if (followEl.checked) lines.scrollTop = lines.scrollHeight;
    status();
  }

  function receive(records) {
    if (!paused) return append(records);
    held = held.concat(records);
    if (held.length > MAX_PAUSED) {
      heldDropped += held.length - MAX_PAUSED;
      held = held.slice(held.length - MAX_PAUSED);
    }
    status();
  }

  function status(extra) {
    var total = 0, shown = 0;
    for (var line = lines.firstElementChild; line; line = line.nextElementSibling) {
      if (!line.record) continue;  // a marker (of a moment, or of a gap)
      total += 1;
      if (!line.hidden) shown += 1;
    }
    // Translators: the English says "lines" for one line too; the singular form is for 1.
    var lineCount = shown === total ? ngettext("%(total)s lines shown (the newest %(max)s are kept)",
      "%(total)s lines shown (the newest %(max)s are kept)", total)
      // Translators: the English says "lines" for one line too; the singular form is for 1 (the total).
      : ngettext("%(shown)s of %(total)s lines shown (the newest %(max)s are kept)",
        "%(shown)s of %(total)s lines shown (the newest %(max)s are kept)", total);
    var parts = [interpolate(lineCount, { shown: shown, total: total, max: MAX_LINES }, true)];
    if (paused) {
      parts.push(interpolate(heldDropped ? gettext("paused, %(held)s waiting, %(dropped)s dropped") : gettext("paused, %(held)s waiting"),
        { held: held.length, dropped: heldDropped }, true));
    }
    if (extra) parts.push(extra);
    statusEl.textContent = parts.join(" · ");
  }

  function refilter() {
    match = compile();
    Array.prototype.forEach.call(lines.children, function (div) { if (div.record) div.hidden = !visible(div.record); });
    var address = params();
    if (root.dataset.at) address.set("at", root.dataset.at);  // opened at a moment (a timeline's mark)
    var query = address.toString();
    history.replaceState(history.state, "", location.pathname + (query ? "?" + query : "") + location.hash);
    var server = params();
    downloadEl.setAttribute("href", downloadBase + (server.toString() ? "?" + server.toString() : ""));
    status();
  }

  // With regular expressions the server sends the records for the level and the page keeps
  // those that match, as in the console, then saves them as the server's text file would be.
  function downloadFiltered(event) {
    if (!regexEl.checked) return;
    event.preventDefault();
    var query = params();
    query.set("format", "json");
    status(gettext("preparing the download…"));
    fetch(downloadBase + "?" + query.toString(), { credentials: "same-origin" })
      .then(function (r) {
        if (!r.ok) throw new Error(interpolate(gettext("the server answered %(status)s"), { status: r.status }, true));
        return r.json();
      })
      .then(function (body) {
        // The server names the filters (log_views.download_names), as in its own text file.
        var text = [interpolate(gettext("# /rosout of %(title)s, downloaded %(moment)s"),
          { title: body.title, moment: when(new Date().toISOString()) }, true), body.filters];
        body.records.filter(visible).forEach(function (r) {
          text.push(when(r.stamp) + " [" + r.level + "] [" + r.logger + "] " + r.message);
        });
        var link = document.createElement("a");
        link.href = URL.createObjectURL(new Blob([text.join("\n") + "\n"], { type: "text/plain" }));
        link.download = body.file_name;
        document.body.appendChild(link);
        link.click();
        link.remove();
        setTimeout(function () { URL.revokeObjectURL(link.href); }, 10000);
        status();
      })
      .catch(function (error) {
        status(interpolate(gettext("download failed: %(reason)s; try again"), { reason: error.message }, true));
      });
  }

  // -- gaps ---------------------------------------------------------------------------
  // A stretch in which the gateway's process was down (log_views: ingest/outages.py): nothing
  // received /rosout then. Marked where it falls among the lines, whatever the filters.
  function addGaps(gaps) {
    (gaps || []).forEach(function (gap) {
      var div = lines.querySelector('[data-gap="' + gap.id + '"]');
      var known = Boolean(div);  // told again when it has ended: its words follow
      if (!div) div = document.createElement("div");
      div.className = "log-gap";
      div.dataset.gap = gap.id;
      // An outage still going on has no end yet (the gateway offline, stopped or quarantined).
      var seconds = Math.round((Date.parse(gap.ended) - Date.parse(gap.began)) / 1000);
      var words = !gap.ended
        ? gettext("gateway %(gateway)s could not be reached since %(began)s: /rosout of that time was not received")
        : isNaN(seconds)
          ? gettext("gateway %(gateway)s could not be reached from %(began)s to %(ended)s: /rosout of that time was not received")
          : gettext("gateway %(gateway)s could not be reached from %(began)s to %(ended)s (%(seconds)s s): /rosout of that time was not received");
      div.textContent = interpolate(words,
        { gateway: gap.gateway, began: when(gap.began), ended: gap.ended ? when(gap.ended) : "", seconds: seconds }, true);
      if (known) return;
      var after = null;
      for (var line = lines.firstElementChild; line; line = line.nextElementSibling) {
        if (line.record && Date.parse(line.record.stamp) > Date.parse(gap.began)) { after = line; break; }
      }
      lines.insertBefore(div, after);
    });
    if (followEl.checked) lines.scrollTop = lines.scrollHeight;
  }

  levelEl.addEventListener("change", refilter);
  regexEl.addEventListener("change", refilter);
  TEXT_FIELDS.forEach(function (field) { var el = q(field[1]); if (el) el.addEventListener("input", refilter); });
  downloadEl.addEventListener("click", downloadFiltered);
  // The filters apply in the page: Enter in a text field must not reload it.
  root.querySelector("form[data-local]").addEventListener("submit", function (event) { event.preventDefault(); });
  pauseEl.addEventListener("click", function () {
    paused = !paused;
    pauseEl.textContent = paused ? gettext("Resume") : gettext("Pause");
    pauseEl.setAttribute("aria-pressed", String(paused));
    if (!paused) {
      var backlog = held; held = []; heldDropped = 0;
      append(backlog);
    }
    status();
  });
  q("clear").addEventListener("click", function () { lines.textContent = ""; status(); });

  // Live stream, reconnecting with a growing delay; on reconnect, fetch what was missed.
  var delay = 500;
  function connect() {
    var url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + root.dataset.ws;
    var socket = new WebSocket(url);
    socket.onopen = function () {
      delay = 500;
      if (window.lifecycleBanner) window.lifecycleBanner(false);
      fetch(root.dataset.since + "?after=" + lastId, { credentials: "same-origin" })
        .then(function (r) { return r.ok ? r.json() : { records: [] }; })
        .then(function (body) { receive(body.records); });
    };
    socket.onmessage = function (event) {
      var data = JSON.parse(event.data);
      if (data.records) receive(data.records);
      if (data.gaps) addGaps(data.gaps);
      if ("gateway_online" in data) {
        var banner = document.getElementById("gateway-banner");
        if (banner && data.gateway_banner) banner.outerHTML = data.gateway_banner;
        else if (banner) banner.hidden = data.gateway_online;
      }
    };
    socket.onclose = function (event) {
      if (event.code === 4401 || event.code === 4404) {
        status(event.code === 4401 ? gettext("logged out: reload the page to log in") : gettext("no longer exists"));
        return;
      }
      if (window.lifecycleBanner) window.lifecycleBanner(true);
      setTimeout(connect, delay);
      delay = Math.min(delay * 2, 10000);
    };
  }

  // Opened at a moment (?at=, from the timeline): paused, so that live lines do not push it
  // away, and the first line from that moment on marked and in view.
  function showMoment() {
    var at = Date.parse(root.dataset.at);
    paused = true;
    followEl.checked = false;
    pauseEl.textContent = gettext("Resume");
    pauseEl.setAttribute("aria-pressed", "true");
    var line = lines.firstElementChild;
    while (line && Date.parse(line.record.stamp) < at) line = line.nextElementSibling;
    var marker = document.createElement("div");
    marker.className = "log-moment";
    marker.textContent = interpolate(gettext("▶ %(moment)s (the moment from the timeline)"),
      { moment: when(new Date(at).toISOString()) }, true);
    lines.insertBefore(marker, line);
    marker.scrollIntoView({ block: "center" });
    status();
  }

  append(JSON.parse(document.getElementById("log-history").textContent));
  if (root.dataset.at && !isNaN(Date.parse(root.dataset.at))) showMoment();
  addGaps(JSON.parse(document.getElementById("log-gaps").textContent));
  refilter();
  connect();
})();
