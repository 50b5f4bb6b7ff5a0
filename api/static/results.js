// Results in the page: a run's plots and tables (its artifacts), two runs overlaid, and a fit's or a
// gap analysis' tables and report, rendered (never raw Markdown, never HTML from the service).

import { API, request } from "./api.js";
import { joinSeries, makeChart } from "./charts.js";
import { el, fmt } from "./dom.js";

const $ = (id) => document.getElementById(id);
const TABLE_ROWS = 40; // rows of a table shown in the page; the CSV link has them all
const OVERLAY_POINTS = 4000; // per run: enough for the eye, cheap for the browser

/** Units of the columns the experiments write, by name (the tables' headers carry no units). */
const COLUMN_UNITS = [
  [/^(omega|speed|velocity)/, "rad/s"],
  [/^theta|_rad$|^angle/, "rad"],
  [/(^tau|torque|_nm)(_std)?$|^tau/, "N·m"],
  [/^i_|current|_a$/, "A"],
  [/^u$|_v$|voltage/, "V"],
  [/_hz$|^f(req)?$|frequency/, "Hz"],
  [/_s$|^t$/, "s"],
  [/_db$|gain_db|magnitude_db/, "dB"],
  [/phase/, "deg"],
];

export function unitOf(column) {
  for (const [pattern, unit] of COLUMN_UNITS) if (pattern.test(column)) return unit;
  return "";
}

function withUnit(column) {
  const unit = unitOf(column);
  return unit ? `${column} [${unit}]` : column;
}

function encodePath(relative) {
  return relative.split("/").map(encodeURIComponent).join("/");
}

export function artifactUrl(runId, relative) {
  return `${API}/runs/${encodeURIComponent(runId)}/artifacts/${encodePath(relative)}`;
}

async function fetchText(url) {
  const response = await fetch(url, { credentials: "same-origin" });
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.text();
}

/** A CSV of numbers (the experiments' tables, the data export) → {columns, rows}; text cells stay text. */
export function parseCsv(text) {
  const lines = text.split(/\r?\n/).filter((line) => line.trim() !== "" && !line.startsWith("#"));
  const columns = (lines.shift() || "").split(",").map((c) => c.trim());
  const rows = lines.map((line) =>
    line.split(",").map((cell) => {
      const number = Number(cell);
      return cell.trim() !== "" && Number.isFinite(number) ? number : cell.trim();
    }),
  );
  return { columns, rows };
}

function tableOf({ columns, rows }, limit = TABLE_ROWS) {
  const shown = rows.slice(0, limit);
  return el(
    "div",
    { class: "table-wrap", tabindex: "0" },
    el(
      "table",
      {},
      el("thead", {}, el("tr", {}, columns.map((c) => el("th", { scope: "col" }, withUnit(c))))),
      el("tbody", {}, shown.map((row) => el("tr", {}, row.map((v) => el("td", { class: typeof v === "number" ? "num" : "" }, fmt(v)))))),
    ),
    rows.length > limit ? el("p", { class: "summary" }, `first ${limit} of ${rows.length} rows`) : null,
  );
}

/** Sorted by x (uPlot draws along x), non-numbers as gaps. */
function sortedColumns(table, x, ys) {
  const ix = table.columns.indexOf(x);
  const rows = table.rows.filter((r) => typeof r[ix] === "number").sort((a, b) => a[ix] - b[ix]);
  return [
    rows.map((r) => r[ix]),
    ...ys.map((y) => {
      const iy = table.columns.indexOf(y);
      return rows.map((r) => (typeof r[iy] === "number" ? r[iy] : null));
    }),
  ];
}

/** |τ| = F_c + b·|ω| per direction (speed_sweep.coulomb_viscous_fit), drawn over the measured points. */
function frictionLaw(metrics, omega) {
  return omega.map((w) => {
    const side = w >= 0 ? "pos" : "neg";
    const level = metrics[`coulomb_${side}_nm`];
    const slope = metrics[`viscous_${side}_nm_s_rad`];
    if (!Number.isFinite(level) || !Number.isFinite(slope)) return null;
    return Math.sign(w) * (level + slope * Math.abs(w));
  });
}

