// Live plots without a library: a rolling buffer of samples and a plain <canvas> line plot.
// The service sends ~100 decimated points a second, so a 10 s window is ~1000 points per trace:
// redrawing them all on each event is cheap and keeps the code obvious.

/** Samples of one run over the last `windowS` seconds, one array per column. */
export class RollingWindow {
  constructor(columns, windowS = 10) {
    this.columns = columns;
    this.windowS = windowS;
    this.received = 0; // every point ever pushed (the window forgets, this does not)
    this.clear();
  }

  clear() {
    this.data = Object.fromEntries(this.columns.map((name) => [name, []]));
  }

  get length() {
    return this.data.t.length;
  }

  /** Append one `samples` event: {t: [...], col: [...]}; a missing column is stored as NaN (a gap). */
  push(event) {
    const t = event.t || [];
    if (t.length && this.length && t[0] < this.data.t[this.length - 1]) {
      this.clear(); // time went back: a new run's clock, not this one's
    }
    for (const name of this.columns) {
      const values = event[name];
      for (let i = 0; i < t.length; i += 1) {
        const v = values && values[i] !== null && values[i] !== undefined ? values[i] : NaN;
        this.data[name].push(v);
      }
    }
    this.received += t.length;
    this.trim();
  }

  /** Drop what fell out of the window (splice once, not shift per point). */
  trim() {
    const t = this.data.t;
    if (!t.length) return;
    const oldest = t[t.length - 1] - this.windowS;
    let first = 0;
    while (first < t.length && t[first] < oldest) first += 1;
    if (first > 0) {
      for (const name of this.columns) this.data[name].splice(0, first);
    }
  }
}

const MARGIN = { left: 62, right: 10, top: 22, bottom: 24 };

/** Draw y against t on `canvas`: autoscaled axes, a title with its unit, NaN breaks the line. */
export function drawPlot(canvas, t, y, { title, unit, color = "#1565c0" }) {
  const ctx = canvas.getContext("2d");
  const { width, height } = canvas;
  ctx.clearRect(0, 0, width, height);
  ctx.font = "12px system-ui, sans-serif";
  ctx.fillStyle = "#212121";
  ctx.fillText(`${title} [${unit}]`, MARGIN.left, 14);

  const [t0, t1] = extent(t);
  const [y0, y1] = padded(extent(y));
  if (!Number.isFinite(t0) || !Number.isFinite(y0)) {
    ctx.fillStyle = "#9e9e9e";
    ctx.fillText("no data", width / 2 - 20, height / 2);
    return;
  }
  const plotW = width - MARGIN.left - MARGIN.right;
  const plotH = height - MARGIN.top - MARGIN.bottom;
  const tSpan = t1 > t0 ? t1 - t0 : 1;
  const px = (v) => MARGIN.left + ((v - t0) / tSpan) * plotW;
  const py = (v) => MARGIN.top + (1 - (v - y0) / (y1 - y0)) * plotH;

  drawAxes(ctx, { t0, t1, y0, y1, px, py, plotW, plotH });

  ctx.strokeStyle = color;
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  let drawing = false;
  for (let i = 0; i < t.length; i += 1) {
    if (!Number.isFinite(y[i])) {
      drawing = false; // a gap: no segment across it
      continue;
    }
    if (drawing) ctx.lineTo(px(t[i]), py(y[i]));
    else ctx.moveTo(px(t[i]), py(y[i]));
    drawing = true;
  }
  ctx.stroke();
}

function drawAxes(ctx, { t0, t1, y0, y1, px, py, plotW, plotH }) {
  ctx.strokeStyle = "#bdbdbd";
  ctx.lineWidth = 1;
  ctx.strokeRect(MARGIN.left, MARGIN.top, plotW, plotH);
  ctx.fillStyle = "#616161";
  for (const v of ticks(y0, y1, 4)) {
    const y = py(v);
    ctx.beginPath();
    ctx.moveTo(MARGIN.left, y);
    ctx.lineTo(MARGIN.left + plotW, y);
    ctx.strokeStyle = "#eeeeee";
    ctx.stroke();
    ctx.fillText(formatTick(v), 4, y + 4);
  }
  for (const v of ticks(t0, t1, 5)) {
    ctx.fillText(`${formatTick(v)} s`, px(v) - 12, MARGIN.top + plotH + 16);
  }
}

function extent(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (Number.isFinite(v)) {
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
  }
  return lo <= hi ? [lo, hi] : [NaN, NaN];
}

/** A flat trace still gets a visible range; others get 5 % headroom. */
function padded([lo, hi]) {
  if (!Number.isFinite(lo)) return [lo, hi];
  const span = hi - lo;
  const pad = span > 0 ? span * 0.05 : Math.max(Math.abs(lo) * 0.1, 1e-3);
  return [lo - pad, hi + pad];
}

/** About `count` round tick values (1, 2, 5 × 10^k steps) inside [lo, hi]. */
function ticks(lo, hi, count) {
  const raw = (hi - lo) / count;
  if (!(raw > 0)) return [lo];
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw) || raw;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) out.push(v);
  return out;
}

function formatTick(v) {
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e5)) return v.toExponential(1);
  return Number(v.toPrecision(4)).toString();
}
