// hilsim control panel: plain JavaScript, no build step. State comes by server-sent events
// (/api/events, 4 Hz); actions are JSON POSTs whose errors are shown beside their field.
"use strict";

const $ = (id) => document.getElementById(id);
const COLORS = ["#0969da", "#cf222e", "#1a7f37", "#8250df", "#bf8700", "#1b7c83", "#e16f24", "#57606a"];
let options = { scenarios: [], planners: [], gain_fields: [] };
let last = null;          // the latest state
let builtFor = "";        // the run (pid) the goal and gains forms were built for
const edited = new Set(); // joints whose target the user has set (slider or field) and not sent yet
let dragging = false;     // a slider is held: nothing moves under the pointer
// everything that came over Zenoh (names, messages, goal ids) is text, never markup: any participant
// of the network may write a health message
const esc = (x) => String(x ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
const fmt = (v, d = 3) => (v === null || v === undefined || Number.isNaN(v)) ? "–" : Number(v).toFixed(d);

function clearErrors(form) {
  for (const e of (form || document).querySelectorAll(".err")) e.textContent = "";
  for (const i of (form || document).querySelectorAll("[aria-invalid]")) i.removeAttribute("aria-invalid");
}

function showError(field, message, fallback) {
  const input = $(field);
  let el = $("err-" + field);
  if (!el && input && input.tagName === "INPUT") {
    // no place reserved for it (a table cell): the message goes right after the field
    el = document.createElement("span");
    el.className = "err"; el.id = "err-" + field; el.setAttribute("aria-live", "polite");
    input.after(el);
  }
  el = el || $("err-" + fallback);
  if (el) el.textContent = message;
  if (input && input.tagName === "INPUT") {
    input.setAttribute("aria-invalid", "true");
    input.setAttribute("aria-describedby", el.id);
  }
}

async function post(path, body, fallback) {
  let res;
  try {
    res = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body || {}) });
  } catch (e) {
    showError(fallback, "the panel server does not answer: " + e, fallback);
    return null;
  }
  let data = {};
  try { data = await res.json(); } catch (e) { data = { error: "unreadable answer (" + res.status + ")" }; }
  if (!res.ok) {
    showError(data.field || fallback, data.error || ("error " + res.status), fallback);
    return null;
  }
  return data;
}

// ------------------------------------------------------------------ run form
function scenarioOption(name) { return options.scenarios.find((s) => s.name === name); }

function fillWorlds() {
  const s = scenarioOption($("scenario").value);
  $("world").replaceChildren(...(s ? s.worlds : []).map((w) => new Option(w, w)));
  const p = $("planner");
  p.disabled = !s || !s.planner;
  p.replaceChildren(new Option(s && s.planner ? "scenario default (" + s.planner + ")" : "(its navigator plans)", ""),
    ...(s && s.planner ? options.planners.map((n) => new Option(n, n)) : []));
}

async function loadOptions() {
  const res = await fetch("/api/options");
  options = await res.json();
  const sel = $("scenario");
  sel.replaceChildren(...options.scenarios.map((s) => new Option(s.name + " (" + s.robot + ")", s.name)));
  if (scenarioOption("arm-lean")) sel.value = "arm-lean";
  fillWorlds();
  $("goal-planner").replaceChildren(new Option("the run's planner", ""), ...options.planners.map((n) => new Option(n, n)));
}

$("scenario").addEventListener("change", fillWorlds);

$("run-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearErrors($("run-form"));
  const mode = document.querySelector("input[name=mode]:checked").value;
  await post("/api/run", { scenario: $("scenario").value, world: $("world").value, planner: $("planner").value,
    clock: $("clock").value, mode }, "run");
});

$("stop").addEventListener("click", async () => {
  clearErrors($("run-form"));
  await post("/api/stop", {}, "run");
});