const COLORS = ["#1565c0", "#c62828", "#2e7d32", "#6a1b9a", "#ef6c00"];

/** A plot of a table: the experiment's own (friction against speed with its law), else its numbers against the first. */
function chartOfTable(box, name, table, metrics) {
  const numeric = table.columns.filter((c, i) => table.rows.length && table.rows.every((r) => typeof r[i] === "number" || r[i] === ""));
  if (name === "friction_vs_velocity.csv" && numeric.includes("omega_m") && numeric.includes("torque_nm")) {
    const [omega, torque] = sortedColumns(table, "omega_m", ["torque_nm"]);
    const law = frictionLaw(metrics, omega);
    const series = [{ label: "measured torque", color: COLORS[0], points: true }];
    const data = [omega, torque];
    if (law.some((v) => v !== null)) {
      series.push({ label: "fitted law F_c + b·|ω|", color: COLORS[1], spanGaps: false });
      data.push(law);
    }
    return makeChart(box, { title: "friction against speed", xLabel: "ω_m [rad/s]", yLabel: "friction torque [N·m]", series, data });
  }
  if (numeric.length < 2 || table.rows.length < 2) return null;
  const [x, ...rest] = numeric;
  const ys = rest.filter((c) => !/_std$/.test(c)).slice(0, 4);
  const units = [...new Set(ys.map(unitOf))];
  return makeChart(box, {
    title: name.replace(/\.csv$/, "").replaceAll("_", " "),
    xLabel: withUnit(x),
    yLabel: units.length === 1 && units[0] ? `[${units[0]}]` : "",
    series: ys.map((y, i) => ({ label: withUnit(y), color: COLORS[i % COLORS.length], points: table.rows.length < 200 })),
    data: sortedColumns(table, x, ys),
  });
}

// ---- frequency responses (chirp) -------------------------------------------------------------------

/** The chirp's FRFs (rig/experiments/chirp.py FRFS): what each relates, and its unit. */
const FRFS = {
  "frf_speed.csv": ["plant i_cmd → ω_m", "rad/s/A"],
  "frf_load.csv": ["plant i_cmd → θ_l", "rad/A"],
  "frf_closed_loop.csv": ["position loop set-point → θ_l", "rad/rad"],
};
const FRF_COLUMNS = ["freq_hz", "magnitude_db", "phase_deg", "coherence", "magnitude_std_db", "phase_std_deg"];

function isFrf(name, table) {
  return name in FRFS && FRF_COLUMNS.every((c) => table.columns.includes(c));
}

/** y ± k·σ, a gap where either is missing. */
function shifted(y, sigma, k) {
  return y.map((v, i) => (v === null || sigma[i] === null ? null : v + k * sigma[i]));
}

/** Magnitude and phase against log frequency, each with its ±1 σ band (the spread over the periods)
 * and the coherence on a right axis, 0 to 1: where it is low the line is not to be trusted. */
