// The engineering page: queues each task without leaving the page, follows its progress, draws readings.
"use strict";
const POLL_MS = 1000;

function csrf() {
  return document.querySelector('input[name="csrf_token"]').value;
}

function taskRow(command) {
  const tbody = document.querySelector("#tasks tbody");
  let row = tbody.querySelector(`tr[data-command="${command.id}"]`);
  if (!row) {
    row = document.createElement("tr");
    row.dataset.command = command.id;
    row.innerHTML = "<td></td><td></td><td></td><td></td><td class=\"state\"></td>" +
                    "<td><progress max=\"1\" value=\"0\"></progress> <span class=\"note\"></span></td>" +
                    "<td><pre class=\"result\"></pre></td>";
    const cells = row.querySelectorAll("td");
    cells[0].textContent = command.id;
    cells[1].textContent = command.kind;
    cells[2].textContent = JSON.stringify(command.args);
    cells[3].textContent = command.user || "";
    tbody.prepend(row);
  }
  return row;
}

function show(command) {
  const row = taskRow(command);
  row.dataset.state = command.state;
  row.querySelector(".state").textContent = command.state;
  row.querySelector("progress").value = command.state === "done" ? 1 : (command.progress || 0);
  row.querySelector(".note").textContent = command.progress_note || "";
  row.querySelector(".result").textContent = command.result || "";
}

async function follow(id) {
  for (;;) {
    const answer = await fetch(`/api/commands/${id}`, {headers: {"Accept": "application/json"}});
    if (!answer.ok) return;
    const command = await answer.json();
    show(command);
    if (command.state !== "pending") { finished(command); return; }
    await new Promise(resolve => setTimeout(resolve, POLL_MS));
  }
}

function finished(command) {
  if (command.state !== "done") return;
  refreshFiles();
  let result = {};
  try { result = JSON.parse(command.result); } catch (e) { return; }
  const newest = result.file || (result.files && result.files[result.files.length - 1]);
  if (newest && newest.endsWith(".csv")) drawReadings(newest);
}

async function submit(event) {
  event.preventDefault();
  const form = event.target;
  const answer = await fetch(form.action, {method: "POST", body: new FormData(form),
                                           headers: {"Accept": "application/json", "X-CSRF-Token": csrf()}});
  const body = await answer.json();
  if (!answer.ok) { alert(body.error || `refused (${answer.status})`); return; }
  show({id: body.command_id, kind: body.task, args: body.args, state: "pending", progress: 0});
  follow(body.command_id);
}

async function refreshFiles() {
  const answer = await fetch("/api/engineering/files", {headers: {"Accept": "application/json"}});
  if (!answer.ok) return;
  const listed = await answer.json();
  const tbody = document.querySelector("#files tbody");
  tbody.innerHTML = "";
  const readings = document.getElementById("readings-file"), chosen = readings.value;
  readings.innerHTML = "";
  const calibrations = document.querySelector('form[data-task="load"] select[name="file"]');
  calibrations.innerHTML = "";
  for (const f of listed) {
    const tr = document.createElement("tr"), a = document.createElement("a"), size = document.createElement("td");
    a.href = `/engineering/files/${encodeURIComponent(f.name)}`;
    a.textContent = f.name;
    const td = document.createElement("td"); td.appendChild(a); tr.appendChild(td);
    size.textContent = `${f.bytes} B`; tr.appendChild(size);
    tbody.appendChild(tr);
    if (f.readings) readings.add(new Option(f.name, f.name, false, f.name === chosen));
    if (f.name.endsWith(".json")) calibrations.add(new Option(f.name, f.name));
  }
}

async function drawReadings(name) {
  const status = document.getElementById("readings-status");
  const answer = await fetch(`/api/engineering/readings/${encodeURIComponent(name)}`);
  const data = await answer.json();
  if (!answer.ok) { status.textContent = data.error; return; }
  document.getElementById("readings-file").value = name;
  const canvas = document.getElementById("readings"), ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const gap = 6, top = 10, bottom = 22;
  const bars = data.readings + gap * (data.groups.length - 1);
  const w = canvas.width / Math.max(bars, 1);
  const high = Math.max(Math.abs(data.min_volts || 0), Math.abs(data.max_volts || 0)) || 1;
  const negative = (data.min_volts || 0) < 0;
  const zero = negative ? top + (canvas.height - top - bottom) / 2 : canvas.height - bottom;
  const scale = (negative ? (canvas.height - top - bottom) / 2 : canvas.height - top - bottom) / high;
  ctx.strokeStyle = "#999"; ctx.beginPath(); ctx.moveTo(0, zero); ctx.lineTo(canvas.width, zero); ctx.stroke();
  ctx.font = "10px sans-serif"; ctx.textAlign = "center";
  let x = 0;
  data.groups.forEach((group, k) => {
    ctx.fillStyle = k % 2 ? "#457b9d" : "#1d3557";
    const start = x;
    for (const reading of group.readings) {
      if (reading.volts === null) { ctx.fillStyle = "#d62828"; ctx.fillRect(x, zero - 3, Math.max(w - 1, 1), 6);
                                    ctx.fillStyle = k % 2 ? "#457b9d" : "#1d3557"; }
      else { const h = reading.volts * scale; ctx.fillRect(x, Math.min(zero, zero - h), Math.max(w - 1, 1), Math.abs(h)); }
      x += w;
    }
    ctx.fillStyle = "#333";
    if ((x - start) > 24) ctx.fillText(group.drive.join("-"), (start + x) / 2, canvas.height - 6);
    x += gap * w;
  });
  status.textContent = `${data.file}: ${data.usable} of ${data.readings} readings usable in ${data.groups.length} ` +
                       `drive pairs, ${(data.min_volts * 1e3).toFixed(3)} to ${(data.max_volts * 1e3).toFixed(3)} mV ` +
                       "(red: unusable reading)";
}

document.querySelectorAll("form.task").forEach(form => form.addEventListener("submit", submit));
document.querySelectorAll('#tasks tr[data-state="pending"]').forEach(row => follow(row.dataset.command));
const readingsFile = document.getElementById("readings-file");
readingsFile.addEventListener("change", () => drawReadings(readingsFile.value));
if (readingsFile.value) drawReadings(readingsFile.value);
