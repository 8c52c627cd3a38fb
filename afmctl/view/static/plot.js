"use strict";
// Small canvas plots for afmctl view: line plots with labelled axes (units), legends,
// optional ±σ bands, equal-aspect x–y plots and a height map with a colour bar.
// No library and no network: everything the page needs ships with afmctl.

const AXIS_COLORS = { x: "#1f77b4", y: "#d62728", z: "#2ca02c" };

function niceStep(span, n) {
  const raw = span / Math.max(n, 1);
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  const m = raw / p;
  return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p;
}

function ticks(lo, hi, n) {
  if (!(hi > lo)) { return [lo]; }
  const step = niceStep(hi - lo, n);
  const out = [];
  // integer multiples of the step: no accumulated rounding (a tick at 0 reads "0")
  for (let k = Math.ceil(lo / step); k * step <= hi + step * 1e-9; k++) { out.push(parseFloat((k * step).toPrecision(12))); }
  return out;
}

function fmt(v) {
  const a = Math.abs(v);
  if (a === 0) { return "0"; }
  if (a >= 1e5 || a < 1e-3) { return v.toExponential(1); }
  return String(parseFloat(v.toPrecision(4)));
}

function extent(arrays, pad) {
  let lo = Infinity, hi = -Infinity;
  for (const a of arrays) {
    for (const v of a) { if (v !== null && isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; } }
  }
  if (!isFinite(lo)) { return [0, 1]; }
  if (hi - lo < 1e-12) { const d = Math.max(Math.abs(lo) * 0.05, 1e-3); return [lo - d, hi + d]; }
  const d = (hi - lo) * (pad || 0.05);
  return [lo - d, hi + d];
}

// A polyline into ctx's current path, points i = 0..n-1 at (sx(x(i)), sy(y(i))) [css px];
// null or non-finite points lift the pen. Runs of points inside one pixel column become
// at most four (first, lowest, highest, last: "M4"), which looks the same at that
// resolution and keeps a 6000-row trace cheap to draw on a slow machine.
function tracePath(c, n, x, y, sx, sy) {
  let pen = false, col = NaN, m = 0;            // m: points held for the current column
  let fx = 0, fy = 0, lx = 0, ly = 0, li = 0, hx = 0, hy = 0, hi = 0, ex = 0, ey = 0;
  const to = (px, py) => { if (pen) { c.lineTo(px, py); } else { c.moveTo(px, py); pen = true; } };
  const flush = () => {
    if (m === 0) { return; }
    to(fx, fy);                                 // first, then the extremes in their order, then last
    if (li < hi) { to(lx, ly); to(hx, hy); } else if (hi < li) { to(hx, hy); to(lx, ly); }
    if (m > 1) { to(ex, ey); }
    m = 0;
  };
  for (let i = 0; i < n; i++) {
    const xv = x(i), yv = y(i);
    if (xv === null || yv === null || !isFinite(xv) || !isFinite(yv)) { flush(); pen = false; continue; }
    const px = sx(xv), py = sy(yv), pc = Math.floor(px);
    if (m > 0 && pc !== col) { flush(); }
    if (m === 0) { col = pc; fx = lx = hx = ex = px; fy = ly = hy = ey = py; li = hi = i; m = 1; continue; }
    if (py < ly) { lx = px; ly = py; li = i; }
    if (py > hy) { hx = px; hy = py; hi = i; }
    ex = px; ey = py; m++;
  }
  flush();
}

class Plot {
  // opts: title, xlabel, ylabel, equal (equal aspect), colorbar (height map)
  constructor(canvas, opts) {
    this.canvas = canvas;
    this.opts = opts;
    this.ctx = canvas.getContext("2d");
    this.margin = { l: 64, r: opts.colorbar ? 84 : 12, t: 26, b: 40 };
  }

  resize() {
    const r = this.canvas.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, Math.round(r.width * dpr)), h = Math.max(50, Math.round(r.height * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) { this.canvas.width = w; this.canvas.height = h; }
    this.ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    this.w = r.width; this.h = r.height;
  }