function frfCharts(magnitudeBox, phaseBox, name, table) {
  const [what, unit] = FRFS[name];
  const [f, magnitude, magnitudeStd, phase, phaseStd, coherence] = sortedColumns(table, "freq_hz", [
    "magnitude_db",
    "magnitude_std_db",
    "phase_deg",
    "phase_std_deg",
    "coherence",
  ]);
  const one = (title, yLabel, y, sigma, color, fill) => ({
    title,
    xLabel: "f [Hz]",
    yLabel,
    xLog: true,
    series: [
      { label: title.split(": ").pop(), color },
      { label: "+1 σ", color: fill.replace("0.15", "0.5"), width: 1 },
      { label: "−1 σ", color: fill.replace("0.15", "0.5"), width: 1 },
      { label: "coherence", color: COLORS[2], scale: "coherence", dash: [5, 4], width: 1 },
    ],
    data: [f, y, shifted(y, sigma, 1), shifted(y, sigma, -1), coherence],
    bands: [[2, 3, fill]],
    right: { scale: "coherence", label: "coherence [–]", range: [0, 1] },
  });
  const magnitudeChart = makeChart(magnitudeBox, one(`${what}: magnitude`, `|H| [dB re 1 ${unit}]`, magnitude, magnitudeStd, COLORS[0], "rgba(21, 101, 192, 0.15)"));
  const phaseChart = makeChart(phaseBox, one(`${what}: phase`, "phase [deg]", phase, phaseStd, COLORS[1], "rgba(198, 40, 40, 0.15)"));
  magnitudeBox.dataset.lines = String(f.length);
  return [magnitudeChart, phaseChart];
}

// ---- set-point against output (step, sine, ramp) --------------------------------------------------

const TRACKING = new Set(["step", "sine", "ramp"]);
const ZERO_WINDOW_S = 0.1; // rig/experiments/tracking.py ZERO_WINDOW_S: the load angle's zero, before the program
const TRACK_POINTS = 6000; // per series: a step's whole run, a long sine thinned

/** A tracking run seen at the output as tracking.output_track sees it: from the program's start, angles
 * from where it started: set-point r·(θ_sp − θ_m0), load θ_l − θ_l0, motor r·(θ_m − θ_m0). */
async function outputTrack(run) {
  const doc = await request("GET", `/runs/${encodeURIComponent(run.id)}`);
  const meta = doc.meta || {};
  const segments = meta.segments || [];
  const r = meta.gear_ratio;
  if (!segments.length || !Number.isFinite(r) || !Number.isFinite(meta.theta_m0)) {
    throw new Error("the run's metadata has no segments, gear_ratio or theta_m0");
  }
  const url = `${API}/runs/${encodeURIComponent(run.id)}/data?format=csv&columns=setpoint,theta_l,theta_m`;
  const table = parseCsv(await fetchText(url));
  const column = (name) => table.rows.map((row) => row[table.columns.indexOf(name)]);
  const [t, setpoint, load, motor] = ["t", "setpoint", "theta_l", "theta_m"].map(column);
  const first = Math.min(...segments.map((s) => s.start));
  const last = Math.max(...segments.map((s) => s.start + s.cycles));
  const zeroRows = Math.round(ZERO_WINDOW_S * (meta.sample_rate_hz || 1000));
  const zero = load.slice(Math.max(0, first - zeroRows), first);
  const loadZero = zero.length ? zero.reduce((a, b) => a + b, 0) / zero.length : load[0];
  const step = Math.max(1, Math.ceil((last - first) / TRACK_POINTS));
  const track = { t: [], setpoint: [], load: [], motor: [] };
  for (let i = first; i < Math.min(last, t.length); i += step) {
    track.t.push(t[i] - t[first]);
    track.setpoint.push(r * (setpoint[i] - meta.theta_m0));
    track.load.push(load[i] - loadZero);
    track.motor.push(r * (motor[i] - meta.theta_m0));
  }
  return track;
}

