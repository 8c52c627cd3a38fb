"use strict";
// afmctl view: the live page. Frames arrive on /ws (new rows only); each scanner's rows are
// kept for the server's history window and at most MAX_ROWS per stream (bounded memory).

const WINDOW_S = 5;        // seconds shown by the fast time plots (voltages, targets, error)
const state = { scanners: {}, selected: null, historyS: 30, maxRows: 6000, frames: 0, dirty: true,
  lastFrameMs: 0, busyMs: { ingest: 0, render: 0 } };
window.afmView = state;   // for tests and the curious: frame count, rows held per stream, time
                          // spent taking frames and drawing [ms] (busyMs)

function newScanner() {
  return { setpoints: [], tips: [], drift: [], status: null, counts: {}, tracking: {}, image: null,
    learn: [], learnState: null };
}

function trim(rows, historyS) {
  if (!rows.length) { return; }
  const tMin = rows[rows.length - 1][0] - historyS;
  let cut = 0;
  while (cut < rows.length && rows[cut][0] < tMin) { cut++; }
  cut = Math.max(cut, rows.length - state.maxRows);
  if (cut > 0) { rows.splice(0, cut); }
}

function ingest(frame) {
  state.historyS = frame.history_s;
  state.maxRows = frame.max_rows;
  for (const [name, f] of Object.entries(frame.scanners)) {
    const s = state.scanners[name] || (state.scanners[name] = newScanner());
    for (const key of ["setpoints", "tips", "drift"]) {
      const rows = f[key];
      if (rows.length && s[key].length && rows[0][0] < s[key][s[key].length - 1][0] - 1) { s[key].length = 0; }
      for (const r of rows) { s[key].push(r); }
      trim(s[key], state.historyS);
    }
    ingestLearn(s, f);
    s.status = f.status; s.counts = f.counts; s.tracking = f.tracking; s.lastRejected = f.last_rejected;
    s.alive = f.alive;
    if ("image" in f) { s.image = f.image; }
  }
  state.frames++; state.dirty = true; state.lastFrameMs = performance.now();
  updateSelector();
}

// learning iterations (afmctl learn): one run at a time; a new run starts over
function ingestLearn(s, f) {
  const ls = f.learn_state;
  if (!ls) { return; }
  if (!s.learnState || s.learnState.run !== ls.run) { s.learn = []; }
  for (const r of f.learn || []) { s.learn.push(r); }
  s.learnState = ls;
}

// presence of a scanner: its liveliness token alive, gone, or never seen (no presence)
function presence(s) { return s.alive === true ? "alive" : s.alive === false ? "gone" : "unknown"; }

function updateSelector() {
  const sel = document.getElementById("scanner"), names = Object.keys(state.scanners).sort();
  const labels = names.map((n) => (presence(state.scanners[n]) === "gone" ? `${n} (gone)` : n));
  if (sel.dataset.labels !== labels.join("|")) {
    sel.innerHTML = names.map((n, i) => `<option value="${esc(n)}">${esc(labels[i])}</option>`).join("");
    sel.dataset.labels = labels.join("|");
    if (!state.selected || !names.includes(state.selected)) { state.selected = names[0] || null; }
    sel.value = state.selected;
  }
  updateLab(names);
}

// the lab: one card per scanner, side by side (state, loop figures, the voltages of the
// last seconds); a scanner whose token went away is greyed out; a click shows it below
function updateLab(names) {
  const lab = document.getElementById("lab");
  for (const n of names) {
    let card = lab.querySelector(`.card[data-name="${CSS.escape(n)}"]`);
    if (!card) {
      card = document.createElement("div");
      card.className = "card"; card.dataset.name = n;
      card.innerHTML = `<div class="head"><b>${esc(n)}</b><span class="presence"></span><span class="cstate"></span></div>` +
        `<canvas class="spark"></canvas><div class="figs muted"></div>`;
      card.addEventListener("click", () => { selectScanner(n); });
      lab.appendChild(card);
    }
    const s = state.scanners[n], st = (s.status && s.status.stats) || {}, p = presence(s);
    card.classList.toggle("gone", p === "gone");
    card.classList.toggle("selected", n === state.selected);
    card.querySelector(".presence").textContent = p;
    card.querySelector(".cstate").textContent = (s.status && s.status.state) || "no status";
    card.querySelector(".figs").textContent = `samples ${fmtN(st.samples, 9)} · p99 lateness ` +
      `${st.lateness_p99_s === undefined ? "–" : fmtN(st.lateness_p99_s * 1e6) + " µs"} · missed ${fmtN(st.missed_deadlines, 9)}`;
  }
}

