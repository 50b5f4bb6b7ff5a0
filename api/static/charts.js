// Plots by uPlot (vendored: vendor/uplot/, MIT), loaded before this module as the global `uPlot`.
// Live plots keep a rolling window of samples and redraw at most once per animation frame, however
// many sample events arrive; result plots are drawn once from a run's tables.

const uPlot = globalThis.uPlot;

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

  /** Append one `samples` event: {t: [...], col: [...]}; a missing value is stored as null (a gap). */
  push(event) {
    const t = event.t || [];
    if (t.length && this.length && t[0] < this.data.t[this.length - 1]) {
      this.clear(); // time went back: a new run's clock, not this one's
    }
    for (const name of this.columns) {
      const values = event[name];
      const column = this.data[name];
      for (let i = 0; i < t.length; i += 1) {
        const v = values ? values[i] : null;
        column.push(v === undefined || (typeof v === "number" && !Number.isFinite(v)) ? null : v);
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

const HEIGHT_PX = 200;

/** Keep a chart as wide as its box (the page reflows from 360 px to 1920 px). */
function fitWidth(chart, box) {
  const resize = () => {
    const width = Math.max(200, Math.floor(box.clientWidth));
    if (width !== chart.width) chart.setSize({ width, height: chart.height });
  };
  new ResizeObserver(resize).observe(box);
  resize();
}

/**
 * A uPlot chart in `box`: `series` are {label, color, points?, spanGaps?, dash?, scale?, width?}; x is
 * labelled `xLabel`. `xLog`: a logarithmic x (frequencies). `bands`: [upper, lower, fill] pairs of series
 * (1-based, as in `data`) filled between. `right`: {scale, label, range} a second y axis on the right for
 * the series with that `scale`. Returns the uPlot instance (call setData on it).
 */
export function makeChart(box, { title, xLabel, yLabel, series, data, xTime = false, xLog = false, bands = [], right = null }) {
  box.replaceChildren();
  // A log x spans the data, not whole decades (uPlot's default): 0.5 to 20 Hz is not drawn to 100 Hz.
  const scales = { x: xLog ? { time: false, distr: 3, range: (u, min, max) => [min, max] } : { time: xTime } };
  const axes = [
    { label: xLabel, stroke: "#212121", grid: { stroke: "#eee" } },
    { label: yLabel, stroke: "#212121", grid: { stroke: "#eee" }, size: 60 },
  ];
  if (right) {
    scales[right.scale] = right.range ? { range: right.range } : {};
    axes.push({ scale: right.scale, label: right.label, side: 1, stroke: "#212121", grid: { show: false }, size: 50 });
  }
  const options = {
    title,
    width: Math.max(200, Math.floor(box.clientWidth) || 360),
    height: HEIGHT_PX,
    scales,
    legend: { show: series.length > 1 },
    axes,
    bands: bands.map(([upper, lower, fill]) => ({ series: [upper, lower], fill })),
    series: [
      { label: xLabel },
      ...series.map((s) => {
        const one = {
          label: s.label,
          stroke: s.color,
          width: s.points ? 0 : (s.width ?? 1.5),
          spanGaps: Boolean(s.spanGaps),
          points: s.points ? { show: true, size: 6, stroke: s.color, fill: s.color } : { show: false },
        };
        // Only when given: uPlot takes an explicit `undefined` over its defaults (scale "y", solid).
        if (s.dash) one.dash = s.dash;
        if (s.scale) one.scale = s.scale;
        return one;
      }),
    ],
  };
  const chart = new uPlot(options, data || [[], ...series.map(() => [])], box);
  fitWidth(chart, box);
  return chart;
}

/** Redraw at most once per animation frame: sample events can come faster than the screen. */
export function frameThrottled(draw) {
  let queued = false;
  return () => {
    if (queued) return;
    queued = true;
    requestAnimationFrame(() => {
      queued = false;
      draw();
    });
  };
}

/** Series of several x grids on one x axis (uPlot wants one shared, sorted x). */
export function joinSeries(tables) {
  return uPlot.join(tables);
}