/** Set-point and the two responses, and their errors, on one time axis each. */
async function trackingFigure(run) {
  const track = await outputTrack(run);
  const responseBox = el("div", { class: "chart", dataset: { testid: "tracking-response" } });
  const errorBox = el("div", { class: "chart", dataset: { testid: "tracking-error" } });
  const range = (values) => [Math.min(...values), Math.max(...values)].map((v) => fmt(v)).join(" to ");
  const figure = el(
    "figure",
    { class: "wide", dataset: { artifact: "tracking", setpointRange: range(track.setpoint), loadEnd: String(track.load.at(-1)) } },
    el("figcaption", {}, `${run.experiment}: set-point and output, at the output (gear ratio applied)`),
    responseBox,
    errorBox,
  );
  const minus = (y) => y.map((v, i) => v - track.setpoint[i]);
  const draw = () => {
    makeChart(responseBox, {
      title: "set-point and output",
      xLabel: "t from the program's start [s]",
      yLabel: "output angle [rad]",
      series: [
        { label: "set-point", color: "#424242", width: 2 },
        { label: "load θ_l", color: COLORS[0] },
        { label: "motor r·θ_m", color: COLORS[1], dash: [6, 3], width: 1 },
      ],
      data: [track.t, track.setpoint, track.load, track.motor],
    });
    makeChart(errorBox, {
      title: "tracking error (output − set-point)",
      xLabel: "t from the program's start [s]",
      yLabel: "error [rad]",
      series: [
        { label: "load θ_l − set-point", color: COLORS[0] },
        { label: "motor r·θ_m − set-point", color: COLORS[1], width: 1 },
      ],
      data: [track.t, minus(track.load), minus(track.motor)],
    });
  };
  return [figure, draw];
}

// ---- a run's results -----------------------------------------------------------------------------

/** Show one run's artifacts: plots as images, tables as tables with their plot, metrics as a table. */
export async function showRunResults(run, recentRuns) {
  const section = $("run-results");
  section.hidden = false;
  section.dataset.run = run.id;
  $("results-run").textContent = `${run.id} (${run.experiment}, ${run.status})`;
  const body = $("results-body");
  body.replaceChildren(el("p", {}, "loading…"));
  $("overlay").replaceChildren();
  fillOverlayChoices(run, recentRuns);
  section.scrollIntoView({ block: "start" });
  let files = [];
  try {
    files = (await request("GET", `/runs/${encodeURIComponent(run.id)}/artifacts`)).files;
  } catch (error) {
    body.replaceChildren(el("p", { class: "problem" }, error.message));
    return;
  }
  let metrics = run.metrics || {};
  if (files.includes("results.json")) {
    try {
      metrics = JSON.parse(await fetchText(artifactUrl(run.id, "results.json"))).metrics || metrics;
    } catch {
      // the catalog's metrics stay
    }
  }
  const figures = [];
  const entries = Object.entries(metrics).filter(([, v]) => typeof v !== "object" || v === null);
  if (entries.length) {
    figures.push(
      el(
        "figure",
        { dataset: { artifact: "metrics" } },
        el("figcaption", {}, "metrics"),
        tableOf({ columns: ["metric", "value"], rows: entries.map(([k, v]) => [k, v]) }, 100),
      ),
    );
  }
  const charts = [];
  if (TRACKING.has(run.experiment) && run.samples) {
    try {
      const [figure, draw] = await trackingFigure(run);
      figures.push(figure);
      charts.push(draw);
    } catch (error) {
      figures.push(el("figure", { dataset: { artifact: "tracking" } }, el("figcaption", {}, "set-point and output"), el("p", { class: "problem" }, error.message)));
    }
  }
  for (const path of files.filter((f) => f.endsWith(".csv"))) {
    const name = path.split("/").pop();
    const figure = el("figure", { dataset: { artifact: path } }, el("figcaption", {}, name));
    try {
      const table = parseCsv(await fetchText(artifactUrl(run.id, path)));
      const box = el("div", { class: "chart" });
      figure.append(box);
      if (isFrf(name, table)) {
        const phaseBox = el("div", { class: "chart" });
        figure.append(phaseBox);
        charts.push(() => frfCharts(box, phaseBox, name, table));
      } else {
        charts.push(() => chartOfTable(box, name, table, metrics));
      }
      figure.append(tableOf(table), el("a", { href: artifactUrl(run.id, path), download: `${run.id}-${name}` }, `download ${name}`));
    } catch (error) {
      figure.append(el("p", { class: "problem" }, error.message));
    }
    figures.push(figure);
  }
  for (const path of files.filter((f) => f.endsWith(".png"))) {
    const name = path.split("/").pop();
    figures.push(
      el(
        "figure",
        { dataset: { artifact: path } },
        el("figcaption", {}, name.replace(/\.png$/, "").replaceAll("_", " ")),
        el("img", { src: artifactUrl(run.id, path), alt: `${name.replace(/\.png$/, "").replaceAll("_", " ")} of run ${run.id}`, loading: "lazy" }),
      ),
    );
  }
  if (run.unit) figures.push(unitTrend(run));
  body.replaceChildren(...(figures.length ? figures : [el("p", {}, "this run has no results")]));
  for (const draw of charts) draw(); // once in the page, so each plot takes its box's width
}

