// Log console: live /rosout lines over a WebSocket (JSON), with a bounded number of lines
// in the page, level and text filters, pause/resume, clear, follow-tail and download.
(function () {
  "use strict";
  var MAX_LINES = 1000;       // lines kept in the page; older ones drop off
  var MAX_PAUSED = 5000;      // lines held back while paused
  var LEVELS = { DEBUG: 10, INFO: 20, WARN: 30, ERROR: 40, FATAL: 50 };

  var root = document.getElementById("log-console");
  if (!root) return;
  var q = function (name) { return root.querySelector('[data-log="' + name + '"]'); };
  var lines = q("lines"), levelEl = q("level"), textEl = q("text"), pauseEl = q("pause"),
      followEl = q("follow"), statusEl = q("status"), downloadEl = q("download");
  var downloadBase = downloadEl.getAttribute("href");
  var paused = false, held = [], heldDropped = 0, lastId = 0, received = 0;

  function visible(record) {
    var text = textEl.value.trim().toLowerCase();
    return LEVELS[record.level] >= LEVELS[levelEl.value] &&
      (!text || (record.message + " " + record.logger).toLowerCase().indexOf(text) !== -1);
  }

  function lineFor(record) {
    var div = document.createElement("div");
    div.className = "log-line level-" + record.level.toLowerCase();
    div.dataset.level = record.level;
    div.dataset.text = (record.message + " " + record.logger).toLowerCase();
    var time = record.stamp.slice(11, 23);
    [[time, "t"], [record.level, "lvl"], [record.logger, "logger"], [record.message, "msg"]].forEach(function (part) {
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
      received += 1;
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
    var parts = [lines.childElementCount + " lines shown (max " + MAX_LINES + ")"];
    if (paused) parts.push("paused, " + held.length + " waiting" + (heldDropped ? ", " + heldDropped + " dropped" : ""));
    if (extra) parts.push(extra);
    statusEl.textContent = parts.join(" · ");
  }

  function refilter() {
    Array.prototype.forEach.call(lines.children, function (div) {
      var text = textEl.value.trim().toLowerCase();
      div.hidden = LEVELS[div.dataset.level] < LEVELS[levelEl.value] || (!!text && div.dataset.text.indexOf(text) === -1);
    });
    var params = new URLSearchParams({ level: levelEl.value });
    if (textEl.value.trim()) params.set("q", textEl.value.trim());
    downloadEl.setAttribute("href", downloadBase + "?" + params.toString());
  }

  levelEl.addEventListener("change", refilter);
  textEl.addEventListener("input", refilter);
  // The filters apply in the page: Enter in the text field must not reload it.
  root.querySelector("form[data-local]").addEventListener("submit", function (event) { event.preventDefault(); });
  pauseEl.addEventListener("click", function () {
    paused = !paused;
    pauseEl.textContent = paused ? "Resume" : "Pause";
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
      if ("gateway_online" in data) {
        var banner = document.getElementById("gateway-banner");
        if (banner && data.gateway_banner) banner.outerHTML = data.gateway_banner;
        else if (banner) banner.hidden = data.gateway_online;
      }
    };
    socket.onclose = function (event) {
      if (event.code === 4401 || event.code === 4404) {
        status(event.code === 4401 ? "logged out: reload the page to log in" : "no longer exists");
        return;
      }
      if (window.lifecycleBanner) window.lifecycleBanner(true);
      setTimeout(connect, delay);
      delay = Math.min(delay * 2, 10000);
    };
  }

  append(JSON.parse(document.getElementById("log-history").textContent));
  refilter();
  connect();
})();
