// The stitch console: the run as it goes, and the supervisor's buttons.
// Served by `stitch run --console`; the token comes in the URL's fragment (never sent to a
// server by the browser) and goes with every command as `Authorization: Bearer`.
"use strict";

const token = new URLSearchParams(location.hash.slice(1)).get("token") || "";
const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";

let viewer = null;      // this page's viewer id
let inControl = null;   // the viewer in control
let ended = false;
let plan = null;
let budget = null;
let used = 0;
let current = null;     // [throw, step] of the attempt under way
const throws = [];      // per throw: {steps: [], retries, entry, exit, thread}
const done = new Map(); // "t:s" -> "ok" | "failed"
const allEvents = [];   // every record received
let replay = null;      // a recording's {duration_s, complete, frames}, when playing one
let at = 0;             // the time shown when playing a recording, s
let helping = false;    // the robot waits for the surgeon's intervention

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

function say(text, refused) {
  const s = $("said");
  s.textContent = text;
  s.className = refused ? "refused" : "";
}

// --- the plan -------------------------------------------------------------------------
function drawPlan() {
  const root = $("plan");
  root.replaceChildren();
  for (const t of plan.throws) {
    const d = el("div", { class: "throw" });
    d.append(el("span", {}, `throw ${t.throw + 1} (wound point ${t.point + 1})`));
    const ol = el("ol");
    for (const op of t.ops) {
      const li = el("li", { id: `op-${t.throw}-${op.step}`, class: op.kind }, op.label);
      ol.append(li);
    }
    d.append(ol);
    root.append(d);
    throws[t.throw] = { steps: [], retries: 0, entry: null, exit: null, thread: null };
  }
}

function lightPlan() {
  document.querySelectorAll("#plan li").forEach((li) => li.classList.remove("current"));
  for (const [k, v] of done) {
    const li = $(`op-${k.replace(":", "-")}`);
    if (li) { li.classList.remove("ok", "failed"); li.classList.add(v); }
  }
  if (current) {
    const li = $(`op-${current[0]}-${current[1]}`);
    if (li) {
      li.classList.add("current");
      // Scroll the plan's own box only, never the page.
      const box = $("plan");
      const top = li.offsetTop; // #plan is positioned: its own offset parent
      if (top < box.scrollTop || top + li.offsetHeight > box.scrollTop + box.clientHeight) {
        box.scrollTop = Math.max(0, top - box.clientHeight / 3);
      }
    }
  }
}

// --- the state diagram (the explorer's edges): the throw's states in their order on one
// row, the supervision states under them, the ends at the bottom ---------------------------
const ROWS = [
  ["ready", "inserting", "sweeping", "extracting", "cinching", "handing_over", "correcting", "perceiving", "deciding", "at_checkpoint"],
  ["paused", "taken_over", "awaiting_intervention"],
  ["completed", "failed", "aborted"],
];
let nodes = new Map();
function drawDiagram(edges) {
  const names = new Set();
  for (const [a, b] of edges) { names.add(a); names.add(b); }
  const rows = ROWS.map((r) => r.filter((n) => names.has(n)));
  const known = new Set(ROWS.flat());
  rows[1].push(...[...names].filter((n) => !known.has(n)).sort());
  const W = 128, H = 24, GX = 26, GY = 46;
  const pos = new Map();
  const wide = Math.max(...rows.map((r) => r.length));
  rows.forEach((r, j) => {
    const pad = ((wide - r.length) * (W + GX)) / 2;
    r.forEach((n, i) => pos.set(n, [pad + i * (W + GX) + 4, j * (H + GY) + 4]));
  });
  const svg = $("diagram");
  svg.replaceChildren();
  svg.setAttribute("viewBox", `0 0 ${wide * (W + GX)} ${rows.length * (H + GY)}`);
  const defs = document.createElementNS(SVG, "defs");
  defs.innerHTML = '<marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z"/></marker>';
  svg.append(defs);
  for (const [a, b] of edges) {
    if (a === b) continue;
    const [x1, y1] = pos.get(a), [x2, y2] = pos.get(b);
    const line = document.createElementNS(SVG, "line");
    // Same row: side to side; across rows: bottom to top (or back up).
    const across = y1 !== y2, down = y2 > y1, right = x2 >= x1;
    line.setAttribute("x1", across ? x1 + W / 2 : x1 + (right ? W : 0));
    line.setAttribute("y1", across ? y1 + (down ? H : 0) : y1 + H / 2);
    line.setAttribute("x2", across ? x2 + W / 2 : x2 + (right ? 0 : W));
    line.setAttribute("y2", across ? y2 + (down ? 0 : H) : y2 + H / 2);
    line.setAttribute("class", "edge");
    svg.append(line);
  }
  nodes = new Map();
  for (const [n, [x, y]] of pos) {
    const g = document.createElementNS(SVG, "g");
    g.setAttribute("class", "node");
    g.setAttribute("id", `state-${n}`);
    const r = document.createElementNS(SVG, "rect");
    r.setAttribute("x", x); r.setAttribute("y", y); r.setAttribute("width", W); r.setAttribute("height", H); r.setAttribute("rx", 5);
    const t = document.createElementNS(SVG, "text");
    t.setAttribute("x", x + W / 2); t.setAttribute("y", y + H / 2 + 1);
    t.textContent = n;
    g.append(r, t);
    svg.append(g);
    nodes.set(n, g);
  }
  lightDiagram();
}