// ------------------------------------------------------------------ goal forms
function buildGoalForms(sc, st) {
  const mobile = sc && sc.mobile;
  $("joint-form").hidden = !sc || mobile;
  $("pose-form").hidden = !sc || mobile;
  $("xy-form").hidden = !sc || !mobile;
  $("no-goal").hidden = !!sc;
  const box = $("sliders");
  box.replaceChildren();
  if (!sc || mobile) return;
  const pos = st.joints && st.joints.position || [];
  sc.joints.forEach((name, i) => {
    const lo = sc.lower[i], hi = sc.upper[i];
    const v = pos[i] !== undefined && pos[i] !== null ? Math.min(hi, Math.max(lo, pos[i])) : 0;
    const row = document.createElement("div");
    row.className = "slider";
    const n = esc(name);
    row.innerHTML = `<label for="range-${n}" title="${n}">${n}</label>
      <input type="range" id="range-${n}" min="${lo}" max="${hi}" step="0.001" value="${v}" aria-describedby="lim-${n}">
      <input id="joint-${n}" inputmode="decimal" value="${v.toFixed(3)}" aria-label="${n} target [rad]">
      <span class="lim" id="lim-${n}">${lo.toFixed(2)} … ${hi.toFixed(2)} rad</span>
      <span class="err" id="err-joint-${n}" aria-live="polite"></span>`;
    box.append(row);
    const range = row.querySelector("input[type=range]"), num = $("joint-" + name);
    range.addEventListener("input", () => { edited.add(name); num.value = Number(range.value).toFixed(3); });
    num.addEventListener("input", () => {
      edited.add(name);
      const x = parseFloat(num.value); if (Number.isFinite(x)) range.value = x;
    });
    range.addEventListener("pointerdown", () => { dragging = true; });
  });
}
window.addEventListener("pointerup", () => { dragging = false; });
window.addEventListener("pointercancel", () => { dragging = false; });

// the sliders show where the joints are (the truth), except one the user is setting: dragged,
// focused, or set and not sent yet
function followTruth(st) {
  const sc = st.scenario;
  if (!sc || sc.mobile || dragging) return;
  const at = new Map((st.joints.names || []).map((n, i) => [n, st.joints.position[i]]));
  sc.joints.forEach((name, i) => {
    const range = $("range-" + name), num = $("joint-" + name), q = at.get(name);
    if (!range || !num || q === null || q === undefined || edited.has(name)) return;
    if (document.activeElement === range || document.activeElement === num) return;
    range.value = Math.min(sc.upper[i], Math.max(sc.lower[i], q));
    num.value = q.toFixed(3);
  });
}

$("use-current").addEventListener("click", () => {
  const sc = last && last.scenario, pos = last && last.joints.position;
  if (!sc || !pos) return;
  edited.clear();
  sc.joints.forEach((name, i) => {
    if (pos[i] === null || pos[i] === undefined) return;
    $("joint-" + name).value = pos[i].toFixed(3);
    $("range-" + name).value = pos[i];
  });
});

$("joint-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearErrors($("joint-form")); $("err-goal").textContent = "";
  const sc = last && last.scenario;
  if (!sc) return;
  // the text as typed: the server says what is wrong with it, beside the field
  const positions = sc.joints.map((n) => $("joint-" + n).value);
  // sent: the sliders follow the joints (to the target) again
  if (await post("/api/goal", { kind: "joints", positions, planner: $("goal-planner").value }, "goal")) edited.clear();
});

$("pose-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearErrors($("pose-form")); $("err-goal").textContent = "";
  const body = { kind: "pose", planner: $("goal-planner").value };
  for (const k of ["x", "y", "z", "roll", "pitch", "yaw"]) body[k] = $("pose-" + k).value;
  await post("/api/goal", body, "goal");
});

$("xy-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  clearErrors($("xy-form")); $("err-goal").textContent = "";
  await post("/api/goal", { kind: "xy", x: $("xy-x").value, y: $("xy-y").value, yaw: $("xy-yaw").value }, "goal");
});

// ------------------------------------------------------------------ gains
function buildGains(sc) {
  const tb = $("gains").querySelector("tbody");
  tb.replaceChildren();
  if (sc && sc.mobile) {
    tb.innerHTML = `<tr><td colspan="6" class="hint">This robot's controller has no joint PID gains to tune here.</td></tr>`;
  }
  if (!sc || sc.mobile) return;
  for (const name of sc.joints) {
    const tr = document.createElement("tr");
    const n = esc(name);
    tr.innerHTML = `<th scope="row">${n}</th>` + options.gain_fields.map((f) =>
      `<td><input id="gain-${n}-${f}" inputmode="decimal" aria-label="${n} ${f}"></td>`).join("") +
      `<td><button type="button" class="small" id="apply-${n}">Apply</button></td>`;
    tb.append(tr);
    for (const inp of tr.querySelectorAll("input")) inp.addEventListener("input", () => { inp.dataset.dirty = "1"; });
    tr.querySelector("button").addEventListener("click", () => applyGains(name));
  }
}