// the cards' voltage sparklines: drawn with the plots, once per animation frame at most
function drawSparks() {
  for (const card of document.querySelectorAll("#lab .card")) {
    const s = state.scanners[card.dataset.name];
    if (s) { drawSpark(card.querySelector(".spark"), s); }
  }
}

function selectScanner(name) {
  state.selected = name; state.dirty = true;
  document.getElementById("scanner").value = name;
  updateLab(Object.keys(state.scanners).sort());
}

function drawSpark(canvas, s) {
  const dpr = window.devicePixelRatio || 1, r = canvas.getBoundingClientRect();
  const w = Math.max(20, Math.round(r.width * dpr)), h = Math.max(20, Math.round(r.height * dpr));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, w, h);
  const rows = s.setpoints.length ? recent(s.setpoints, timeRange(s, WINDOW_S)) : [];
  if (rows.length < 2) { return; }
  const t0 = rows[0][0], t1 = rows[rows.length - 1][0] || t0 + 1;
  const yr = extent([4, 5, 6].map((k) => col(rows, k)));
  const sx = (t) => ((t - t0) / Math.max(t1 - t0, 1e-9)) * (w - 2) + 1, sy = (v) => h - 1 - ((v - yr[0]) / (yr[1] - yr[0])) * (h - 2);
  ["x", "y", "z"].forEach((a, i) => {
    ctx.strokeStyle = AXIS_COLORS[a]; ctx.lineWidth = dpr; ctx.beginPath();
    tracePath(ctx, rows.length, (j) => rows[j][0], (j) => rows[j][4 + i], sx, sy);
    ctx.stroke();
  });
}

function col(rows, k) { return rows.map((r) => r[k]); }

const plots = {};

function setupPlots() {
  const mk = (id, opts) => { plots[id] = new Plot(document.getElementById(id), opts); };
  mk("plot-volts", { title: "Voltages sent (after the safety layer)", xlabel: `controller time t [s] (last ${WINDOW_S} s)`, ylabel: "u [V]" });
  mk("plot-targets", { title: "Target (—) and true tip (- -)", xlabel: `controller time t [s] (last ${WINDOW_S} s)`, ylabel: "position [nm]" });
  mk("plot-xy", { title: "Tip path against the target, x–y", xlabel: "x [nm]", ylabel: "y [nm]", equal: true });
  mk("plot-error", { title: "Tracking error: tip − target", xlabel: `controller time t [s] (last ${WINDOW_S} s)`, ylabel: "error [nm]" });
  mk("plot-drift", { title: "Drift estimate (band: ±1σ)", xlabel: "controller time t [s]", ylabel: "drift [nm]" });
  mk("plot-learn", { title: "Learning: error per iteration (afmctl learn)", xlabel: "iteration",
    ylabel: "error [% of the range]" });
  mk("plot-image", { title: "Image (sample height under the tip)", xlabel: "x [nm]", ylabel: "y [nm]",
    equal: true, colorbar: true });
}

function timeRange(s, spanS) {
  const all = [s.setpoints, s.tips, s.drift].filter((r) => r.length);
  const tMax = Math.max(...all.map((r) => r[r.length - 1][0]));
  return isFinite(tMax) ? [tMax - spanS, tMax] : [0, 1];
}

function recent(rows, tr) {
  let i = rows.length;
  while (i > 0 && rows[i - 1][0] >= tr[0]) { i--; }
  return i > 0 ? rows.slice(i - 1) : rows;
}

function axesPlot(p, s, rows, cols, names, tr, dash) {
  const xs = col(rows, 0);
  p.frame(tr, extent(cols.map((k) => col(rows, k))));
  p.clip();
  cols.forEach((k, i) => p.line(xs, col(rows, k), AXIS_COLORS[names[i]], 1.5, dash));
  p.ctx.restore();
}

function drawVolts(s, tr) {
  const p = plots["plot-volts"];
  p.resize();
  if (!s.setpoints.length) { p.frame(tr, [0, 1]); p.message("waiting for setpoints…"); return; }
  axesPlot(p, s, recent(s.setpoints, tr), [4, 5, 6], ["x", "y", "z"], tr);
  p.legend(["x", "y", "z"].map((a) => ({ name: `u_${a} [V]`, color: AXIS_COLORS[a] })));
}

