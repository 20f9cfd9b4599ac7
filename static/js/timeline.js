// State timeline: a tap (or click, or Enter on a mark) shows what a bar or a mark stands for
// under the drawing, not only in the tooltip a mouse gets. A bar: its state, times and length,
// with links to the node's log at its start and to the audit records of that stretch. A mark:
// its line of the list of events (the node's reason, its audit record, the log of that moment).
// Without this script a mark still links to its line of the list.
(function () {
  "use strict";
  var figure = document.querySelector("figure.timeline[data-start]");
  var panel = document.getElementById("tl-detail");
  if (!figure || !panel) return;
  var body = panel.querySelector(".tl-detail-body");
  var start = Date.parse(figure.dataset.start);
  var shown = null;

  function iso(ms) { return new Date(ms).toISOString().slice(0, 19); }

  function element(tag, text) {
    var made = document.createElement(tag);
    if (text) made.textContent = text;
    return made;
  }

  function link(text, href) {
    var a = element("a", text);
    a.href = href;
    return a;
  }

  function show(source, parts) {
    if (shown) shown.classList.remove("tl-selected");
    shown = source;
    source.classList.add("tl-selected");
    body.replaceChildren.apply(body, parts);
    panel.hidden = false;
    panel.focus({ preventScroll: true });
    panel.scrollIntoView({ block: "nearest" });
  }

  function close() {
    panel.hidden = true;
    if (shown) shown.classList.remove("tl-selected");
    shown = null;
  }

  function barDetails(bar) {
    var lane = bar.closest(".tl-lane");
    var from = start + 1000 * Number(bar.dataset.s), to = start + 1000 * Number(bar.dataset.e);
    var links = element("p");
    links.append(link(gettext("the log at its start"), lane.dataset.logs + "?at=" + iso(from) + "Z"), " · ",
      link(gettext("audit records of this stretch"), lane.dataset.audit + "&since=" + iso(from) + "&until=" + iso(to + 1000)));
    return [element("p", bar.querySelector("title").textContent), links];
  }

  // A mark's line of the list, as label: value pairs (its cells say what they are).
  function markDetails(row) {
    var list = element("dl");
    Array.prototype.forEach.call(row.cells, function (cell) {
      list.append(element("dt", cell.dataset.label));
      var value = element("dd");
      Array.prototype.forEach.call(cell.childNodes, function (child) { value.append(child.cloneNode(true)); });
      list.append(value);
    });
    return [list];
  }

  figure.addEventListener("click", function (event) {
    var mark = event.target.closest("a.tl-mark, a.tl-outage");
    if (mark) {
      var row = document.getElementById(mark.getAttribute("href").slice(1));
      if (!row) return;
      event.preventDefault();
      show(mark, markDetails(row));
      return;
    }
    var bar = event.target.closest(".tl-bar");
    if (bar) show(bar, barDetails(bar));
  });
  panel.querySelector(".tl-detail-close").addEventListener("click", close);
  document.addEventListener("keydown", function (event) {
    if (event.key === "Escape" && !panel.hidden) close();
  });
})();