let stateName = "ready";
function lightDiagram() {
  const kind = stateName.split("(")[0];
  for (const [n, g] of nodes) g.classList.toggle("lit", n === kind);
}

// --- the throws' table -------------------------------------------------------------------
const mm = (m) => (m * 1000).toFixed(2) + " mm";
function drawThrows() {
  const body = $("throws").querySelector("tbody");
  body.replaceChildren();
  throws.forEach((t, i) => {
    if (!t || (!t.steps.length && (!current || current[0] !== i))) return;
    const tr = el("tr");
    tr.append(el("td", {}, String(i + 1)));
    const steps = el("td");
    for (const s of t.steps) {
      steps.append(el("span", { class: s.cls }, s.text));
      steps.append(" ");
    }
    tr.append(steps);
    tr.append(el("td", {}, String(t.retries)));
    tr.append(el("td", {}, t.entry === null ? "–" : `${mm(t.entry)} / ${mm(t.exit)}`));
    tr.append(el("td", {}, t.thread === null ? "–" : (t.thread * 100).toFixed(1) + " cm"));
    body.append(tr);
  });
}

// --- events ------------------------------------------------------------------------------
function summary(r) {
  switch (r.event) {
    case "transition": return `${r.from} → ${r.to}`;
    case "step_start": return `throw ${r.throw + 1} ${r.primitive} attempt ${r.attempt + 1}`;
    case "step_end": return `throw ${r.throw + 1} ${r.primitive}: ${r.outcome.result}${r.outcome.kind ? " (" + r.outcome.kind + ")" : ""}`;
    case "supervisor": return `${r.command} from ${r.from || "?"}${r.acted ? "" : " (no effect)"}`;
    case "refused": return `REFUSED ${r.command} from ${r.from}: ${r.why}`;
    case "finished": return `finished: ${r.outcome.result}${r.outcome.reason ? " (" + r.outcome.reason + ")" : ""}`;
    default: {
      const { seq, t_s, event, ...rest } = r;
      return `${event} ${JSON.stringify(rest)}`;
    }
  }
}

function onRecord(r) {
  $("clock").textContent = r.t_s.toFixed(1) + " s";
  switch (r.event) {
    case "plan": budget = r.interventions; break;
    case "transition": stateName = r.to; break;
    case "step_start": current = [r.throw, r.step]; break;
    case "step_end": {
      const t = throws[r.throw];
      const ok = r.outcome.result === "succeeded";
      const cls = ok ? "ok" : r.outcome.result === "failed" ? "failed" : "other";
      t.steps.push({ cls, text: `${r.primitive}${ok ? " ✓" : " ✗ " + (r.outcome.kind || r.outcome.result)}` });
      const m = r.outcome.measured || {};
      if (m.entry_error_m !== undefined) { t.entry = m.entry_error_m; t.exit = m.exit_error_m; }
      if (m.thread_left_m !== undefined) t.thread = m.thread_left_m;
      done.set(`${r.throw}:${r.step}`, ok ? "ok" : "failed");
      current = null;
      break;
    }
    case "retry": throws[r.throw].retries += 1; break;
    case "intervention_requested": used = r.used; helping = true; break;
    case "intervention_ended": helping = false; break;
    case "finished": stateName = r.outcome.result; break;
  }
  const li = el("li", { value: r.seq, class: r.event }, `${r.t_s.toFixed(2)} s  ${summary(r)}`);
  const log = $("events");
  const stick = log.scrollTop + log.clientHeight >= log.scrollHeight - 4;
  log.append(li);
  while (log.children.length > 400) log.firstChild.remove();
  if (stick) log.scrollTop = log.scrollHeight;
}

