// Dangerous actions ask first, in the page's own dialog (templates/_confirm_dialog.html), not
// window.confirm: keyboard (it opens on Cancel, Esc cancels, Tab reaches the other button) and
// touch, under the Content-Security-Policy. A button says what to ask with data-confirm
// (the question), data-confirm-detail (what follows) and data-confirm-yes (the confirm button's
// words). htmx asks on the element that triggers a request: for a form that is the form, so
// the button used (the event's submitter) is read as well; hx-confirm on a submit button was
// never read, and a robot-wide Shut down ran at once.
(function () {
  "use strict";
  var pending = null;  // {source, elt, issue}: the request waiting for an answer
  var skipOnce = null;  // a redrawn button clicked again for a confirmed request

  // "all 5 nodes" of the robot whose section holds the button: the nodes a whole-robot run
  // goes through (every one but those watched and not seen yet), counted when asked, as rows
  // come and go live; a collapsed robot's from its counts by state.
  function robotNodes(el) {
    var section = el.closest("section.robot");
    // Translators: this and the next three texts fill {nodes} in the questions "Shut down {nodes} of
    // robot_1?", "Restart {nodes} of robot_1?" and "Reset {nodes} of robot_1 to unconfigured?" (the object
    // of the verb); where the question starts with {nodes}, the page puts a capital first.
    if (!section) return gettext("every node");
    var count;
    if (section.querySelector("tr.node-row")) {
      count = section.querySelectorAll("tr.node-row:not([data-status='waiting'])").length;
    } else {
      var summary = section.querySelector(".robot-summary");
      var waiting = summary && summary.querySelector("[data-count-status='waiting']");
      count = Number(summary ? summary.dataset.total : 0) - (waiting ? parseInt(waiting.textContent, 10) || 0 : 0);
    }
    if (count === 1) return gettext("the one node");
    if (count) return interpolate(ngettext("all %(count)s node", "all %(count)s nodes", count), { count: count }, true);
    return gettext("every node (none is known yet)");
  }

  // The question with {nodes} put in; where a language puts it first, it starts with a capital.
  function question(source) {
    var text = source.dataset.confirm;
    var nodes = robotNodes(source);
    if (text.indexOf("{nodes}") === 0) nodes = nodes.charAt(0).toUpperCase() + nodes.slice(1);
    return text.replace("{nodes}", nodes);
  }

  function dialog() { return document.getElementById("confirm-dialog"); }

  function ask(source, elt, issue) {
    var box = dialog();
    if (!box || typeof box.showModal !== "function") return false;  // no dialog: htmx sends as before
    pending = { source: source, elt: elt, issue: issue };
    box.querySelector("[data-confirm-question]").textContent = question(source);
    box.querySelector("[data-confirm-detail]").textContent = source.dataset.confirmDetail || "";
    box.querySelector("button[value=confirm]").textContent = source.dataset.confirmYes || gettext("Confirm");
    box.returnValue = "";
    box.showModal();
    box.querySelector("button[value=cancel]").focus();  // Enter right away is the safe answer
    return true;
  }

  // The same button after a live update redrew it (same row, same data-transition), or none.
  function redrawn(elt) {
    var row = elt.closest("[id]");
    var fresh = row && row.id && document.getElementById(row.id);
    var which = elt.dataset.transition;
    return fresh && which ? fresh.querySelector("button[data-transition='" + which + "']:not([disabled])") : null;
  }

  function answered() {
    var box = dialog(), request = pending;
    pending = null;
    if (!request) return;
    // Back to the button used (the browser may have put the focus elsewhere): the keyboard
    // goes on from there, and for a form htmx reads the button's name and value from it.
    if (request.source.isConnected) request.source.focus({ preventScroll: true });
    if (box.returnValue !== "confirm") return;
    if (request.elt.isConnected) { request.issue(true); return; }
    var again = redrawn(request.source);
    if (again) { skipOnce = again; again.click(); }
  }

  document.addEventListener("htmx:confirm", function (e) {
    if (skipOnce && e.detail.elt === skipOnce) { skipOnce = null; return; }
    var submitter = e.detail.triggeringEvent && e.detail.triggeringEvent.submitter;
    var source = submitter && submitter.dataset.confirm ? submitter : e.detail.elt;
    if (!source || !source.dataset || !source.dataset.confirm) return;
    if (ask(source, e.detail.elt, e.detail.issueRequest)) e.preventDefault();
  });

  document.addEventListener("DOMContentLoaded", function () {
    var box = dialog();
    if (box) box.addEventListener("close", answered);  // a button, Esc, or the form's submit
  });
})();