const TREND_RUNS = 200; // the newest complete runs of the unit and experiment

/** A unit's trend: one metric of every complete run of the same experiment on the same gear unit,
 * against the run's start (GET /runs?unit=...&experiment=...). */
function unitTrend(run) {
  const select = el("select", { id: "trend-metric", "aria-label": "metric to follow" });
  const box = el("div", { class: "chart", dataset: { testid: "trend" } });
  const figure = el(
    "figure",
    { class: "wide", dataset: { artifact: "trend" } },
    el("figcaption", {}, `trend of unit ${run.unit} (${run.experiment})`),
    el("label", {}, "metric ", select),
    box,
  );
  const query = `unit=${encodeURIComponent(run.unit)}&experiment=${encodeURIComponent(run.experiment)}&status=complete&limit=${TREND_RUNS}`;
  request("GET", `/runs?${query}`)
    .then((runs) => {
      const dated = runs.filter((r) => r.started && r.metrics).sort((a, b) => Date.parse(a.started) - Date.parse(b.started));
      const names = [...new Set(dated.flatMap((r) => Object.keys(r.metrics).filter((k) => typeof r.metrics[k] === "number")))];
      select.replaceChildren(...names.map((n) => el("option", { value: n }, n)));
      const draw = () => {
        const name = select.value;
        const points = dated.filter((r) => Number.isFinite(r.metrics[name]));
        makeChart(box, {
          title: `${name}: ${points.length} runs of ${run.unit}`,
          xLabel: "run started",
          yLabel: name,
          xTime: true,
          series: [{ label: name, color: COLORS[0], points: true, spanGaps: true }],
          data: [points.map((r) => Date.parse(r.started) / 1000), points.map((r) => r.metrics[name])],
        });
        box.dataset.points = String(points.length);
      };
      select.addEventListener("change", draw);
      if (names.length) draw();
      else box.replaceChildren(el("p", {}, "no complete run of this unit has metrics"));
    })
    .catch((error) => box.replaceChildren(el("p", { class: "problem" }, error.message)));
  return figure;
}

function fillOverlayChoices(run, recentRuns) {
  const select = $("overlay-run");
  const others = recentRuns.filter((r) => r.id !== run.id && r.samples);
  select.replaceChildren(...others.map((r) => el("option", { value: r.id }, `${r.id} (${r.experiment}, ${r.status})`)));
  $("overlay-form").hidden = others.length === 0;
}

/** Every n-th point, so a long run stays a few thousand points. */
function thin(t, y, most) {
  const step = Math.max(1, Math.ceil(t.length / most));
  const tt = [];
  const yy = [];
  for (let i = 0; i < t.length; i += step) {
    tt.push(t[i]);
    yy.push(y[i]);
  }
  return [tt, yy];
}

async function runColumn(runId, column) {
  const url = `${API}/runs/${encodeURIComponent(runId)}/data?format=csv&columns=${encodeURIComponent(column)}`;
  const table = parseCsv(await fetchText(url));
  const it = table.columns.indexOf("t");
  const iy = table.columns.indexOf(column);
  const t = table.rows.map((r) => r[it]);
  const t0 = t.length ? t[0] : 0; // both from their own start
  return thin(t.map((v) => v - t0), table.rows.map((r) => (typeof r[iy] === "number" ? r[iy] : null)), OVERLAY_POINTS);
}