async function applyGains(joint) {
  clearErrors($("gains")); $("err-gains").textContent = ""; $("gains-ok").textContent = "";
  const body = { joint };
  for (const f of options.gain_fields) {
    const inp = $(`gain-${joint}-${f}`);
    if (inp.dataset.dirty) body[f] = inp.value;
  }
  const res = await post("/api/gains", body, "gains");
  if (res) {
    for (const f of options.gain_fields) delete $(`gain-${joint}-${f}`).dataset.dirty;
    $("gains-ok").textContent = "set " + Object.entries(res.set).map(([k, v]) => k + " = " + v).join(", ");
  }
}

function renderGains(gains) {
  for (const [joint, g] of Object.entries(gains || {})) {
    for (const f of options.gain_fields) {
      const inp = $(`gain-${joint}-${f}`);
      if (inp && !inp.dataset.dirty && document.activeElement !== inp && g[f] !== undefined) inp.value = String(g[f]);
    }
  }
}

// ------------------------------------------------------------------ recording
$("open-viewer").addEventListener("click", async () => {
  $("err-viewer").textContent = "";
  const res = await post("/api/viewer", {}, "viewer");
  if (res) { $("viewer-link").href = res.url; $("viewer-link").hidden = false; }
});

// ------------------------------------------------------------------ rendering
function renderRun(st) {
  const r = st.run, b = $("run-banner");
  let cls = "idle", text = "No run";
  if (r.state === "running") {
    cls = r.ready ? "running" : "starting";
    text = (r.ready ? "Running: " : "Starting: ") + `${r.scenario} · ${r.world} · ${r.clock} · ${r.mode} · pid ${r.pid}`;
  } else if (r.state === "stopping") { cls = "stopping"; text = `Stopping ${r.scenario}…`; }
  else if (r.state === "finished") {
    cls = r.rc === 0 ? "idle" : "failed";
    text = `Finished: ${r.scenario}, exit code ${r.rc}` + (r.rc === 0 ? " (OK)" : "");
  }
  if (!(r.state === "running" || r.state === "stopping") && st.external) {
    cls = "running"; text = `Connected to a run started elsewhere: ${st.robot}`;
  }
  b.className = "banner " + cls; b.textContent = text;
  const busy = r.state === "running" || r.state === "stopping";
  $("start").disabled = busy || !!st.external; $("stop").disabled = !busy || r.state === "stopping";
  $("run-cmd").textContent = r.command || "hilsim up";
  const out = $("output"), atEnd = out.scrollTop + out.clientHeight >= out.scrollHeight - 4;
  out.textContent = (r.output || []).join("\n");
  if (atEnd) out.scrollTop = out.scrollHeight;
  const rec = r.recording;
  $("rec").hidden = !rec; $("rec-none").hidden = !!rec;
  if (rec) $("rec-cmd").textContent = "hilsim view " + rec + "   (or: rerun " + rec + ")";
  if (st.viewer) { $("viewer-link").href = st.viewer; $("viewer-link").hidden = false; }
}

function renderServices(st) {
  const expected = (st.run.state === "running" && st.run.services) || [];
  const rows = new Map(st.services.map((s) => [s.name, s]));
  for (const n of expected) if (!rows.has(n)) rows.set(n, { name: n, alive: false, level: null, state: "", message: "" });
  const tb = $("services").querySelector("tbody");
  tb.replaceChildren(...[...rows.values()].map((s) => {
    const tr = document.createElement("tr");
    tr.dataset.service = s.name;
    const lvl = s.level === null || s.level === undefined ? "" : ["OK", "WARN", "ERROR", "STALE"][s.level] || s.level;
    // a service that left because it was stopped (its last health: stopped, done) is not alarming
    const left = s.alive ? "up" : ["stopped", "done"].includes(s.state) ? "left" : "down";
    tr.innerHTML = `<th scope="row">${esc(s.name)}</th><td class="${left}">${s.alive ? "alive" : "gone"}</td>
      <td class="${["fault", "stalled", "error"].includes(s.state) ? "down" : ""}">${esc(s.state)}</td><td class="lvl${Number(s.level)}">${esc(lvl)}${s.message ? ": " + esc(s.message) : ""}${s.last_error ? " (" + esc(s.last_error) + ")" : ""}</td>`;
    return tr;
  }));
}