function drawTargets(s, tr) {
  const p = plots["plot-targets"];
  p.resize();
  if (!s.setpoints.length) { p.frame(tr, [0, 1]); p.message("waiting for setpoints…"); return; }
  const sp = recent(s.setpoints, tr), tips = recent(s.tips, tr);
  p.frame(tr, extent([col(sp, 1), col(sp, 2), col(tips, 1), col(tips, 2)]));
  p.clip();
  for (const [a, k] of [["x", 1], ["y", 2]]) {
    p.line(col(sp, 0), col(sp, k), AXIS_COLORS[a], 1.5);
    if (tips.length) { p.line(col(tips, 0), col(tips, k), AXIS_COLORS[a], 1.5, [5, 3]); }
  }
  p.ctx.restore();
  const items = [{ name: "target x [nm]", color: AXIS_COLORS.x }, { name: "target y [nm]", color: AXIS_COLORS.y }];
  if (tips.length) { items.push({ name: "tip x, y [nm]", color: "#555", dash: [5, 3] }); }
  p.legend(items);
}

function drawXY(s) {
  const p = plots["plot-xy"];
  p.resize();
  const sp = s.setpoints.slice(-4000), tips = s.tips.slice(-4000);
  if (!sp.length && !tips.length) { p.frame([0, 1], [0, 1]); p.message("waiting for setpoints…"); return; }
  p.frame(extent([col(sp, 1), col(tips, 1)]), extent([col(sp, 2), col(tips, 2)]));
  p.clip();
  p.line(col(sp, 1), col(sp, 2), "#9aa3b2", 1.2);
  if (tips.length) { p.line(col(tips, 1), col(tips, 2), "#e6550d", 1.5); }
  p.ctx.restore();
  const items = [{ name: "target", color: "#9aa3b2" }];
  items.push({ name: tips.length ? "true tip (sim/tip)" : "no tip published", color: "#e6550d" });
  p.legend(items);
}

function drawError(s, tr) {
  const p = plots["plot-error"];
  p.resize();
  const rows = recent(s.tips, tr).filter((r) => r[4] !== null);
  if (!rows.length) { p.frame(tr, [-1, 1]); p.message("needs the simulator's sim/tip and setpoints"); return; }
  axesPlot(p, s, rows, [4, 5], ["x", "y"], tr);
  const t = s.tracking || {}, rms = t.rms_nm || [], pct = t.rms_pct || [];
  p.legend(["x", "y"].map((a, i) => ({ name: `e_${a} [nm]  rms ${fmtN(rms[i])} nm = ${fmtN(pct[i])} % of range`,
    color: AXIS_COLORS[a] })));
}

function drawDrift(s, tr) {
  const p = plots["plot-drift"];
  p.resize();
  const rows = s.drift;
  if (!rows.length) { p.frame(tr, [-1, 1]); p.message("waiting for drift estimates…"); return; }
  const lo = (k) => rows.map((r) => (r[k + 3] === null ? null : r[k] - r[k + 3]));
  const hi = (k) => rows.map((r) => (r[k + 3] === null ? null : r[k] + r[k + 3]));
  p.frame(tr, extent([1, 2, 3].flatMap((k) => [col(rows, k), lo(k), hi(k)])));
  p.clip();
  const xs = col(rows, 0), names = ["x", "y", "z"];
  [1, 2, 3].forEach((k, i) => p.band(xs, lo(k), hi(k), AXIS_COLORS[names[i]] + "33"));
  [1, 2, 3].forEach((k, i) => p.line(xs, col(rows, k), AXIS_COLORS[names[i]], 1.5));
  p.ctx.restore();
  const hasStd = rows.some((r) => r[4] !== null);
  const items = names.map((a) => ({ name: `drift ${a} [nm]`, color: AXIS_COLORS[a] }));
  items.push({ name: hasStd ? "±1σ" : "no σ (open-loop predictor)", color: "#88888855", box: true });
  p.legend(items);
}

const LEARN_SERIES = [[1, "max, whole table", "#3b528b"], [3, "max, central 80 % of each line", "#e6550d"],
  [4, "RMS, central 80 %", "#21908d"]];

function drawLearn(s) {
  const p = plots["plot-learn"];
  p.resize();
  const rows = s.learn;
  if (!rows.length) { p.frame([0, 1], [0, 1]); p.message("no learning run (afmctl learn --config …)"); return; }
  const xs = col(rows, 0), n = xs[xs.length - 1];
  const series = LEARN_SERIES.filter(([k]) => rows.some((r) => r[k] !== null));
  p.frame([Math.min(0, xs[0]), Math.max(1, n)], extent([[0], ...series.map(([k]) => col(rows, k))]));
  p.clip();
  for (const [k, , color] of series) { p.line(xs, col(rows, k), color, 2); }
  p.ctx.restore();
  const last = rows[rows.length - 1], ls = s.learnState || {};
  const items = series.map(([k, name, color]) => ({ name: `${name}: ${fmtN(last[k])} %`, color }));
  items.push({ name: `iteration ${ls.iteration}: ${ls.state}${ls.detail ? " — " + ls.detail : ""}`, color: "#888",
    box: true });
  p.legend(items);
}