  frame(xr, yr) {
    // axes box, ticks, labels, title; sets this.sx/this.sy (data → css px)
    const c = this.ctx, m = this.margin;
    c.clearRect(0, 0, this.w, this.h);
    let pw = this.w - m.l - m.r, ph = this.h - m.t - m.b;
    if (this.opts.equal) { [xr, yr] = this.equalize(xr, yr, pw, ph); }
    this.xr = xr; this.yr = yr;
    this.sx = (v) => m.l + (v - xr[0]) / (xr[1] - xr[0]) * pw;
    this.sy = (v) => m.t + ph - (v - yr[0]) / (yr[1] - yr[0]) * ph;
    c.strokeStyle = "#c8ced8"; c.lineWidth = 1; c.fillStyle = "#1d2330";
    c.font = "11px system-ui, 'DejaVu Sans', sans-serif";
    c.textAlign = "center"; c.textBaseline = "top";
    for (const v of ticks(xr[0], xr[1], pw / 80)) {
      const x = this.sx(v);
      c.beginPath(); c.moveTo(x, m.t); c.lineTo(x, m.t + ph); c.stroke();
      c.fillText(fmt(v), x, m.t + ph + 4);
    }
    c.textAlign = "right"; c.textBaseline = "middle";
    for (const v of ticks(yr[0], yr[1], ph / 40)) {
      const y = this.sy(v);
      c.beginPath(); c.moveTo(m.l, y); c.lineTo(m.l + pw, y); c.stroke();
      c.fillText(fmt(v), m.l - 4, y);
    }
    c.strokeStyle = "#5b6474"; c.strokeRect(m.l, m.t, pw, ph);
    c.textAlign = "center"; c.textBaseline = "bottom"; c.font = "12px system-ui, 'DejaVu Sans', sans-serif";
    c.fillText(this.opts.xlabel, m.l + pw / 2, this.h - 4);
    c.save(); c.translate(13, m.t + ph / 2); c.rotate(-Math.PI / 2); c.textBaseline = "middle";
    c.fillText(this.opts.ylabel, 0, 0); c.restore();
    c.font = "bold 13px system-ui, 'DejaVu Sans', sans-serif"; c.textAlign = "left"; c.textBaseline = "top";
    c.fillText(this.opts.title, m.l, 5);
    this.pw = pw; this.ph = ph;
  }

  equalize(xr, yr, pw, ph) {
    const sx = (xr[1] - xr[0]) / pw, sy = (yr[1] - yr[0]) / ph, s = Math.max(sx, sy);
    const cx = (xr[0] + xr[1]) / 2, cy = (yr[0] + yr[1]) / 2;
    return [[cx - s * pw / 2, cx + s * pw / 2], [cy - s * ph / 2, cy + s * ph / 2]];
  }

  clip() {
    const c = this.ctx, m = this.margin;
    c.save(); c.beginPath(); c.rect(m.l, m.t, this.pw, this.ph); c.clip();
  }

  line(xs, ys, color, width, dash) {
    const c = this.ctx;
    c.strokeStyle = color; c.lineWidth = width || 1.5; c.setLineDash(dash || []);
    c.beginPath();
    tracePath(c, xs.length, (i) => xs[i], (i) => ys[i], this.sx, this.sy);
    c.stroke(); c.setLineDash([]);
  }

  band(xs, lo, hi, color) {
    const c = this.ctx;
    c.fillStyle = color;
    let i = 0;
    while (i < xs.length) {
      while (i < xs.length && (lo[i] === null || hi[i] === null)) { i++; }
      const start = i;
      while (i < xs.length && lo[i] !== null && hi[i] !== null) { i++; }
      if (i - start < 2) { continue; }
      c.beginPath(); c.moveTo(this.sx(xs[start]), this.sy(hi[start]));
      for (let k = start + 1; k < i; k++) { c.lineTo(this.sx(xs[k]), this.sy(hi[k])); }
      for (let k = i - 1; k >= start; k--) { c.lineTo(this.sx(xs[k]), this.sy(lo[k])); }
      c.closePath(); c.fill();
    }
  }

  legend(items) {
    // items: [{name, color, dash, box}] drawn at the top right inside the plot
    const c = this.ctx, m = this.margin;
    c.font = "11px system-ui, 'DejaVu Sans', sans-serif"; c.textBaseline = "middle"; c.textAlign = "left";
    const widths = items.map((it) => c.measureText(it.name).width + 30);
    const w = Math.max(...widths, 40) + 8, h = items.length * 15 + 6;
    const x0 = m.l + this.pw - w - 6, y0 = m.t + 6;
    c.fillStyle = "rgba(255,255,255,0.85)"; c.fillRect(x0, y0, w, h);
    c.strokeStyle = "#c8ced8"; c.lineWidth = 1; c.strokeRect(x0, y0, w, h);
    items.forEach((it, k) => {
      const y = y0 + 10 + k * 15;
      if (it.box) { c.fillStyle = it.color; c.fillRect(x0 + 6, y - 5, 20, 10); }
      else {
        c.strokeStyle = it.color; c.lineWidth = 2; c.setLineDash(it.dash || []);
        c.beginPath(); c.moveTo(x0 + 6, y); c.lineTo(x0 + 26, y); c.stroke(); c.setLineDash([]);
      }
      c.fillStyle = "#1d2330"; c.fillText(it.name, x0 + 30, y);
    });
  }