function renderJoints(st) {
  const j = st.joints, tb = $("joints").querySelector("tbody");
  tb.replaceChildren(...j.names.map((n, i) => {
    const tr = document.createElement("tr");
    const p = j.position[i], s = j.setpoint[i];
    tr.innerHTML = `<th scope="row"><span class="swatch" style="background:${COLORS[i % COLORS.length]}"></span>${esc(n)}</th>
      <td class="num">${fmt(p)}</td><td class="num">${fmt(s)}</td><td class="num">${s === null || p === null ? "–" : fmt(p - s, 4)}</td>`;
    return tr;
  }));
  $("pose").textContent = st.pose ? `base (truth): x ${fmt(st.pose[0], 2)} m, y ${fmt(st.pose[1], 2)} m, yaw ${fmt(st.pose[2], 2)} rad` : "";
  drawPlot(st.history);
}

function drawPlot(h) {
  const c = $("plot"), ctx = c.getContext("2d");
  const w = c.width = c.clientWidth || 720, hh = c.height = 220;
  ctx.clearRect(0, 0, w, hh);
  ctx.font = "11px system-ui, sans-serif"; ctx.fillStyle = "#57606a";
  if (!h || h.t.length < 2) { ctx.fillText("no joint data yet", 10, 20); return; }
  let lo = Infinity, hi = -Infinity;
  for (const row of h.pos.concat(h.ref)) for (const v of row) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (hi - lo < 0.2) { const m = (hi + lo) / 2; lo = m - 0.1; hi = m + 0.1; }
  const t0 = h.t[0], t1 = h.t[h.t.length - 1], L = 40, R = 8, T = 8, B = 18;
  const X = (t) => L + (w - L - R) * (t - t0) / Math.max(t1 - t0, 1e-6);
  const Y = (v) => T + (hh - T - B) * (hi - v) / (hi - lo);
  ctx.strokeStyle = "#eaeef2"; ctx.lineWidth = 1;
  for (let k = 0; k <= 4; k++) {
    const v = lo + (hi - lo) * k / 4, y = Y(v);
    ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(w - R, y); ctx.stroke();
    ctx.fillText(v.toFixed(2), 2, y + 4);
  }
  ctx.fillText(`sim ${t0.toFixed(1)} s`, L, hh - 4);
  ctx.fillText(`${t1.toFixed(1)} s`, w - R - 40, hh - 4);
  const n = h.pos[h.pos.length - 1].length;
  for (let j = 0; j < n; j++) {
    ctx.strokeStyle = COLORS[j % COLORS.length];
    for (const [series, dash] of [[h.pos, []], [h.ref, [5, 4]]]) {
      ctx.setLineDash(dash); ctx.lineWidth = dash.length ? 1.2 : 1.8; ctx.beginPath();
      let on = false;
      series.forEach((row, i) => {
        const v = row[j];
        if (v === null || v === undefined) { on = false; return; }
        if (on) ctx.lineTo(X(h.t[i]), Y(v)); else { ctx.moveTo(X(h.t[i]), Y(v)); on = true; }
      });
      ctx.stroke();
    }
  }
  ctx.setLineDash([]);
}

function setCell(td, html, cls) {
  // only what changed is touched: a row rebuilt on every update detached its Cancel button under the
  // pointer (a click on a busy machine never landed)
  if (td.dataset.h !== html) { td.innerHTML = html; td.dataset.h = html; }
  if (cls !== undefined && td.className !== cls) td.className = cls;
}

