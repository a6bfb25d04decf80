// The ward: one tile per bed, in the station's order (alarming beds first, then the offline ones); with the hospital
// history, each tile's peak pressure over the last hours and the ward's events of that time below the tiles.
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
let lastWard = null;        // the board as last pushed, drawn again when the history arrives
let wardHistory = null;     // the latest answer of /api/ward/history, null until one came
let historyTop = 1;         // the sparklines' common scale: the ward's highest peak in the look-back, mmHg

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
  if (wardHistory && wardHistory.available) div.appendChild(trend(wardHistory.trends[bed.bed_id] || []));
  if (canAct) {
    div.appendChild(button("Record turn", `/ward/${encodeURIComponent(bed.bed_id)}/turn`, `Record a turn at bed ${bed.bed_id}`));
    for (const c of bed.commands) div.appendChild(commandLine(c));
  }
  return div;
}

// A notification service whose pages are not going out, or that has not said for too long whether they do: the
// nurses must not count on the phones.
function pagingLine(service) {
  const since = service.since === null ? "" : ` since ${timeOfDay(service.since)}`;
  const words = service.state === "not delivering"
    ? `Paging (${service.notifier}) not delivering${since}: call nurses directly`
      + (service.reason ? ` (${service.reason})` : "")
    : `Paging (${service.notifier}) unknown: no word from it${since}; pages may not be going out: call nurses directly`;
  return element("p", "paging " + service.state.replace(" ", "-"), words);
}

function draw(ward) {
  lastWard = ward;
  document.getElementById("lost").hidden = true;
  document.getElementById("broker").hidden = ward.connected;
  const failing = (ward.paging || []).filter(s => s.state !== "delivering");
  const paging = document.getElementById("paging");
  paging.replaceChildren(...failing.map(pagingLine));
  paging.hidden = failing.length === 0;
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

// The hospital history: each bed's highest peak per minute and the ward's events over the look-back, polled as
// often as the station reads it; only on a station that has one (the page then has a #history section).
const SVG = "http://www.w3.org/2000/svg";
const SPARK_W = 200, SPARK_H = 32;
const GAP_S = 90;           // minutes further apart than this were not heard: the line breaks there

function hours() {
  return `${wardHistory.look_back_h} h`;
}

function highestPeak(points) {
  return points.reduce((top, [, peak]) => peak === null || (top !== null && top >= peak) ? top : peak, null);
}

function trend(points) {
  const p = element("p", "trend");
  const highest = highestPeak(points);
  if (highest === null) {
    p.textContent = `no pressure in the history for the last ${hours()}`;
    return p;
  }
  const svg = document.createElementNS(SVG, "svg");
  svg.setAttribute("class", "sparkline");
  svg.setAttribute("viewBox", `0 0 ${SPARK_W} ${SPARK_H}`);
  svg.setAttribute("preserveAspectRatio", "none");
  svg.setAttribute("role", "img");
  const words = `highest peak pressure per minute over the last ${hours()}: up to ${highest.toFixed(0)} mmHg`;
  svg.setAttribute("aria-label", words);
  const title = document.createElementNS(SVG, "title");
  title.textContent = words;
  svg.appendChild(title);
  const span = wardHistory.read_at - wardHistory.since;
  let d = "", pen = "M", last = null;
  for (const [t, peak] of points) {
    if (last !== null && t - last > GAP_S) pen = "M";
    last = t;
    if (peak === null) { pen = "M"; continue; }            // a minute without a map
    const x = (t - wardHistory.since) / span * SPARK_W, y = SPARK_H - 1 - peak / historyTop * (SPARK_H - 2);
    d += `${pen}${x.toFixed(1)},${y.toFixed(1)}` + (pen === "M" ? "h0" : "");   // a lone minute: a dot
    pen = "L";
  }
  const line = document.createElementNS(SVG, "path");
  line.setAttribute("d", d);
  svg.appendChild(line);
  p.appendChild(svg);
  p.appendChild(element("span", "trend-words", `${hours()}: up to ${highest.toFixed(0)} mmHg`));
  return p;
}

function timeOfDay(s) {
  return new Date(s * 1000).toLocaleTimeString([], {hour: "2-digit", minute: "2-digit"});
}

function historyLine(e) {
  // classes of their own: a past alarm must not look like a live one (the page's .alarm.high flashes)
  const li = element("li", "past-" + e.type + (e.priority ? " priority-" + e.priority : ""));
  const when = element("time", null, timeOfDay(e.stored_at));
  when.dateTime = new Date(e.stored_at * 1000).toISOString();
  // an alarm's words stay the same from raised to ended: its kind says what happened; a turn's words say it all
  const what = e.type === "alarm"
    ? `alarm ${e.kind}` + (e.priority ? ` (${e.priority})` : "") + (e.message ? `: ${e.message}` : "")
    : e.message || `${e.type} ${e.kind}`;
  li.append(when, ` ${e.bed_id}: ${what}`);
  return li;
}

function drawHistory(answer, refreshS) {
  wardHistory = answer;
  historyTop = Object.values(answer.trends).reduce((top, points) => Math.max(top, highestPeak(points) || 0), 1);
  const state = document.getElementById("history-state");
  state.className = "history-state" + (answer.available ? "" : " unavailable");
  state.textContent = !answer.available
    ? `The hospital history is unavailable (its database does not answer): trying again in ${refreshS} s.`
    : answer.events_cut ? `the newest ${answer.events.length} events, newest first (older ones of the last ${hours()} `
      + "are in the hospital history, not listed here)"
    : answer.events.length ? `${answer.events.length} event(s), newest first` : "no events in this time";
  document.getElementById("history-events").replaceChildren(...answer.events.map(historyLine));
  if (lastWard) draw(lastWard);
}

function pollHistory(refreshS) {
  fetch("/api/ward/history", {headers: {"Accept": "application/json"}})
    .then(r => { if (!r.ok) throw new Error(`answered ${r.status}`); return r.json(); })
    .then(answer => drawHistory(answer, refreshS))
    .catch(() => drawHistory({available: false, trends: {}, events: []}, refreshS))
    .finally(() => setTimeout(() => pollHistory(refreshS), refreshS * 1000));
}

const historySection = document.getElementById("history");
if (historySection) pollHistory(Math.max(1, Number(historySection.dataset.refreshS)));
