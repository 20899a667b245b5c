// playseg review: the page (plain JavaScript, no library). Steps are observation indices: a segment
// [start, end) covers actions start..end-1 and observations start..end. A camera's video comes in files of
// ep.video_chunk observations (chunk c: observations c * video_chunk ...); a file shows its k-th
// observation from k / fps to (k + 1) / fps. A video element holds one chunk and moves to another when
// the playhead does.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const withToken = (url) => (token ? url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : url);
const $ = (id) => document.getElementById(id);

async function api(path, body) {
  const options = body === undefined ? {} : { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) };
  const response = await fetch(withToken(path), options);
  const value = await response.json();
  if (!response.ok) throw Object.assign(new Error(value.error || response.statusText), { status: response.status });
  return value;
}

const S = {
  info: null, ep: null, labels: [], proposals: [], rejected: [], selected: null, inPoint: null,
  step: 0, view: { start: 0, end: 1 }, undo: [], redo: [], dirty: false, playing: false, timer: null,
  signals: null, drag: null, opened: 0,
};

// ------------------------------------------------------------------------------------------------
// Status, queue, episode loading

function status(text, kind) {
  const el = $("status");
  el.textContent = text;
  el.className = kind || "";
}

function renderQueue() {
  const list = $("episodes");
  list.innerHTML = "";
  for (const row of S.info.episodes) {
    const li = document.createElement("li");
    li.dataset.index = row.index;
    if (S.ep && S.ep.index === row.index) li.className = "current";
    const conf = row.min_confidence === null ? "no proposals" : `min conf ${row.min_confidence.toFixed(2)} (${row.proposals})`;
    li.innerHTML = `<div>${escapeHtml(row.episode_id)}${row.reviewed ? " &#x2714;" : ""}</div>
      <div class="meta">${row.split} · ${row.num_steps} steps · ${(100 * row.coverage).toFixed(0)}% labelled · ${conf}</div>
      <div class="bar" style="width:${(100 * row.coverage).toFixed(0)}%"></div>`;
    li.onclick = () => openEpisode(row.index);
    list.appendChild(li);
  }
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

async function refreshInfo() {
  S.info = await api("/api/info");
  $("dataset").textContent = S.info.dataset + (S.info.model ? "  ·  model " + S.info.model : "");
  $("vocabulary").innerHTML = S.info.instructions.map((t) => `<option value="${escapeHtml(t)}">`).join("");
  renderQueue();
  renderJobs(S.info.jobs);
}

async function openEpisode(index) {
  if (S.dirty && !confirm("This episode has unsaved changes. Leave it?")) return;
  const ep = await api(`/api/episode/${index}`);
  S.ep = ep;
  S.labels = ep.labels;
  S.proposals = ep.proposals;
  S.rejected = ep.rejected;
  S.selected = null; S.inPoint = null; S.undo = []; S.redo = []; S.dirty = false;
  S.view = { start: 0, end: Math.max(1, ep.num_steps) };
  $("reviewed").checked = ep.reviewed;
  $("episode-title").textContent = `${ep.episode_id} · ${ep.num_steps} steps · ${ep.fps} Hz · labels: ${ep.labels_file}`;
  $("episode-source").textContent = ep.source_text ? `source: ${ep.source_text}` : "";
  const videos = $("videos");
  videos.innerHTML = "";
  for (const camera of ep.cameras) {
    const figure = document.createElement("figure");
    const video = document.createElement("video");
    video.preload = "auto"; video.muted = true; video.dataset.camera = camera;
    video.addEventListener("timeupdate", onVideoTime);
    video.addEventListener("loadedmetadata", onVideoLoaded);
    video.addEventListener("ended", onVideoEnded);
    figure.appendChild(video);
    figure.insertAdjacentHTML("beforeend", `<figcaption>${escapeHtml(camera)}</figcaption>`);
    videos.appendChild(figure);
  }
  if (!ep.cameras.length) videos.textContent = "(this dataset has no camera: signals only)";
  status("", "");
  seek(0);
  renderQueue();
  loadSignals();
  S.opened += 1;  // tests wait on this: the episode is shown
}

// ------------------------------------------------------------------------------------------------
// Playhead, playback

const videos = () => Array.from(document.querySelectorAll("#videos video"));
const clampStep = (k) => Math.max(0, Math.min(S.ep.num_steps, Math.round(k)));

// the observation a video element shows: its chunk's first plus the frame at its time
const videoStep = (v) => Number(v.dataset.chunk) * S.ep.video_chunk + Math.floor(v.currentTime * S.ep.fps);

function showStep(v, step) {
  // the middle of the observation's frame in the chunk holding it; another chunk loads first
  const chunk = Math.floor(step / S.ep.video_chunk), time = (step - chunk * S.ep.video_chunk + 0.5) / S.ep.fps;
  if (v.dataset.chunk === String(chunk) && v.readyState >= 1) { v.currentTime = time; return; }
  v.dataset.time = time;
  if (v.dataset.chunk === String(chunk)) return;  // loading: onVideoLoaded seeks there
  v.dataset.chunk = chunk;
  v.src = withToken(`/api/episode/${S.ep.index}/video/${encodeURIComponent(v.dataset.camera)}?chunk=${chunk}`);
}

function onVideoLoaded(event) {
  const v = event.target;
  v.currentTime = Number(v.dataset.time);
  if (S.playing) { v.playbackRate = parseFloat($("speed").value); v.play().catch(() => {}); }
}

function onVideoEnded(event) {
  // a chunk played to its end: go on in the next one
  const next = (Number(event.target.dataset.chunk) + 1) * S.ep.video_chunk;
  if (S.playing && next <= S.ep.num_steps) showStep(event.target, next);
}

function seek(step) {
  if (!S.ep) return;
  S.step = clampStep(step);
  for (const v of videos()) if (!S.playing || Math.abs(videoStep(v) - S.step) > 1.5) showStep(v, S.step);
  if (S.step < S.view.start || S.step > S.view.end) {
    const width = S.view.end - S.view.start;
    S.view.start = Math.max(0, Math.min(S.step - width / 2, S.ep.num_steps - width));
    S.view.end = S.view.start + width;
    loadSignals();
  }
  draw();
}

function onVideoTime(event) {
  if (!S.playing || event.target !== videos()[0]) return;
  S.step = clampStep(videoStep(event.target));
  checkLoop();
  draw();
}

function loopSegment() {
  return $("loop").checked ? S.labels.find((l) => l.start <= S.step && S.step < l.end) || selectedItem() : null;
}

function checkLoop() {
  const segment = S.loopSegment;
  if (segment && S.step >= segment.end) seek(segment.start);
  if (S.step >= S.ep.num_steps && !segment) pause();
}

function play() {
  if (!S.ep) return;
  S.playing = true;
  S.loopSegment = loopSegment();
  const rate = parseFloat($("speed").value);
  $("play").textContent = "Pause";
  if (videos().length) {
    for (const v of videos()) { v.playbackRate = rate; v.play().catch(() => {}); }
  }
  clearInterval(S.timer);
  S.timer = setInterval(() => {
    if (!videos().length) { S.step = clampStep(S.step + 1); checkLoop(); draw(); }
    else { const v = videos()[0]; S.step = clampStep(videoStep(v)); checkLoop(); draw(); }
  }, 1000 / (S.ep.fps * (videos().length ? 2 : rate)));
}

function pause() {
  S.playing = false;
  clearInterval(S.timer);
  for (const v of videos()) v.pause();
  $("play").textContent = "Play";
  seek(S.step);
}

function boundaries() {
  const set = new Set([0, S.ep.num_steps]);
  for (const s of [...S.labels, ...S.proposals]) { set.add(s.start); set.add(s.end); }
  return Array.from(set).sort((a, b) => a - b);
}

function jumpBoundary(direction) {
  const all = boundaries();
  const target = direction > 0 ? all.find((b) => b > S.step) : all.reverse().find((b) => b < S.step);
  if (target !== undefined) seek(target);
}

// ------------------------------------------------------------------------------------------------
// Editing (every change goes through edit(): one undo step)

function snapshot() {
  return JSON.stringify({ labels: S.labels, proposals: S.proposals, rejected: S.rejected });
}

function edit(change) {
  const before = snapshot();
  const result = change();
  if (result === false) return;
  S.labels.sort((a, b) => a.start - b.start);
  S.undo.push(before); S.redo = []; S.dirty = true;
  status("unsaved changes", "");
  draw();
}

function restore(from, to) {
  if (!from.length) return;
  to.push(snapshot());
  Object.assign(S, JSON.parse(from.pop()));
  S.selected = null; S.dirty = true;
  draw();
}

function selectedItem() {
  if (!S.selected) return null;
  return (S.selected.kind === "label" ? S.labels : S.proposals)[S.selected.i] || null;
}

function reviewer() { return $("reviewer").value.trim() || null; }

function freeGap(step) {
  // the free stretch around `step` between labels
  let lo = 0, hi = S.ep.num_steps;
  for (const l of S.labels) {
    if (l.end <= step) lo = Math.max(lo, l.end);
    if (l.start > step) hi = Math.min(hi, l.start);
    if (l.start <= step && step < l.end) return null;
  }
  return [lo, hi];
}

function markOut() {
  if (S.inPoint === null) { status("set an in-point first (i)", "error"); return; }
  let a = Math.min(S.inPoint, S.step), b = Math.max(S.inPoint, S.step);
  const gap = freeGap(a);
  if (!gap) { status("the in-point lies inside a label", "error"); return; }
  b = Math.min(b, gap[1]);
  if (b - a < 1) { status("a segment needs at least one step", "error"); return; }
  const instruction = $("relabel").value.trim();
  edit(() => {
    S.labels.push({ start: a, end: b, instruction, provenance: "human", confidence: 1, reviewer: reviewer() });
    S.labels.sort((x, y) => x.start - y.start);
    S.selected = { kind: "label", i: S.labels.findIndex((l) => l.start === a) };
  });
  S.inPoint = null;
  if (!instruction) { $("relabel").focus(); status("type its instruction and press Enter", ""); }
  draw();
}

function relabel() {
  const text = $("relabel").value.trim();
  const item = selectedItem();
  if (!text || !item) { status(item ? "type an instruction first" : "select a segment first", "error"); return; }
  edit(() => {
    if (S.selected.kind === "proposal") return acceptProposal(S.selected.i, text);
    item.instruction = text;
    if (item.provenance !== "human") item.provenance = "edited";
    item.reviewer = reviewer() || item.reviewer;
  });
  $("relabel").blur();
}

function acceptProposal(i, instruction) {
  const p = S.proposals[i];
  if (S.labels.some((l) => l.start < p.end && p.start < l.end)) { status("the proposal overlaps a label: change that first", "error"); return false; }
  S.proposals.splice(i, 1);
  const changed = instruction && instruction !== p.instruction;
  S.labels.push({ start: p.start, end: p.end, instruction: instruction || p.instruction,
    provenance: changed ? "edited" : p.provenance, confidence: p.confidence, reviewer: reviewer() });
  S.labels.sort((x, y) => x.start - y.start);
  S.selected = { kind: "label", i: S.labels.findIndex((l) => l.start === p.start) };
}

function accept() {
  if (!S.selected || S.selected.kind !== "proposal") { status("select a proposal first", "error"); return; }
  edit(() => acceptProposal(S.selected.i));
}

function reject() {
  if (!S.selected || S.selected.kind !== "proposal") { status("select a proposal first", "error"); return; }
  edit(() => {
    const [p] = S.proposals.splice(S.selected.i, 1);
    S.rejected.push([p.start, p.end, p.instruction]);
    S.selected = null;
  });
}

function acceptAbove() {
  const threshold = parseFloat($("threshold").value);
  edit(() => {
    let count = 0;
    for (let i = S.proposals.length - 1; i >= 0; i--) {
      if (S.proposals[i].confidence >= threshold && acceptProposal(i) !== false) count++;
    }
    S.selected = null;
    status(`${count} proposal(s) accepted`, "ok");
    if (!count) return false;
  });
}

function split() {
  const item = selectedItem();
  if (!item || S.selected.kind !== "label" || !(item.start < S.step && S.step < item.end)) { status("select a label and put the playhead inside it", "error"); return; }
  edit(() => {
    S.labels.push({ ...item, start: S.step, provenance: item.provenance === "human" ? "human" : "edited" });
    item.end = S.step;
  });
}

function merge() {
  const item = selectedItem();
  const next = item && S.labels[S.selected.i + 1];
  if (!item || S.selected.kind !== "label" || !next) { status("select a label that has a next one", "error"); return; }
  edit(() => {
    item.end = next.end;
    if (item.provenance !== "human") item.provenance = "edited";
    S.labels.splice(S.selected.i + 1, 1);
  });
}

function remove() {
  if (!S.selected || S.selected.kind !== "label") { status("select a label first", "error"); return; }
  edit(() => { S.labels.splice(S.selected.i, 1); S.selected = null; });
}

async function save() {
  if (!S.ep) return;
  const unlabelled = S.labels.find((l) => !l.instruction);
  if (unlabelled) { status(`the label at step ${unlabelled.start} has no instruction`, "error"); return; }
  try {
    const result = await api(`/api/episode/${S.ep.index}/save`, {
      labels: S.labels, version: S.ep.version, reviewed: $("reviewed").checked, rejected: S.rejected,
    });
    S.ep.version = result.version; S.dirty = false;
    status(`saved ${result.saved} label(s) to ${result.file}`, "ok");
    await refreshInfo();
  } catch (error) {
    status(error.message, "error");
  }
}

// ------------------------------------------------------------------------------------------------
// Drawing: signals, overview, detail (a labels lane and a proposals lane)

const LANES = { label: [18, 34], proposal: [58, 34] };

function labelColour(l) {
  return l.provenance === "human" ? "#1e88e5" : l.provenance === "edited" ? "#8e24aa" : "#00897b";
}

function proposalColour(p, alpha) {
  return `hsla(${Math.round(120 * Math.max(0, Math.min(1, p.confidence)))}, 70%, 42%, ${alpha})`;
}

function fitCanvas(canvas) {
  const width = canvas.clientWidth;
  if (canvas.width !== width) canvas.width = width;
  return canvas.getContext("2d");
}

function xOf(step, canvas) { return ((step - S.view.start) / (S.view.end - S.view.start)) * canvas.width; }
function stepOf(x, canvas) { return S.view.start + (x / canvas.width) * (S.view.end - S.view.start); }

function draw() {
  if (!S.ep) return;
  drawOverview(); drawDetail(); drawSignals();
  const t = S.ep.start_time + S.step / S.ep.fps;
  $("clock").textContent = `step ${S.step} / ${S.ep.num_steps} · ${t.toFixed(2)} s` + (S.inPoint !== null ? ` · in ${S.inPoint}` : "");
  const item = selectedItem();
  $("selection").textContent = item
    ? `${S.selected.kind} [${item.start}, ${item.end}) "${item.instruction}" · provenance ${item.provenance} · confidence ${Number(item.confidence).toFixed(3)}` + (item.reviewer ? ` · reviewer ${item.reviewer}` : "")
    : "";
}

function drawOverview() {
  const canvas = $("overview"), g = fitCanvas(canvas), n = Math.max(1, S.ep.num_steps), w = canvas.width;
  g.clearRect(0, 0, w, canvas.height);
  for (const l of S.labels) { g.fillStyle = labelColour(l); g.fillRect((l.start / n) * w, 4, Math.max(1, ((l.end - l.start) / n) * w), 11); }
  for (const p of S.proposals) { g.fillStyle = proposalColour(p, 0.9); g.fillRect((p.start / n) * w, 19, Math.max(1, ((p.end - p.start) / n) * w), 11); }
  g.strokeStyle = "#263238"; g.lineWidth = 2;
  g.strokeRect((S.view.start / n) * w, 1, Math.max(2, ((S.view.end - S.view.start) / n) * w), canvas.height - 2);
  g.fillStyle = "#d32f2f"; g.fillRect((S.step / n) * w - 1, 0, 2, canvas.height);
}

function drawDetail() {
  const canvas = $("detail"), g = fitCanvas(canvas), w = canvas.width;
  g.clearRect(0, 0, w, canvas.height);
  g.fillStyle = "#666"; g.font = "10px sans-serif";
  g.fillText("labels", 2, 12); g.fillText("proposals", 2, 56);
  const visible = (s) => s.end >= S.view.start && s.start <= S.view.end;
  S.labels.forEach((l, i) => {
    if (!visible(l)) return;
    const x0 = xOf(l.start, canvas), x1 = xOf(l.end, canvas), [y, h] = LANES.label;
    g.fillStyle = labelColour(l); g.fillRect(x0, y, x1 - x0, h);
    g.strokeStyle = "#fff"; g.lineWidth = 1; g.strokeRect(x0, y, x1 - x0, h);
    if (S.selected && S.selected.kind === "label" && S.selected.i === i) { g.strokeStyle = "#ffb300"; g.lineWidth = 3; g.strokeRect(x0 + 1, y + 1, x1 - x0 - 2, h - 2); }
    text(g, l.instruction || "(no instruction)", x0, x1, y + 21, "#fff");
  });
  S.proposals.forEach((p, i) => {
    if (!visible(p)) return;
    const x0 = xOf(p.start, canvas), x1 = xOf(p.end, canvas), [y, h] = LANES.proposal;
    // boundary uncertainty: the edges fade over a width that grows as the confidence falls
    const fade = Math.min((x1 - x0) / 3, 4 + 30 * (1 - p.confidence));
    const gradient = g.createLinearGradient(x0, 0, x1, 0);
    const f = fade / Math.max(1, x1 - x0);
    gradient.addColorStop(0, proposalColour(p, 0.15)); gradient.addColorStop(f, proposalColour(p, 0.85));
    gradient.addColorStop(1 - f, proposalColour(p, 0.85)); gradient.addColorStop(1, proposalColour(p, 0.15));
    g.fillStyle = gradient; g.fillRect(x0, y, x1 - x0, h);
    if (S.selected && S.selected.kind === "proposal" && S.selected.i === i) { g.strokeStyle = "#ffb300"; g.lineWidth = 3; g.strokeRect(x0 + 1, y + 1, x1 - x0 - 2, h - 2); }
    text(g, `${p.instruction} (${p.confidence.toFixed(2)})`, x0, x1, y + 21, "#fff");
  });
  if (S.inPoint !== null) { g.fillStyle = "#ff6f00"; g.fillRect(xOf(S.inPoint, canvas) - 1, 0, 3, canvas.height); }
  g.fillStyle = "#d32f2f"; g.fillRect(xOf(S.step, canvas) - 1, 0, 2, canvas.height);
}

function text(g, value, x0, x1, y, colour) {
  if (x1 - x0 < 24) return;
  g.save(); g.beginPath(); g.rect(x0 + 2, y - 12, x1 - x0 - 4, 16); g.clip();
  g.fillStyle = colour; g.font = "11px sans-serif"; g.fillText(value, x0 + 4, y); g.restore();
}

const SIGNAL_COLOURS = ["#1e88e5", "#e53935", "#43a047", "#fb8c00", "#8e24aa", "#00acc1", "#6d4c41", "#3949ab", "#c0ca33", "#d81b60", "#546e7a", "#7cb342"];

async function loadSignals() {
  if (!S.ep) return;
  const canvas = $("signals");
  const start = Math.floor(S.view.start), end = Math.ceil(S.view.end) + 1, index = S.ep.index;
  const points = Math.max(50, canvas.clientWidth);
  const data = await api(`/api/episode/${index}/signals?start=${start}&end=${end}&points=${points}`);
  if (S.ep.index === index) { S.signals = data; drawSignals(); }
}

function drawSignals() {
  const canvas = $("signals"), g = fitCanvas(canvas), w = canvas.width, h = canvas.height;
  g.clearRect(0, 0, w, h);
  const data = S.signals;
  if (data && data.steps.length) {
    data.values.forEach((series, k) => {
      const lo = Math.min(...series), hi = Math.max(...series), span = hi - lo || 1;
      g.strokeStyle = SIGNAL_COLOURS[k % SIGNAL_COLOURS.length]; g.lineWidth = 1; g.beginPath();
      series.forEach((v, j) => { const x = xOf(data.steps[j], canvas), y = h - 6 - ((v - lo) / span) * (h - 12); j ? g.lineTo(x, y) : g.moveTo(x, y); });
      g.stroke();
    });
    g.font = "10px sans-serif";
    let x = 4;
    data.names.forEach((name, k) => { g.fillStyle = SIGNAL_COLOURS[k % SIGNAL_COLOURS.length]; g.fillText(name, x, 10); x += g.measureText(name).width + 10; });
  }
  g.fillStyle = "#d32f2f"; g.fillRect(xOf(S.step, canvas) - 1, 0, 2, h);
}

// ------------------------------------------------------------------------------------------------
// Mouse: select, seek, drag boundaries (a shared edge moves both neighbours), zoom, pan

function hit(event) {
  const canvas = $("detail"), rect = canvas.getBoundingClientRect();
  const x = (event.clientX - rect.left) * (canvas.width / rect.width), y = event.clientY - rect.top;
  const step = stepOf(x, canvas);
  const lane = y >= LANES.label[0] && y < LANES.label[0] + LANES.label[1] ? "label" : y >= LANES.proposal[0] && y < LANES.proposal[0] + LANES.proposal[1] ? "proposal" : null;
  return { x, step, lane, canvas };
}

function onDetailDown(event) {
  if (!S.ep) return;
  const { x, step, lane, canvas } = hit(event);
  if (lane === "label") {
    // a boundary within 6 px: drag it (with the label that shares it)
    for (let i = 0; i < S.labels.length; i++) {
      const l = S.labels[i];
      for (const edge of ["start", "end"]) {
        if (Math.abs(xOf(l[edge], canvas) - x) <= 6) {
          const at = l[edge];
          const left = S.labels.find((o) => o.end === at), right = S.labels.find((o) => o.start === at);
          S.drag = { at, left, right, before: snapshot(), moved: false };
          event.preventDefault();
          return;
        }
      }
    }
  }
  const list = lane === "label" ? S.labels : lane === "proposal" ? S.proposals : null;
  const i = list ? list.findIndex((s) => s.start <= step && step < s.end) : -1;
  S.selected = i >= 0 ? { kind: lane, i } : null;
  if (S.selected && lane === "label") $("relabel").value = S.labels[i].instruction;
  if (S.selected && lane === "proposal") $("relabel").value = S.proposals[i].instruction;
  seek(step);
}

function onDetailMove(event) {
  if (!S.drag) return;
  const { step } = hit(event), d = S.drag;
  const lo = d.left ? d.left.start + 1 : 0, hi = d.right ? d.right.end - 1 : S.ep.num_steps;
  const target = Math.max(lo, Math.min(hi, Math.round(step)));
  if (d.left) d.left.end = target;
  if (d.right) d.right.start = target;
  for (const l of [d.left, d.right]) if (l && l.provenance !== "human") l.provenance = "edited";
  d.moved = d.moved || target !== d.at;
  S.step = target;
  draw();
}

function onDetailUp() {
  if (!S.drag) return;
  const d = S.drag;
  S.drag = null;
  if (d.moved) { S.undo.push(d.before); S.redo = []; S.dirty = true; status("unsaved changes", ""); }
  seek(S.step);
}

function onWheel(event) {
  if (!S.ep) return;
  event.preventDefault();
  const { step } = hit(event), factor = event.deltaY > 0 ? 1.25 : 0.8, n = S.ep.num_steps;
  const width = Math.max(10, Math.min(n, (S.view.end - S.view.start) * factor));
  let start = step - ((step - S.view.start) / (S.view.end - S.view.start)) * width;
  start = Math.max(0, Math.min(start, n - width));
  S.view = { start, end: start + width };
  draw(); loadSignals();
}

function onOverview(event) {
  if (!S.ep) return;
  const canvas = $("overview"), rect = canvas.getBoundingClientRect();
  const step = ((event.clientX - rect.left) / rect.width) * S.ep.num_steps;
  const width = S.view.end - S.view.start;
  S.view.start = Math.max(0, Math.min(step - width / 2, S.ep.num_steps - width));
  S.view.end = S.view.start + width;
  seek(step); loadSignals();
}

// ------------------------------------------------------------------------------------------------
// Jobs, export preview

function renderJobs(jobs) {
  $("jobs").textContent = Object.values(jobs)
    .filter((j) => j.state !== "idle")
    .map((j) => `${j.name}: ${j.state}${j.progress ? " · " + j.progress : ""}${j.error ? " · " + j.error : ""}`)
    .join("  |  ");
}

async function startJob(path, body) {
  try { await api(path, body || {}); pollJobs(true); } catch (error) { status(error.message, "error"); }
}

async function pollJobs(started) {
  // while a job runs, poll it; when one has ended, the queue and proposals may have changed
  const jobs = await api("/api/jobs");
  renderJobs(jobs);
  if (Object.values(jobs).some((j) => j.state === "running")) setTimeout(() => pollJobs(true), 1000);
  else if (started) {
    await refreshInfo();
    if (S.ep && !S.dirty) await openEpisode(S.ep.index);  // new proposals
  }
}

async function exportPreview() {
  try {
    const preview = await api("/api/export/preview");
    $("preview").textContent = preview.episodes.map((e) => `${e.episode_id}\n` + e.rows.map((r) => "  " + JSON.stringify(r)).join("\n")).join("\n");
  } catch (error) { status(error.message, "error"); }
}

async function exportMcap() {
  try {
    const result = await api("/api/export/mcap", {});
    status(`${result.messages} messages written to ${result.out}`, "ok");
  } catch (error) { status(error.message, "error"); }
}

// ------------------------------------------------------------------------------------------------
// Keys

function onKey(event) {
  if (!S.ep) return;
  const typing = event.target.tagName === "INPUT" && event.target.type !== "checkbox";
  if (typing) {
    if (event.target.id === "relabel" && event.key === "Enter") { event.preventDefault(); relabel(); }
    if (event.key === "Escape") event.target.blur();
    return;
  }
  const ctrl = event.ctrlKey || event.metaKey;
  const actions = {
    " ": () => (S.playing ? pause() : play()),
    ArrowLeft: () => seek(S.step - (event.shiftKey ? 10 : 1)),
    ArrowRight: () => seek(S.step + (event.shiftKey ? 10 : 1)),
    i: () => { S.inPoint = S.step; draw(); },
    o: markOut, a: accept, x: reject, s: () => (ctrl ? save() : split()), m: merge,
    Delete: remove, Backspace: remove, "[": () => jumpBoundary(-1), "]": () => jumpBoundary(1),
    z: () => restore(S.undo, S.redo), Z: () => restore(S.redo, S.undo), y: () => restore(S.redo, S.undo),
    l: () => { $("loop").checked = !$("loop").checked; },
    "-": () => stepSpeed(-1), "=": () => stepSpeed(1), "+": () => stepSpeed(1),
    n: () => nextInQueue(),
  };
  const action = actions[event.key];
  if (action) { event.preventDefault(); action(); }
}

function stepSpeed(direction) {
  const select = $("speed");
  select.selectedIndex = Math.max(0, Math.min(select.options.length - 1, select.selectedIndex + direction));
  if (S.playing) play();
}

function nextInQueue() {
  const rows = S.info.episodes, at = rows.findIndex((r) => r.index === S.ep.index);
  if (rows[at + 1]) openEpisode(rows[at + 1].index);
}

// ------------------------------------------------------------------------------------------------

function bind() {
  const click = { play: () => (S.playing ? pause() : play()), "step-back": () => seek(S.step - 1), "step-forward": () => seek(S.step + 1),
    "prev-boundary": () => jumpBoundary(-1), "next-boundary": () => jumpBoundary(1), "apply-label": relabel,
    "mark-in": () => { S.inPoint = S.step; draw(); }, "mark-out": markOut, split, merge, delete: remove, accept, reject,
    "accept-above": acceptAbove, undo: () => restore(S.undo, S.redo), redo: () => restore(S.redo, S.undo), save,
    propose: () => startJob("/api/propose"), retrain: () => startJob("/api/retrain", { steps: parseInt($("retrain-steps").value, 10) }), "export-preview": exportPreview,
    export: () => startJob("/api/export"), "export-mcap": exportMcap };
  // a clicked button gives the focus back, so that space plays instead of clicking it again
  for (const [id, handler] of Object.entries(click)) $(id).addEventListener("click", (event) => { event.currentTarget.blur(); handler(); });
  $("reviewed").addEventListener("change", () => { S.dirty = true; status("unsaved changes", ""); });
  const detail = $("detail");
  detail.addEventListener("mousedown", onDetailDown);
  window.addEventListener("mousemove", onDetailMove);
  window.addEventListener("mouseup", onDetailUp);
  detail.addEventListener("wheel", onWheel, { passive: false });
  $("overview").addEventListener("mousedown", onOverview);
  document.addEventListener("keydown", onKey);
  window.addEventListener("resize", draw);
  window.addEventListener("beforeunload", (event) => { if (S.dirty) event.preventDefault(); });
}

// For tests and for the curious: the page's state and the x of a step on the detail lane.
window.review = { state: S, xOfStep: (step) => xOf(step, $("detail")), laneY: LANES };

bind();
refreshInfo().then(() => { if (S.info.episodes.length) openEpisode(S.info.episodes[0].index); pollJobs(); })
  .catch((error) => status(error.message, "error"));
