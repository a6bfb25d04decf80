// The live view: draws each snapshot the server streams (map, regions, alarms, turn clock).
"use strict";
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

function draw(snapshot) {
  document.getElementById("stale").hidden = !snapshot.stale;
  if (snapshot.status) showSource(snapshot);
  const status = document.getElementById("status");
  if (!snapshot.map) { status.textContent = snapshot.message || "no map yet"; return; }
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
    for (const text of [r.words || r.zone || "region " + r.id, r.peak_mmhg.toFixed(0), since.toFixed(0) + " min",
                        r.dose === null ? "-" : Math.round(100 * r.dose) + " %"]) {
      const td = document.createElement("td"); td.textContent = text; tr.appendChild(td);
    }
    tbody.appendChild(tr);
  }
  document.getElementById("peak").textContent = (snapshot.map.peak_kpa / 0.133322).toFixed(0);
  const patient = snapshot.patient;
  document.getElementById("patient").textContent = patient ? patient.patient_id + (patient.name ? ` (${patient.name})` : "")
                                                           : "not admitted";
  const posture = snapshot.posture_words || snapshot.posture || "-";
  document.getElementById("posture").textContent =
    snapshot.posture_sure === false ? `${posture} (kept: the latest map is unclear)` : posture;
  const turn = snapshot.turn || {};
  document.getElementById("turn").textContent = turn.turning_since_s == null ? clock(turn.due_in_s)
    : `${clock(turn.due_in_s)} (a turn is being held: counted once it lasts)`;
  const changed = document.getElementById("changed"), differing = snapshot.settings_changed || [];
  changed.hidden = !differing.length;
  changed.querySelector("strong").textContent = differing.map(s => s.text).join(", ");
  const alarms = document.getElementById("alarms");
  alarms.innerHTML = "";
  for (const a of snapshot.alarms || []) {
    const div = document.createElement("div");
    div.className = "alarm " + a.priority;
    div.textContent = `${a.priority.toUpperCase()}: ${a.message}` + (a.acknowledged_by ? ` (acknowledged by ${a.acknowledged_by})` : "") +
                      (a.delivery ? ` [${deliveryWords(a.delivery, snapshot.ward_link)}]` : "");
    alarms.appendChild(div);
  }
  const link = snapshot.ward_link;
  document.getElementById("ward-row").hidden = !link;
  if (link) document.getElementById("ward").textContent = wardWords(link);
  status.textContent = `bed ${snapshot.bed_id}, frame ${snapshot.sequence}, ${snapshot.status.faults} fault(s), ` +
                       `${Math.round(snapshot.age_s)} s old`;
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