// A recording: the run as it stood at `t` (every record up to it, again).
function rebuild(t) {
  at = t;
  stateName = "ready"; current = null; used = 0; helping = false; done.clear();
  $("events").replaceChildren();
  drawPlan();
  for (const r of allEvents) if (r.t_s <= t) onRecord(r);
  $("scrub").value = String(t);
  $("at").textContent = `${t.toFixed(1)} s of ${replay.duration_s.toFixed(1)} s`;
  $("clock").textContent = t.toFixed(1) + " s";
  if (ws && !inFlight) askFrame(ws);
  refresh();
}

function refresh() {
  $("state").textContent = stateName;
  document.body.dataset.state = stateName;
  $("budget").textContent = budget === null ? "–" : `${used} of ${budget} used`;
  lightPlan();
  lightDiagram();
  drawThrows();
  const mine = viewer !== null && inControl === viewer;
  $("control").textContent = inControl === null ? "no viewer in control"
    : mine ? `you (viewer ${viewer}) are in control` : `viewer ${inControl} is in control`;
  document.body.dataset.control = mine ? "mine" : "other";
  $("take-control").disabled = ended || mine || viewer === null;
  document.querySelectorAll("button[data-command]").forEach((b) => {
    const answer = b.dataset.command === "done" || b.dataset.command === "failed";
    b.disabled = ended || (!mine && b.dataset.command !== "e-stop") || viewer === null || (answer && !helping);
  });
}

