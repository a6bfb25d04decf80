// The live view: draws each snapshot the server streams (map, regions, alarms, turn clock), and lets the nurse
// acknowledge an alarm or pause its sound from here. Times are shown as the site time zone's clock time (the
// page names it): the monitor's own time (time_s) is turned into wall time through the snapshot's written_at.
"use strict";
const TURN_SOON_S = 30 * 60;        // the turn clock is amber from this long before the turn is due, red once overdue
const RANK = {low: 1, medium: 2, high: 3};
const MARKS = {high: "!!!", medium: "!!", low: "!"};     // the priority also in text, not only in colour
const sent = {};                    // alarm id -> what was sent for it and not yet shown by the monitor
const sound = new AlarmSound();
// The scale pressure-mapping nurses know: white where nothing presses, blue to green below the alarm threshold,
// yellow at it, through orange to dark red at 100 mmHg and above.
const STOPS = [[0, [255, 255, 255]], [10, [158, 202, 225]], [25, [49, 163, 84]], [32, [255, 217, 47]],
               [60, [244, 109, 67]], [100, [165, 0, 38]]];
const FULL_SCALE = STOPS[STOPS.length - 1][0];

function colour(mmhg) {
  if (mmhg === null) return "#bbbbbb";
  const v = Math.max(0, Math.min(FULL_SCALE, mmhg));
  let k = 1;
  while (STOPS[k][0] < v) k++;
  const [v0, c0] = STOPS[k - 1], [v1, c1] = STOPS[k], t = (v - v0) / (v1 - v0);
  const [r, g, b] = c0.map((c, i) => Math.round(c + t * (c1[i] - c)));
  return `rgb(${r},${g},${b})`;
}

function showSource(snapshot) {
  const banner = document.getElementById("simulated");
  const text = JSON.parse(banner.dataset.texts)[(snapshot.status || {}).source];
  banner.hidden = !text;
  banner.textContent = text || "";
}

// The words at the map's four edges. Wide mats lie along x with the head at x = 0 and the patient's left at +y,
// drawn downwards; a mat longer in y has its head at the top and the patient's left at +x (appliance.alerts.anatomy).
function mapSides(map) {
  const rows = map.mmhg.length, cols = map.mmhg[0].length, [pw, ph] = map.pixel_mm;
  return cols * pw > rows * ph ? {top: "patient's RIGHT", bottom: "patient's LEFT", left: "HEAD", right: "FEET"}
                               : {top: "HEAD", bottom: "FEET", left: "patient's RIGHT", right: "patient's LEFT"};
}

// "ok" (green), "soon" (amber: due within TURN_SOON_S, or due now) or "overdue" (red); "" without a turn clock.
function turnState(dueInS) {
  if (dueInS === null || dueInS === undefined) return "";
  return dueInS < 0 ? "overdue" : dueInS <= TURN_SOON_S ? "soon" : "ok";
}

// Hours and minutes in the site's time zone (an IANA name the server puts on the page) with its abbreviation, so
// the hour repeated when the clocks go back reads apart; as the screen's locale writes them.
const CLOCK = {hour: "2-digit", minute: "2-digit", timeZoneName: "short",
               timeZone: document.getElementById("live").dataset.timeZone};

// The wall-clock time of the monitor time t (s) in the site's zone.
function clockTime(snapshot, t, seconds = false) {
  const at = new Date((snapshot.written_at - (snapshot.time_s - t)) * 1000);
  return at.toLocaleTimeString([], seconds ? {...CLOCK, second: "2-digit"} : CLOCK);
}

// The priority to sound: the highest of the alarms neither acknowledged nor paused (nor just acknowledged here),
// and a medium technical alarm while the data is stale.
function soundFor(snapshot) {
  let loud = (snapshot.alarms || []).filter(a => !a.acknowledged_by && !a.audio_paused && !sent[a.alarm_id]);
  if ("audible" in snapshot && snapshot.audible === null) loud = [];        // the monitor's pause of every alarm
  if (snapshot.stale) loud.push({priority: "medium"});
  return loud.reduce((best, a) => (!best || RANK[a.priority] > RANK[best] ? a.priority : best), null);
}

