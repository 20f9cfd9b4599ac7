// The node page: after a transition started from its buttons (the keyboard, mostly), the
// keyboard stays there. Its buttons are disabled while the request runs and the state panel is
// redrawn by the answer and by live updates, so the browser drops the focus to the top of the
// page; it goes back to the same transition if it is offered again, else to the first one
// offered, else (a transition under way, or none possible) to the result until there is one.
(function () {
  "use strict";
  var used = null;  // {transition, at}: the button used last
  var PARKED = "transition-result";

  function restore() {
    if (!used || Date.now() - used.at > 60000) return;
    var active = document.activeElement;
    if (active && active !== document.body && active.id !== PARKED && !active.disabled) return;
    var group = document.querySelector("#node-state .transitions");
    var target = group && (group.querySelector("button[data-transition='" + used.transition + "']:not([disabled])") ||
                           group.querySelector("button:not([disabled])"));
    if (!target) target = document.getElementById(PARKED);
    if (target && target !== active) target.focus({ preventScroll: true });
  }
  document.addEventListener("htmx:beforeRequest", function (e) {
    var elt = e.detail.elt;
    if (elt && elt.closest && elt.closest("#node-state .transitions")) {
      used = { transition: elt.dataset.transition, at: Date.now() };
    }
  });
  // A click elsewhere means the user moved on: no focus is brought back then.
  document.addEventListener("pointerdown", function (e) {
    if (!e.target.closest || !e.target.closest("#node-state .transitions")) used = null;
  });
  ["htmx:afterRequest", "htmx:afterSwap", "htmx:oobAfterSwap", "htmx:wsAfterMessage"].forEach(function (name) {
    document.addEventListener(name, function () { setTimeout(restore, 0); });
  });
})();