// --- commands ------------------------------------------------------------------------------
async function post(path, body) {
  const r = await fetch(path, {
    method: "POST",
    headers: { "Authorization": `Bearer ${token}`, "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  const j = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(j.refused || `HTTP ${r.status}`);
  return j;
}

async function command(name) {
  try {
    await post("/api/command", { command: name, viewer });
    say(`sent: ${name}`);
  } catch (e) {
    say(`refused: ${e.message}`, true);
  }
}

async function takeControl() {
  try {
    await post("/api/control", { viewer });
  } catch (e) {
    say(`refused: ${e.message}`, true);
  }
}

// --- the camera: one frame in flight; the next asked for once this one is drawn -----------
let overlay = null;
let frames = [];
let inFlight = false;
let askedAt = null;
let ws = null;
function askFrame(ws) {
  if (ws.readyState !== WebSocket.OPEN || inFlight || $("camera-panel").hidden) return;
  if (replay) {
    if (askedAt === at) return;
    askedAt = at;
    inFlight = true;
    ws.send(JSON.stringify({ type: "frame", t_s: at }));
  } else if (!ended) {
    inFlight = true;
    ws.send(JSON.stringify({ type: "frame" }));
  }
}

async function drawFrame(ws, blob) {
  const o = overlay;
  try {
    const img = await createImageBitmap(blob);
    const canvas = $("camera");
    if (canvas.width !== img.width) { canvas.width = img.width; canvas.height = img.height; }
    const g = canvas.getContext("2d");
    g.drawImage(img, 0, 0);
    if (o && o.needle) {
      g.strokeStyle = "#00c853"; g.lineWidth = 2.5;
      g.beginPath();
      o.needle.forEach(([u, v], i) => (i ? g.lineTo(u, v) : g.moveTo(u, v)));
      g.stroke();
    }
    // A recording's drawing: what the recorder drew on the image (estimate, truth).
    for (const l of (o && o.drawn && o.drawn.lines) || []) {
      g.strokeStyle = l.color; g.lineWidth = 2.5;
      g.beginPath();
      l.points.forEach(([u, v], i) => (i ? g.lineTo(u, v) : g.moveTo(u, v)));
      g.stroke();
    }
    for (const t of (o && o.drawn && o.drawn.labels) || []) {
      g.fillStyle = t.color; g.font = "14px sans-serif"; g.fillText(t.text, t.at[0], t.at[1]);
    }
    for (const j of (o && o.jaws) || []) {
      g.strokeStyle = "#2979ff"; g.fillStyle = "#2979ff"; g.lineWidth = 2;
      g.beginPath(); g.moveTo(...j.back); g.lineTo(...j.tip); g.stroke();
      g.beginPath(); g.arc(j.tip[0], j.tip[1], 4, 0, 2 * Math.PI); g.fill();
      g.font = "12px sans-serif"; g.fillText(j.arm, j.tip[0] + 6, j.tip[1] - 6);
    }
    const now = performance.now();
    frames.push(now);
    frames = frames.filter((t) => now - t < 2000);
    $("fps").textContent = `${(frames.length / 2).toFixed(1)} frames/s, t ${o ? o.t_s.toFixed(1) : "?"} s`;
    document.body.dataset.frames = String((Number(document.body.dataset.frames) || 0) + 1);
    $("estimate").textContent = replay
      ? (o && o.drawn ? `as recorded: the drawing of ${o.drawn_t_s.toFixed(1)} s` : "as recorded")
      : o && o.confidence !== null
      ? `last estimate: confidence ${o.confidence.toFixed(2)}, ${o.estimate_age_s.toFixed(1)} s old`
      : "no estimate yet";
  } finally {
    inFlight = false;
    askFrame(ws);
  }
}

// --- the stream ------------------------------------------------------------------------------
function connect() {
  ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/stream`);
  const link = $("link");
  ws.binaryType = "blob";
  ws.onopen = () => ws.send(JSON.stringify({ token }));
  ws.onmessage = (m) => {
    if (typeof m.data !== "string") { drawFrame(ws, m.data); return; }
    const msg = JSON.parse(m.data);
    switch (msg.type) {
      case "hello":
        viewer = msg.viewer; plan = msg.plan;
        $("mission").textContent = `${plan.name} — ${plan.file}`;
        drawPlan();
        link.textContent = `live (viewer ${viewer})`; link.className = "link live";
        replay = msg.replay;
        if (replay) {
          $("timeline").hidden = false; $("controls").hidden = true;
          // A recording's frames carry what the recorder drew, in its own colours.
          document.querySelectorAll(".needle-key, .jaw-key").forEach((k) => { k.hidden = true; });
          $("scrub").max = String(replay.duration_s);
          link.textContent = replay.complete ? "recording" : "recording (unfinished)";
          link.className = "link ended";
        }
        if (msg.camera) { $("camera-panel").hidden = false; askFrame(ws); }
        // On a real dVRK the person here answers the robot's requests for help.
        $("btn-done").hidden = !msg.answers_interventions;
        $("btn-failed").hidden = !msg.answers_interventions;
        break;
      case "frame": overlay = msg.overlay; break;
      case "no-frame": inFlight = false; setTimeout(() => askFrame(ws), 500); break;
      case "refused":
        say(`the console refused this page: ${msg.why} (open the URL printed at start, with its #token=)`, true);
        link.textContent = "refused"; link.className = "link lost";
        break;
      case "control": inControl = msg.viewer; break;
      case "diagram": drawDiagram(msg.edges); break;
      case "events":
        for (const r of msg.events) {
          allEvents.push(r);
          if (!replay) onRecord(r);
        }
        if (replay) rebuild(at);
        break;
      case "ended":
        if (replay) break;
        ended = true; link.textContent = "run ended"; link.className = "link ended";
        break;
    }
    refresh();
  };
  ws.onclose = () => {
    if (!ended && !replay && link.className !== "link lost") {
      ended = true; link.textContent = "connection lost"; link.className = "link lost";
      refresh();
    }
  };
}

document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("button[data-command]").forEach((b) => b.addEventListener("click", () => command(b.dataset.command)));
  $("take-control").addEventListener("click", takeControl);
  $("scrub").addEventListener("input", () => rebuild(Number($("scrub").value)));
  let playing = null;
  $("play").addEventListener("click", () => {
    if (playing) { clearInterval(playing); playing = null; $("play").textContent = "Play"; return; }
    if (at >= replay.duration_s) at = 0;
    $("play").textContent = "Pause";
    playing = setInterval(() => {
      const t = Math.min(replay.duration_s, at + 0.1 * Number($("speed").value));
      rebuild(t);
      if (t >= replay.duration_s) { clearInterval(playing); playing = null; $("play").textContent = "Play"; }
    }, 100);
  });
  refresh();
  connect();
});