  message(text) {
    const c = this.ctx;
    c.fillStyle = "#6b7280"; c.font = "12px system-ui, 'DejaVu Sans', sans-serif";
    c.textAlign = "center"; c.textBaseline = "middle";
    c.fillText(text, this.margin.l + this.pw / 2, this.margin.t + this.ph / 2);
  }
}

// viridis, 9 stops (matplotlib's), interpolated
const VIRIDIS = [[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
  [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]];

function viridis(f) {
  f = Math.min(1, Math.max(0, f)) * (VIRIDIS.length - 1);
  const i = Math.min(Math.floor(f), VIRIDIS.length - 2), t = f - i, a = VIRIDIS[i], b = VIRIDIS[i + 1];
  return [0, 1, 2].map((k) => Math.round(a[k] + (b[k] - a[k]) * t));
}

function drawHeightMap(plot, img) {
  // img: {x_nm:[lo,hi], y_nm:[lo,hi], height_nm: rows×cols (null = no sample), h_range_nm}
  plot.frame(img.x_nm, img.y_nm);
  if (plot.mapOf !== img) { plot.map = heightPixels(img); plot.mapOf = img; }   // once per new image
  const c = plot.ctx, x0 = plot.sx(img.x_nm[0]), x1 = plot.sx(img.x_nm[1]);
  const y0 = plot.sy(img.y_nm[1]), y1 = plot.sy(img.y_nm[0]);
  c.imageSmoothingEnabled = false;
  if (plot.map.width && plot.map.height) { c.drawImage(plot.map, x0, y0, x1 - x0, y1 - y0); }
  drawColorbar(plot, img.h_range_nm[0], img.h_range_nm[1]);
}

// the image's pixels (viridis over h_range_nm; no sample: transparent), one per cell
function heightPixels(img) {
  const rows = img.height_nm.length, cols = rows ? img.height_nm[0].length : 0;
  const [hlo, hhi] = img.h_range_nm, span = (hhi - hlo) || 1;
  const off = document.createElement("canvas");
  off.width = cols; off.height = rows;
  if (!cols || !rows) { return off; }
  const oc = off.getContext("2d"), data = oc.createImageData(cols, rows);
  for (let r = 0; r < rows; r++) {
    for (let k = 0; k < cols; k++) {
      const v = img.height_nm[r][k], p = ((rows - 1 - r) * cols + k) * 4;
      if (v === null) { data.data[p + 3] = 0; continue; }
      const rgb = viridis((v - hlo) / span);
      data.data[p] = rgb[0]; data.data[p + 1] = rgb[1]; data.data[p + 2] = rgb[2]; data.data[p + 3] = 255;
    }
  }
  oc.putImageData(data, 0, 0);
  return off;
}

function drawColorbar(plot, lo, hi) {
  const c = plot.ctx, m = plot.margin, x = m.l + plot.pw + 12, w = 12, top = m.t, h = plot.ph;
  const g = c.createLinearGradient(0, top + h, 0, top);
  VIRIDIS.forEach((rgb, i) => g.addColorStop(i / (VIRIDIS.length - 1), `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`));
  c.fillStyle = g; c.fillRect(x, top, w, h);
  c.strokeStyle = "#5b6474"; c.strokeRect(x, top, w, h);
  c.fillStyle = "#1d2330"; c.font = "11px system-ui, 'DejaVu Sans', sans-serif";
  c.textAlign = "left"; c.textBaseline = "middle";
  for (const v of ticks(lo, hi, 5)) { c.fillText(fmt(v), x + w + 3, top + h - (v - lo) / ((hi - lo) || 1) * h); }
  c.save(); c.translate(x + w + 56, top + h / 2); c.rotate(-Math.PI / 2); c.textAlign = "center";
  c.font = "12px system-ui, 'DejaVu Sans', sans-serif"; c.fillText("height [nm]", 0, 0); c.restore();
}