function draw(snapshot) {
  document.getElementById("stale").hidden = !snapshot.stale;
  if (snapshot.status) showSource(snapshot);
  showAlarms(snapshot);
  sound.set(soundFor(snapshot));
  const status = document.getElementById("status");
  showStarting(snapshot.starting);
  if (!snapshot.map) { status.textContent = snapshot.message || "no map yet"; return; }
  const sides = mapSides(snapshot.map);
  for (const side of Object.keys(sides)) document.getElementById("side-" + side).textContent = sides[side];
  const rows = snapshot.map.mmhg, canvas = document.getElementById("map"), ctx = canvas.getContext("2d");
  const [pw, ph] = snapshot.map.pixel_mm;
  const height = Math.round(canvas.width * rows.length * ph / (rows[0].length * pw));   // the mat's own shape
  if (canvas.height !== height) canvas.height = height;
  const w = canvas.width / rows[0].length, h = canvas.height / rows.length;
  rows.forEach((row, i) => row.forEach((v, j) => { ctx.fillStyle = colour(v); ctx.fillRect(j * w, i * h, w + 1, h + 1); }));
  ctx.strokeStyle = "#111"; ctx.lineWidth = 2; ctx.setLineDash([6, 4]);
  const tbody = document.querySelector("#regions tbody");
  tbody.innerHTML = "";
  for (const r of snapshot.regions || []) {
    ctx.beginPath();
    ctx.arc(r.x_mm / pw * w, r.y_mm / ph * h, Math.max(w, Math.sqrt(r.area_cm2 * 100 / Math.PI) / pw * w), 0, 2 * Math.PI);
    ctx.stroke();
    const tr = document.createElement("tr");
    const since = (snapshot.time_s - r.since_s) / 60;
    for (const text of [r.words || r.zone || "region " + r.id, r.peak_mmhg.toFixed(0),
                        `${since.toFixed(0)} min (since ${clockTime(snapshot, r.since_s)})`,
                        r.dose === null ? "-" : Math.round(100 * r.dose) + " %"]) {
      const td = document.createElement("td"); td.textContent = text; tr.appendChild(td);
    }
    tbody.appendChild(tr);
  }
  document.getElementById("peak").textContent = (snapshot.map.peak_kpa / 0.133322).toFixed(0);
  const patient = snapshot.patient;
  document.getElementById("patient").textContent = patient ? patient.patient_id + (patient.name ? ` (${patient.name})` : "")
                                                           : "not admitted";
  showHeaderPatient(patient);
  const posture = snapshot.posture_words || snapshot.posture || "-";
  document.getElementById("posture").textContent =
    snapshot.posture_sure === false ? `${posture} (kept: the latest map is unclear)` : posture;
  const turn = snapshot.turn || {}, turnClock = document.getElementById("turn");
  turnClock.textContent = turn.turning_since_s == null ? clock(turn.due_in_s)
    : `${clock(turn.due_in_s)} (a turn is being held: counted once it lasts)`;
  turnClock.className = "turn-clock " + turnState(turn.due_in_s);
  document.getElementById("turn-at").textContent =
    turn.due_in_s == null ? "" : `(at ${clockTime(snapshot, snapshot.time_s + turn.due_in_s)})`;
  const changed = document.getElementById("changed"), differing = snapshot.settings_changed || [];
  changed.hidden = !differing.length;
  changed.querySelector("strong").textContent = differing.map(s => s.text).join(", ");
  const link = snapshot.ward_link;
  document.getElementById("ward-row").hidden = !link;
  if (link) document.getElementById("ward").textContent = wardWords(link);
  status.textContent = `bed ${snapshot.bed_id}, frame ${snapshot.sequence}, ${snapshot.status.faults} fault(s), ` +
                       `updated ${clockTime(snapshot, snapshot.time_s, true)} (${Math.round(snapshot.age_s)} s ago)`;
}

// The header's patient, as the server writes it on every page, kept current here: a screen left on the live view
// must not go on naming a patient discharged (or not yet naming one admitted) since it was loaded.
function showHeaderPatient(patient) {
  const header = document.getElementById("header-patient");
  if (!header) return;
  if (!patient) { header.textContent = "No patient admitted"; return; }
  const name = document.createElement("strong");
  name.textContent = patient.name || "";
  header.replaceChildren("Patient ", name, ` ${patient.patient_id}`);
}

// The start-up's progress bar and phase in words, shown until the first map replaces the start-up snapshot.
function showStarting(starting) {
  document.getElementById("starting").hidden = !starting;
  if (!starting) return;
  document.getElementById("starting-bar").value = starting.share;
  document.getElementById("starting-phase").textContent =
    `${starting.phase}${starting.step ? ": " + starting.step : ""} (${Math.round(100 * starting.share)} %)`;
}