/** Two runs' column on one time axis, each from its own start. */
export async function overlayRuns(event) {
  event.preventDefault();
  const first = $("run-results").dataset.run;
  const second = $("overlay-run").value;
  const column = $("overlay-column").value;
  const box = $("overlay");
  box.replaceChildren(el("p", {}, "loading…"));
  try {
    const [a, b] = await Promise.all([runColumn(first, column), runColumn(second, column)]);
    const data = joinSeries([a, b]);
    makeChart(box, {
      title: `${column}: ${first} and ${second}`,
      xLabel: "t from the run's start [s]",
      yLabel: withUnit(column),
      series: [
        { label: first, color: COLORS[0], spanGaps: true },
        { label: second, color: COLORS[1], spanGaps: true },
      ],
      data,
    });
    box.dataset.runs = `${first},${second}`;
  } catch (error) {
    box.replaceChildren(el("p", { class: "problem" }, error.message));
  }
}

// ---- fits and gap analyses ------------------------------------------------------------------------

/** Minimal Markdown as DOM nodes: headings, tables, lists, paragraphs, `code`, **bold**, images. */
export function renderMarkdown(text, imageUrl) {
  const root = el("div", { class: "markdown" });
  const lines = text.split(/\r?\n/);
  let i = 0;
  const inline = (line) => {
    const nodes = [];
    const pattern = /(`[^`]+`|\*\*[^*]+\*\*|!\[[^\]]*\]\([^)]+\))/g;
    let last = 0;
    for (const match of line.matchAll(pattern)) {
      if (match.index > last) nodes.push(line.slice(last, match.index));
      const token = match[0];
      if (token.startsWith("`")) nodes.push(el("code", {}, token.slice(1, -1)));
      else if (token.startsWith("**")) nodes.push(el("strong", {}, token.slice(2, -2)));
      else {
        const [, alt, src] = token.match(/!\[([^\]]*)\]\(([^)]+)\)/);
        nodes.push(/^[\w./-]+$/.test(src) && !src.includes("..") ? el("img", { src: imageUrl(src), alt: alt || src }) : token);
      }
      last = match.index + token.length;
    }
    if (last < line.length) nodes.push(line.slice(last));
    return nodes;
  };
  const cells = (line) => line.trim().replace(/^\|/, "").replace(/\|$/, "").split("|").map((c) => c.trim());
  while (i < lines.length) {
    const line = lines[i];
    if (!line.trim()) {
      i += 1;
    } else if (/^#{1,6}\s/.test(line)) {
      const level = Math.min(6, line.match(/^#+/)[0].length + 2); // under the page's own h2
      root.append(el(`h${level}`, {}, inline(line.replace(/^#+\s*/, ""))));
      i += 1;
    } else if (line.trim().startsWith("|")) {
      const head = cells(line);
      i += 1;
      if (i < lines.length && /^\s*\|?\s*:?-/.test(lines[i])) i += 1;
      const rows = [];
      while (i < lines.length && lines[i].trim().startsWith("|")) rows.push(cells(lines[i++]));
      root.append(
        el(
          "div",
          { class: "table-wrap", tabindex: "0" },
          el("table", {}, el("thead", {}, el("tr", {}, head.map((h) => el("th", { scope: "col" }, inline(h))))), el("tbody", {}, rows.map((r) => el("tr", {}, r.map((c) => el("td", {}, inline(c))))))),
        ),
      );
    } else if (/^\s*([-*]|\d+\.)\s/.test(line)) {
      const ordered = /^\s*\d+\./.test(line);
      const list = el(ordered ? "ol" : "ul");
      while (i < lines.length && /^\s*([-*]|\d+\.)\s/.test(lines[i])) {
        list.append(el("li", {}, inline(lines[i].replace(/^\s*([-*]|\d+\.)\s+/, ""))));
        i += 1;
      }
      root.append(list);
    } else if (line.startsWith("```")) {
      const code = [];
      i += 1;
      while (i < lines.length && !lines[i].startsWith("```")) code.push(lines[i++]);
      i += 1;
      root.append(el("pre", {}, el("code", {}, code.join("\n"))));
    } else {
      const para = [];
      while (i < lines.length && lines[i].trim() && !/^(#|\||\s*[-*]\s|```)/.test(lines[i])) para.push(lines[i++]);
      root.append(el("p", {}, inline(para.join(" "))));
    }
  }
  return root;
}

function relativeTo(folder, path) {
  const base = folder ? folder.replace(/\/?$/, "/") : "";
  return base && path.startsWith(base) ? path.slice(base.length) : path.split("/").pop();
}

function fileUrl(collection, jobId, relative) {
  return `${API}/${collection}/${encodeURIComponent(jobId)}/files/${encodePath(relative)}`;
}

/** What the analysis was made from, for names: its runs, else what was asked ("latest"). */
function sourceName(job) {
  const data = (job.request && job.request.data) || [];
  const name = data.length === 1 ? data[0] : data.length ? `${data[0]}+${data.length - 1}` : "runs";
  return name.replace(/[^\w.-]+/g, "_");
}

function parameterTable(parameters) {
  const rows = Object.entries(parameters).map(([name, p]) =>
    el(
      "tr",
      { dataset: { param: name } },
      el("th", { scope: "row" }, name),
      el("td", { class: "num" }, fmt(p.estimate)),
      p.uncertainty === null || p.uncertainty === undefined
        ? el("td", { class: "not-determined" }, "not determined")
        : el("td", { class: "num" }, fmt(p.uncertainty)),
      el("td", { class: "num" }, fmt(p.start)),
      el("td", {}, p.stage),
      el("td", {}, p.note || ""),
    ),
  );
  return el(
    "div",
    { class: "table-wrap", tabindex: "0" },
    el(
      "table",
      { dataset: { testid: "fit-parameters" } },
      el("thead", {}, el("tr", {}, ["parameter", "estimate", "σ", "start", "stage", "note"].map((h) => el("th", { scope: "col" }, h)))),
      el("tbody", {}, rows),
    ),
  );
}

function recordsTable(records) {
  const columns = [...new Set(records.flatMap((r) => Object.keys(r)))];
  return tableOf({ columns, rows: records.map((r) => columns.map((c) => r[c] ?? "")) }, 100);
}

async function reportInto(box, collection, job, relative) {
  try {
    const text = await fetchText(fileUrl(collection, job.id, relative));
    const dir = relative.includes("/") ? relative.slice(0, relative.lastIndexOf("/") + 1) : "";
    box.replaceChildren(renderMarkdown(text, (src) => fileUrl(collection, job.id, dir + src)));
  } catch (error) {
    box.replaceChildren(el("p", { class: "problem" }, error.message));
  }
}

/** A fit's parameters with σ, its validation table, notes, the fitted model and report; a gap
 * analysis' steps, verdict and report. */
export async function renderJobResults(job) {
  const section = $("job-results");
  const body = $("job-body");
  const result = job.result || {};
  const collection = job.kind === "fit" ? "fits" : "gaps";
  section.hidden = false;
  section.dataset.job = job.id;
  section.dataset.kind = job.kind;
  $("results-job").textContent = `${job.kind} ${job.id} (${(job.request && job.request.data || []).join(", ")}; from ${job.request && job.request.model})`;
  const parts = [];
  let modelPath = null;
  if (job.kind === "fit") {
    const e = result.fit_error || {};
    parts.push(
      el(
        "figure",
        { class: "wide" },
        el("figcaption", {}, "parameters"),
        Number.isFinite(e.before) && Number.isFinite(e.after) ? el("p", {}, `${e.metric}: ${fmt(e.before)} → ${fmt(e.after)}`) : el("p", { class: "summary" }, `${e.metric || "fit error"}: not computed for these runs`),
        parameterTable(result.parameters || {}),
      ),
    );
    if (result.validation && result.validation.length) {
      parts.push(el("figure", { class: "wide", dataset: { testid: "validation" } }, el("figcaption", {}, "validation (simulation beside measurement and the article)"), recordsTable(result.validation)));
    }
    if (result.notes && result.notes.length) parts.push(el("figure", { class: "wide" }, el("figcaption", {}, "notes"), el("ul", {}, result.notes.map((n) => el("li", {}, n)))));
    modelPath = result.model_file;
  } else {
    parts.push(el("p", { class: "wide", dataset: { testid: "gaps-verdict" } }, el("strong", {}, "verdict: "), result.verdict || "–"));
    const steps = result.steps || [];
    const rows = [
      el("tr", {}, el("th", { scope: "row" }, "start"), el("td", {}, ""), el("td", { class: "num" }, fmt(result.initial_gap)), el("td", {}, "the starting model"), el("td", {}, "")),
      ...steps.map((s, i) =>
        el(
          "tr",
          { dataset: { step: String(i + 1) } },
          el("th", { scope: "row" }, String(i + 1)),
          el("td", {}, s.effect),
          el("td", { class: "num" }, `${fmt(s.gap_before)} → ${fmt(s.gap_after)}`),
          el("td", {}, s.evidence),
          el("td", {}, Object.entries(s.parameters || {}).map(([k, v]) => `${k} = ${fmt(v)}`).join(", ")),
        ),
      ),
    ];
    parts.push(
      el(
        "figure",
        { class: "wide", dataset: { testid: "gaps-steps" } },
        el("figcaption", {}, `steps (${result.metric || "gap"})`),
        el(
          "div",
          { class: "table-wrap", tabindex: "0" },
          el("table", {}, el("thead", {}, el("tr", {}, ["step", "effect added", "gap", "evidence", "parameters"].map((h) => el("th", { scope: "col" }, h)))), el("tbody", {}, rows)),
        ),
        el("p", {}, `final gap ${fmt(result.final_gap)}${steps.length ? "" : " (no effect was added)"}`),
      ),
    );
    if (result.unexplained) parts.push(el("p", { class: "wide" }, el("strong", {}, "unexplained: "), result.unexplained));
    if (result.rejected && result.rejected.length) parts.push(el("figure", { class: "wide" }, el("figcaption", {}, "tried and rejected"), el("ul", {}, result.rejected.map((r) => el("li", {}, r)))));
    modelPath = result.final_model;
  }
  if (modelPath) {
    const relative = relativeTo(result.folder, modelPath);
    const extension = relative.includes(".") ? relative.slice(relative.lastIndexOf(".")) : ".yaml";
    // Named after what it came from and the analysis that made it, not after its starting model.
    const name = `${sourceName(job)}-${job.id}${extension}`;
    parts.push(el("p", { class: "wide" }, el("a", { href: fileUrl(collection, job.id, relative), download: name, dataset: { testid: "model-download" } }, `download the fitted model (${name})`)));
  }
  const reports = (job.kind === "fit" ? [result.report] : result.report || []).filter(Boolean);
  const boxes = [];
  for (const path of reports) {
    const relative = relativeTo(result.folder, path);
    if (relative.endsWith(".md")) {
      const box = el("div", { class: "wide", dataset: { testid: "report" } }, "loading the report…");
      boxes.push([box, relative]);
      parts.push(box);
    } else if (relative.endsWith(".png")) {
      parts.push(el("figure", {}, el("figcaption", {}, relative), el("img", { src: fileUrl(collection, job.id, relative), alt: relative })));
    }
  }
  body.replaceChildren(...parts);
  section.scrollIntoView({ block: "start" });
  await Promise.all(boxes.map(([box, relative]) => reportInto(box, collection, job, relative)));
}
