// The ward: one tile per bed, in the station's order (alarming beds first, then the offline ones).
"use strict";

function element(tag, className, text) {
  const e = document.createElement(tag);
  if (className) e.className = className;
  if (text !== undefined) e.textContent = text;
  return e;
}

const COMMAND_WORDS = {"acknowledge": "Acknowledge", "record-turn": "Record turn"};
const STATE_WORDS = {"pending": "pending", "done": "done", "refused": "refused", "expired": "expired"};
let canAct = false;

// A nurse's command to a bed: posted with the session's CSRF token; the stream shows it pending, then done.
function act(button, path) {
  button.disabled = true;
  const token = document.querySelector('meta[name="csrf-token"]').content;
  fetch(path, {method: "POST", headers: {"Accept": "application/json", "X-CSRF-Token": token}})
    .then(r => r.json().then(body => ({ok: r.ok, body})))
    .then(({ok, body}) => say(body.message, ok))
    .catch(() => say("not sent: no connection to the station", false))
    .finally(() => { button.disabled = false; });
}

function say(message, ok) {
  const p = document.getElementById("said");
  p.textContent = message;
  p.className = "flash " + (ok ? "info" : "error");
  p.hidden = false;
}

function button(text, path, label) {
  const b = element("button", "act", text);
  b.type = "button";
  b.setAttribute("aria-label", label);
  b.addEventListener("click", () => act(b, path));
  return b;
}

function commandLine(c) {
  const what = COMMAND_WORDS[c.kind] + (c.kind === "acknowledge" ? ` alarm ${c.args.alarm_id}` : "");
  const state = STATE_WORDS[c.state] + (c.state === "pending" ? "..." : "") + (c.result && c.state !== "done" ? `: ${c.result}` : "");
  const p = element("p", "command " + c.state, `${what} by ${c.user}: ${state}`);
  p.dataset.command = c.id;
  return p;
}

// What a notification service did with the alarm's latest change: paged to the phones, or refused by their gateway.
function pageLine(page) {
  const at = new Date(page.notified_at * 1000).toLocaleTimeString([], {hour: "2-digit", minute: "2-digit"});
  const words = page.outcome === "paged" ? `paged (${page.notifier}) at ${at}`
                                         : `page refused (${page.notifier}, HTTP ${page.status}) at ${at}`;
  return element("span", "page " + page.outcome, words);
}

function tile(bed) {
  const div = element("article", "bed " + (!bed.online ? "offline" : bed.highest_priority || "quiet"));
  div.dataset.bed = bed.bed_id;
  const title = element("h2", null, bed.bed_id);
  if (bed.screen_url) {
    const a = element("a", null, "Open screen");
    a.href = bed.screen_url; a.target = "_blank"; a.rel = "noopener";
    title.appendChild(a);
  }
  div.appendChild(title);
  if (bed.simulated) div.appendChild(element("p", "simulated", bed.simulated));
  if (!bed.online) {
    const heard = bed.heard_s_ago === null ? "never heard" : `last heard ${Math.round(bed.heard_s_ago)} s ago`;
    div.appendChild(element("p", "offline-note", `OFFLINE (${bed.status === "offline" ? "monitor stopped" : "silent"}, ${heard})`));
  }
  for (const a of bed.alarms) {
    const text = `${(a.priority || "?").toUpperCase()}: ${a.message}` +
                 (a.acknowledged_by ? ` (acknowledged by ${a.acknowledged_by})` : "");
    const p = element("p", "alarm " + a.priority, text);
    p.dataset.alarm = a.alarm_id;
    for (const page of a.pages || []) p.appendChild(pageLine(page));
    if (canAct && !a.acknowledged_by) {
      p.appendChild(button("Acknowledge", `/ward/${encodeURIComponent(bed.bed_id)}/alarms/${a.alarm_id}/acknowledge`,
                           `Acknowledge alarm ${a.alarm_id} at bed ${bed.bed_id}`));
    }
    div.appendChild(p);
  }
  const facts = element("p", "facts");
  facts.append(`Peak ${bed.peak_mmhg === null || bed.peak_mmhg === undefined ? "-" : bed.peak_mmhg.toFixed(0)} mmHg · turn `);
  const turn = element("span", bed.turn_due_in_s !== null && bed.turn_due_in_s < 0 ? "overdue" : null, clock(bed.turn_due_in_s));
  facts.appendChild(turn);
  div.appendChild(facts);
  if (bed.regions.length) {
    div.appendChild(element("p", "facts", bed.regions.map(r => `${r.words || r.zone || "region"} ${Math.round(100 * (r.dose || 0))} %`).join(" · ")));
  }
  if (canAct) {
    div.appendChild(button("Record turn", `/ward/${encodeURIComponent(bed.bed_id)}/turn`, `Record a turn at bed ${bed.bed_id}`));
    for (const c of bed.commands) div.appendChild(commandLine(c));
  }
  return div;
}

function draw(ward) {
  document.getElementById("lost").hidden = true;
  document.getElementById("broker").hidden = ward.connected;
  canAct = ward.can_act;
  const c = ward.counts;
  document.getElementById("counts").textContent =
    `${c.beds} bed(s): ${c.alarming} with alarms, ${c.offline} offline`;
  document.getElementById("beds").replaceChildren(...ward.beds.map(tile));
}

fetch("/api/ward").then(r => r.json()).then(draw);
const REFUSED_RETRY_MS = 10000;     // the server's Retry-After when all its live streams are taken

function listen() {
  const source = new EventSource("/api/ward/stream");
  source.onmessage = event => draw(JSON.parse(event.data));
  source.onerror = () => {
    document.getElementById("lost").hidden = false;
    // The browser retries a stream that ended by itself; one refused (503) is closed for good, so ask again later.
    if (source.readyState === EventSource.CLOSED) setTimeout(listen, REFUSED_RETRY_MS);
  };
}

listen();