function renderGoals(st) {
  const tb = $("goals").querySelector("tbody");
  const rows = new Map([...tb.children].map((tr) => [tr.dataset.goal, tr]));
  const order = st.goals.map((g) => {
    let tr = rows.get(g.id);
    if (!tr) {
      tr = document.createElement("tr");
      tr.dataset.goal = g.id;
      for (let i = 0; i < 6; i++) tr.append(document.createElement("td"));
    }
    tr.dataset.state = g.state;
    const err = g.error && g.error.length ? "max error " + Math.max(...g.error.map(Math.abs)).toFixed(4) : "";
    const res = g.done ? (g.success ? "reached" : "failed") + (g.message ? ": " + g.message : "") + (err ? "; " + err : "") : "";
    const td = tr.children;
    setCell(td[0], esc(g.id));
    setCell(td[1], esc(g.state), g.success === false ? "down" : g.success ? "up" : "");
    setCell(td[2], `${Math.round(100 * (Number(g.progress) || 0))} %`, "num");
    setCell(td[3], esc(g.planner || "") + (g.choice ? "<br><small>" + esc(g.choice) + "</small>" : ""), "planner");
    td[3].title = g.choice || "";
    setCell(td[4], esc(res));
    const b = td[5].querySelector("button");
    if (!g.done && !b) {
      const nb = document.createElement("button");
      nb.type = "button"; nb.className = "small"; nb.textContent = "Cancel"; nb.setAttribute("aria-label", "cancel goal " + g.id);
      nb.addEventListener("click", async () => { $("err-cancel").textContent = ""; await post("/api/cancel", { goal_id: g.id }, "cancel"); });
      td[5].append(nb);
    } else if (g.done && b) {
      b.remove();
    }
    return tr;
  });
  if (order.length !== tb.children.length || order.some((tr, i) => tb.children[i] !== tr)) tb.replaceChildren(...order);
}

function renderFaults(st) {
  const box = $("faults");
  box.hidden = !st.faults.length;
  $("fault-list").replaceChildren(...st.faults.map((f) => {
    const li = document.createElement("li");
    li.textContent = `${new Date(f.wall * 1000).toLocaleTimeString()} ${f.source}: ${f.text}`;
    return li;
  }));
}

function render(st) {
  last = st;
  renderRun(st);
  $("sim-time").textContent = st.sim_time === null ? "–" : st.sim_time.toFixed(2) + " s" + (st.paused_for ? " (paused: " + st.paused_for + ")" : "");
  $("rtf").textContent = st.rtf || "–";
  $("overruns").textContent = st.overruns === null || st.overruns === undefined ? "–" : st.overruns;
  $("robot").textContent = st.robot;
  // the forms follow the run they command: the panel's (by pid), or one started elsewhere
  const key = !st.scenario ? "" : st.external ? "external-" + st.robot + "-" + st.scenario.name : String(st.run.pid);
  if (key !== builtFor && (key === "" || (st.joints.names.length || (st.scenario && st.scenario.mobile)))) {
    builtFor = key;
    // the run form shows what runs (a run started elsewhere, or before this page was opened)
    if (key && !st.external && scenarioOption(st.run.scenario) && $("scenario").value !== st.run.scenario) {
      $("scenario").value = st.run.scenario; fillWorlds();
      if ([...$("world").options].some((o) => o.value === st.run.world)) $("world").value = st.run.world;
    }
    edited.clear();
    buildGoalForms(key ? st.scenario : null, st);
    buildGains(key ? st.scenario : null);
  } else if (key) followTruth(st);
  renderServices(st); renderJoints(st); renderGoals(st); renderGains(st.gains); renderFaults(st);
}

function connect() {
  const es = new EventSource("/api/events");
  es.onopen = () => { $("link").textContent = "live"; };
  es.onmessage = (ev) => { try { render(JSON.parse(ev.data)); } catch (e) { console.error(e); } };
  es.onerror = () => { $("link").textContent = "reconnecting…"; };
}

loadOptions().then(connect);

// The robot, live: Rerun's web viewer on the run's stream (hilsim up --view), beside the joint plots, once
// asked for: its wasm and WebGL hold a small machine's cores (seen: a headless browser's page unresponsive
// for 30 s on 2 busy cores), so the page does not load it by itself
let liveUrl = null, liveOn = false;
function showLive(url) {
  if (url === liveUrl) return;
  liveUrl = url;
  $("live").hidden = !url;
  $("joints-live").classList.toggle("with-live", !!url && liveOn);
  $("live-view").hidden = !liveOn;
  $("live-view").src = url && liveOn ? url : "about:blank";
  $("live-link").href = url || "#";
  $("live-show").textContent = liveOn ? "Hide the 3D view" : "Show the robot in 3D";
}
$("live-show").addEventListener("click", () => {
  liveOn = !liveOn;
  const url = liveUrl; liveUrl = null; showLive(url);
});
async function pollLive() {
  try {
    const res = await fetch("/api/live");
    if (res.ok) showLive((await res.json()).viewer || "");
  } catch (e) { /* the panel's server is away: try again */ }
  setTimeout(pollLive, 3000);
}
pollLive();