// One row per open alarm: its priority in colour, flash rate and text, patient or equipment, and its controls.
// Redrawn only when something in it changed, so a finger on a button is not lost to a redraw.
function showAlarms(snapshot) {
  const list = document.getElementById("alarms"), alarms = snapshot.alarms || [];
  for (const id of Object.keys(sent)) {
    const a = alarms.find(x => String(x.alarm_id) === id);
    if (!a || (sent[id] === "acknowledge" ? a.acknowledged_by : a.audio_paused)) delete sent[id];
  }
  const shown = JSON.stringify([alarms, sent, snapshot.ward_link]);
  if (list.dataset.shown === shown) return;
  list.dataset.shown = shown;
  list.innerHTML = "";
  for (const a of alarms) {
    const div = document.createElement("div"), words = document.createElement("span");
    div.className = `alarm ${a.priority} ${a.category}` + (a.acknowledged_by ? " acknowledged" : "");
    div.dataset.alarmId = a.alarm_id;
    const tag = document.createElement("span");
    tag.className = "tag";
    tag.textContent = a.category === "technical" ? "\u2699 EQUIPMENT" : "PATIENT";
    words.textContent = `${MARKS[a.priority]} ${a.priority.toUpperCase()}: ${a.message} (since ` +
                        `${clockTime(snapshot, a.raised_s)})` +
                        (a.acknowledged_by ? `, acknowledged by ${a.acknowledged_by}` : "") +
                        (a.audio_paused ? ", sound paused" : "") +
                        (a.delivery ? ` [${deliveryWords(a.delivery, snapshot.ward_link)}]` : "");
    div.append(tag, words);
    if (sent[a.alarm_id]) {
      const note = document.createElement("em");
      note.textContent = sent[a.alarm_id] === "acknowledge" ? "acknowledgement sent" : "sound pause sent";
      div.appendChild(note);
    } else if (!a.acknowledged_by) {
      div.appendChild(button("Acknowledge", "ack", () =>
        post(`/alarms/${a.alarm_id}/acknowledge`, {}, a.alarm_id, "acknowledge")));
      const minutes = list.dataset.maxPauseMin;
      if (!a.audio_paused) div.appendChild(button(`Pause sound ${minutes} min`, "pause", () =>
        post("/alarms/pause-audio", {alarm_id: a.alarm_id, minutes}, a.alarm_id, "pause")));
    }
    list.appendChild(div);
  }
}

function button(label, className, action) {
  const b = document.createElement("button");
  b.type = "button"; b.className = className; b.textContent = label;
  b.addEventListener("click", action);
  return b;
}

// A form POST with the page's CSRF token (its meta tag); the server's answer is shown under the alarms.
function post(url, fields, alarmId, what) {
  const answer = document.getElementById("alarm-answer");
  const token = document.querySelector('meta[name="csrf-token"]').content;
  return fetch(url, {method: "POST", body: new URLSearchParams(fields), credentials: "same-origin",
                     headers: {"X-CSRF-Token": token, "Accept": "application/json"}})
    .then(r => (r.headers.get("Content-Type") || "").includes("json") ? r.json().then(j => [r.ok, j.message])
                                                                      : [false, `refused (HTTP ${r.status})`])
    .then(([ok, message]) => {
      answer.textContent = message;
      if (ok) { sent[alarmId] = what; fetch("/api/live").then(r => r.json()).then(draw); }
    })
    .catch(() => { answer.textContent = "not sent: the screen cannot reach the monitor; try again"; });
}

function soundOn() {
  sound.enable().then(() => {
    document.getElementById("sound-on").hidden = true;
    document.getElementById("sound-state").textContent = "Alarm sound on.";
  });
}

// How far an alarm's latest change got (the snapshot's "delivery"); without confirmation the broker's receipt is all.
function deliveryWords(delivery, link) {
  if (delivery === "broker") return link && !link.confirming ? "sent to the ward" : "sent, not yet confirmed by the ward";
  return delivery === "bed" ? "at this bed only" : "shown at the ward station";
}

function wardWords(link) {
  if (!link.connected) return "not connected: alarms are shown only at this bed";
  if (link.unconfirmed) return `${link.unconfirmed} alarm change(s) awaiting the ward's confirmation`;
  return link.confirming ? "connected, every alarm confirmed" : "connected (the broker's receipt counts as delivery)";
}

function scale() {
  const c = document.getElementById("scale"), ctx = c.getContext("2d");
  for (let x = 0; x < c.width; x++) { ctx.fillStyle = colour(x / c.width * FULL_SCALE); ctx.fillRect(x, 0, 1, c.height); }
}

scale();
document.getElementById("sound-on").addEventListener("click", soundOn);
fetch("/api/live").then(r => r.json()).then(draw);
const REFUSED_RETRY_MS = 10000;     // the server's Retry-After when all its live streams are taken

function listen() {
  const source = new EventSource("/api/live/stream");
  source.onmessage = event => draw(JSON.parse(event.data));
  source.onerror = () => {
    document.getElementById("status").textContent = "connection lost: retrying...";
    // The browser retries a stream that ended by itself; one refused (503) is closed for good, so ask again later.
    if (source.readyState === EventSource.CLOSED) setTimeout(listen, REFUSED_RETRY_MS);
  };
}

listen();
setInterval(() => fetch("/api/live").then(r => r.json()).then(s => { if (s.stale) draw(s); }), 5000);