function drawImage(s) {
  const p = plots["plot-image"];
  p.resize();
  if (!s.image) { p.frame([0, 1], [0, 1]); p.message("no image (afmctl sim --sample …)"); return; }
  drawHeightMap(p, s.image);
  p.legend([{ name: `${s.image.sample || "sample"}: ${s.image.samples} px samples`, color: "#21908d", box: true }]);
}

function fmtN(v, nd) {
  if (v === null || v === undefined || !isFinite(v)) { return "–"; }
  if (Number.isInteger(v) && (nd || 0) >= 9) { return v.toLocaleString("en-US"); }
  return Math.abs(v) >= 1e4 ? v.toExponential(2) : String(parseFloat(Number(v).toPrecision(nd || 3)));
}

function drawStats(s) {
  const st = (s.status && s.status.stats) || {}, b = st.bridge || {}, c = s.counts || {}, t = s.tracking || {};
  const us = (v) => (v === undefined ? "–" : `${fmtN(v * 1e6)} µs`);
  const rows = [
    ["state", (s.status && s.status.state) || "–", "samples", fmtN(st.samples, 9)],
    ["lateness p50 / p99 / max", `${us(st.lateness_p50_s)} / ${us(st.lateness_p99_s)} / ${us(st.lateness_max_s)}`,
      "missed deadlines", fmtN(st.missed_deadlines, 9)],
    ["errors / dropped records", `${fmtN(st.errors, 9)} / ${fmtN(st.dropped_records, 9)}`,
      "rejected inputs (service)", fmtN(s.status && s.status.rejected, 9)],
    ["setpoint batches / samples received", `${fmtN(c.setpoint_batches, 9)} / ${fmtN(c.setpoint_samples, 9)}`,
      "batch sequence gaps (viewer)", fmtN(c.seq_gaps, 9)],
    ["tracking error rms x / y", `${fmtN((t.rms_nm || [])[0])} / ${fmtN((t.rms_nm || [])[1])} nm`,
      "in % of scan range x / y", `${fmtN((t.rms_pct || [])[0])} / ${fmtN((t.rms_pct || [])[1])} %`],
    ["tips / drift / image / status msgs", `${fmtN(c.tips, 9)} / ${fmtN(c.drift, 9)} / ${fmtN(c.image, 9)} / ${fmtN(c.status, 9)}`,
      "messages rejected (viewer)", fmtN(c.rejected, 9)],
  ];
  document.querySelector("#stats tbody").innerHTML = rows.map((r) =>
    `<tr><td class="k">${r[0]}</td><td id="v-${slug(r[0])}">${esc(r[1])}</td><td class="k">${r[2]}</td>` +
    `<td id="v-${slug(r[2])}">${esc(r[3])}</td></tr>`).join("");
  const errs = (s.status && s.status.errors) || [];
  document.getElementById("errors").textContent = errs.length
    ? `last error: ${errs[errs.length - 1].source}: ${errs[errs.length - 1].message}` : (s.lastRejected || "");
  const badge = document.getElementById("state"), name = (s.status && s.status.state) || "no status";
  badge.textContent = name; badge.className = `state ${name.replace(/[^a-z]/g, "")}`;
}

function esc(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}

function slug(text) { return text.split(" ")[0].replace(/[^a-z]/g, ""); }

function render() {
  requestAnimationFrame(render);
  if (!state.dirty || !state.selected) { return; }
  state.dirty = false;
  const t0 = performance.now();
  drawSparks();
  const s = state.scanners[state.selected], tr = timeRange(s, WINDOW_S), all = timeRange(s, state.historyS);
  drawVolts(s, tr); drawTargets(s, tr); drawXY(s); drawError(s, tr); drawDrift(s, all); drawLearn(s); drawImage(s);
  drawStats(s);
  document.getElementById("clock").textContent = `t = ${fmtN(tr[1], 6)} s · frames ${state.frames}`;
  state.busyMs.render += performance.now() - t0;
}

function connect() {
  const link = document.getElementById("link");
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onopen = () => { link.textContent = "live"; };
  // each frame is answered once taken: the server sends the next only then (flow control)
  // (also after a frame this page could not take: the feed never stalls on one bad frame)
  ws.onmessage = (ev) => {
    const t0 = performance.now();
    try { ingest(JSON.parse(ev.data)); } finally {
      state.busyMs.ingest += performance.now() - t0;
      ws.send("next");
    }
  };
  ws.onclose = () => { link.textContent = "disconnected — retrying"; setTimeout(connect, 1000); };
}

document.getElementById("scanner").addEventListener("change", (ev) => { selectScanner(ev.target.value); });
window.addEventListener("resize", () => { state.dirty = true; });
setupPlots();
connect();
requestAnimationFrame(render);
