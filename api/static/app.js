// hdrig's browser page: log in, watch the rig, start experiments, follow a run live, stop it.
// Plain ES modules, no build step and no network beyond the service itself (labs have no internet).

import { ProblemError, errorLines, request, whenUnauthorized } from "./api.js";
import { RollingWindow, frameThrottled, makeChart } from "./charts.js";
import { el, fmt } from "./dom.js";
import { overlayRuns, renderJobResults, showRunResults } from "./results.js";

const RIG_POLL_MS = 1000; // the rig's state: often, it is what an operator watches
const LISTS_POLL_MS = 5000; // runs and jobs: they change when runs end, the stream tells us sooner
const WINDOW_S = 10; // live plots show the last ten seconds
const FINAL_RUN_STATUSES = new Set(["complete", "aborted", "interrupted", "failed"]);
const FINAL_JOB_STATUSES = new Set(["complete", "aborted", "failed"]);
const RECENT_RUNS = 25;

const PLOTS = [
  { id: "plot-omega", column: "omega_m", title: "speed ω_m", unit: "rad/s", color: "#1565c0" },
  { id: "plot-current", column: "i_a", title: "current i_a", unit: "A", color: "#c62828" },
  { id: "plot-position", column: "theta_m", title: "position θ_m", unit: "rad", color: "#2e7d32" },
  { id: "plot-error", column: "error", title: "tracking error (set-point − measured)", unit: "–", color: "#6a1b9a" },
];
const ACKED_ABORT = "hdrig-acknowledged-abort"; // localStorage: the last abort a person has reset
const STOP_RETRIES = 5; // a failed STOP is sent again, once a second, this many times
const STOP_RETRY_MS = 1000;

const $ = (id) => document.getElementById(id);

const page = {
  loggedIn: false,
  experiments: [],
  timers: [],
  live: null, // {runId, source, window, lastEventId}
  charts: new Map(), // plot id → uPlot
  rig: null, // the last GET /rig answer
  closed: null, // why the service said it closed (its `closed` event), until it answers again
};

// ---- small DOM helpers --------------------------------------------------------------------------

function showMessage(text, seconds = 8, tone = "") {
  const box = $("message");
  box.textContent = text;
  box.className = tone;
  box.hidden = false;
  clearTimeout(showMessage.timer);
  if (seconds) showMessage.timer = setTimeout(() => (box.hidden = true), seconds * 1000);
}

/** A problem document next to the form that caused it: title, detail and one line per field error. */
function showProblem(box, error) {
  box.replaceChildren();
  if (!error) {
    box.hidden = true;
    return;
  }
  const problem = error instanceof ProblemError ? error.problem : { title: String(error), detail: "" };
  box.append(el("strong", {}, `${problem.status ? problem.status + " " : ""}${problem.title || "error"}`));
  if (problem.detail) box.append(el("p", {}, problem.detail));
  const lines = errorLines(problem).filter((line) => line !== problem.detail);
  if (lines.length) box.append(el("ul", {}, lines.map((line) => el("li", {}, line))));
  box.hidden = false;
}

/** "aborted" + "aborted: quick stop" → "aborted: quick stop", not the word twice. */
function prefixed(word, text) {
  if (!text) return word;
  return text.startsWith(word) ? text : `${word}: ${text}`;
}

function formatSeconds(s) {
  if (s === null || s === undefined || !Number.isFinite(s)) return "";
  if (s < 90) return `${Math.round(s)} s`;
  return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

// ---- login --------------------------------------------------------------------------------------

function showLogin(why) {
  page.loggedIn = false;
  stopPolling();
  $("app").hidden = true;
  $("logout").hidden = true;
  $("rig-summary").hidden = true;
  $("login").hidden = false;
  if (why) showProblem($("login-problem"), why);
  $("login-key").focus();
}

async function login(event) {
  event.preventDefault();
  const key = $("login-key").value.trim();
  try {
    await request("POST", "/session", { key });
    $("login-key").value = ""; // the key is not kept: the HttpOnly cookie holds the session
    showProblem($("login-problem"), null);
    await enterApp();
  } catch (error) {
    showProblem($("login-problem"), error);
  }
}

async function logout() {
  try {
    await request("DELETE", "/session");
  } catch {
    // gone already: the login form is what we show either way
  }
  closeLive();
  showLogin();
}

async function enterApp() {
  page.loggedIn = true;
  $("login").hidden = true;
  $("app").hidden = false;
  if (!page.charts.size) makeLiveCharts(); // once the box is shown, so the plots take its width
  $("logout").hidden = false;
  await Promise.all([loadExperiments(), pollRig(), refreshRuns(), refreshJobs()]);
  startPolling();
}

// ---- polling ------------------------------------------------------------------------------------

/** Repeat `task` every `ms` after it finished, so a slow answer never piles requests up. */
function every(ms, task) {
  let timer;
  const loop = async () => {
    try {
      await task();
    } catch (error) {
      if (!(error instanceof ProblemError && error.status === 401)) console.warn(error);
    }
    if (page.loggedIn) timer = setTimeout(loop, ms);
  };
  timer = setTimeout(loop, ms);
  page.timers.push(() => clearTimeout(timer));
}

function startPolling() {
  stopPolling();
  every(RIG_POLL_MS, pollRig);
  every(LISTS_POLL_MS, refreshRuns);
  every(LISTS_POLL_MS, refreshJobs);
}

function stopPolling() {
  for (const cancel of page.timers) cancel();
  page.timers = [];
}

// ---- the rig ------------------------------------------------------------------------------------

async function pollRig() {
  let rig;
  try {
    rig = await request("GET", "/rig");
  } catch (error) {
    // Not answered: the bar must not keep the last green it had. A 401 is the login form's business.
    if (!(error instanceof ProblemError && error.status === 401)) renderUnreachable(error);
    throw error;
  }
  page.closed = null; // answered again: a service that closed is back
  renderRig(rig);
  // A run in progress that this page does not follow yet (started elsewhere, or before a reload).
  const run = currentRun(rig);
  const runId = run && run.id;
  if (runId && (!page.live || page.live.runId !== runId)) followRun(runId);
  // The notice follows the run's state even between its stream's events (queued → running).
  if (run && page.live && page.live.runId === runId && $("message").textContent.startsWith(`Run ${runId} queued`) && run.status !== "queued") {
    showMessage(`Run ${runId} ${run.status}.`, 0);
  }
}

/** The service names it `current_run` (api/schemas.py RigStatus); `run` is the older name. */
function currentRun(rig) {
  return rig.current_run || rig.run || null;
}

function renderRig(rig) {
  page.rig = rig;
  $("rig-summary").hidden = false;
  $("rig-name").textContent = rig.name || "";
  const mode = rig.mode || (rig.backend === "sim" ? "sim" : "hardware");
  const badge = $("rig-mode");
  badge.textContent = mode === "sim" ? "SIM" : "HARDWARE";
  badge.className = `badge ${mode === "sim" ? "sim" : "hardware"}`;
  renderState(rig.state);
  renderHealth(rig.health || {}, rig.state);
  renderRigDetails(rig);
}

/** The service is not answering: its state and health are unknown (grey), not the last ones seen. If it
 * said why it went away (the `closed` event), that stays: it says more than "unreachable". */
function renderUnreachable(error) {
  if (page.closed) return renderClosed(page.closed);
  renderUnknown("unreachable", `service unreachable (${error.message})`);
}

/** The service said it is closing (its event stream's last event): the rig is quick-stopped by now. */
function renderClosed(why) {
  renderUnknown("closed", `the service closed: ${why}`);
}

function renderUnknown(state, text) {
  renderState(state);
  const drive = $("rig-drive");
  drive.textContent = "drive unknown";
  drive.className = "chip health-unknown";
  const node = $("rig-health");
  node.textContent = text;
  node.dataset.level = "unknown";
  node.className = "chip health-unknown";
  $("reset").hidden = true;
}

function renderState(state) {
  const node = $("rig-state");
  node.textContent = state;
  node.dataset.state = state;
  node.className = `state ${state}`;
}

/** Green when healthy; amber after an abort until a person resets; red on a fault or a faulted rig. */
function renderHealth(health, state) {
  const faults = health.faults || [];
  const drive = $("rig-drive");
  drive.textContent = health.enabled ? "drive enabled" : "drive disabled";
  drive.className = `chip ${health.enabled ? "drive-on" : "drive-off"}`;
  const abort = health.last_abort && health.last_abort !== localStorage.getItem(ACKED_ABORT) ? health.last_abort : "";
  let level = "ok";
  let text = "healthy";
  if (faults.length || state === "faulted") {
    level = "bad";
    text = faults.length ? `fault: ${faults.map(fmt).join(", ")}` : "faulted";
  } else if (abort) {
    level = "warn";
    text = `last run ${prefixed("aborted", fmt(abort))}`;
  }
  const node = $("rig-health");
  node.textContent = text;
  node.dataset.level = level;
  node.className = `chip health-${level}`;
  $("reset").hidden = level === "ok";
}

/** Reset: leave the faulted state (the service) and take note of the abort a person has seen (here). */
async function resetRig() {
  const health = (page.rig && page.rig.health) || {};
  try {
    const rig = await request("POST", "/rig/reset");
    if (health.last_abort) localStorage.setItem(ACKED_ABORT, health.last_abort);
    renderRig(rig);
  } catch (error) {
    showMessage(`Reset failed: ${error.message}`, 0, "final-bad");
  }
}

function renderRigDetails(rig) {
  const run = currentRun(rig);
  const rows = [
    ["backend", rig.backend + (rig.pace ? ` (${rig.pace})` : "")],
    ["state", rig.state],
    ["run", run ? `${run.id} (${run.experiment}, ${run.status})` : "none"],
  ];
  if (rig.sample_rate_hz) rows.push(["sample rate", `${fmt(rig.sample_rate_hz)} Hz`]);
  if (rig.queued && rig.queued.length) rows.push(["queued", rig.queued.join(", ")]);
  for (const [name, value] of Object.entries(rig.limits || {})) rows.push([`limit ${name}`, fmt(value)]);
  $("rig-details").replaceChildren(...rows.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
}

/** The big red button: ask the service to stop everything. A failure is said beside the button and
 * the stop is sent again, once a second, a few times; pressing again always sends at once. */
async function stopRig(attempt = 0) {
  clearTimeout(stopRig.retry);
  const problem = $("stop-problem");
  try {
    const rig = await request("POST", "/rig/stop");
    problem.hidden = true;
    $("stop").classList.remove("failed");
    showMessage("Stop sent: the rig is quick-stopping.");
    if (rig && rig.state) renderRig(rig); // the answer is the rig's status right after the stop
  } catch (error) {
    $("stop").classList.add("failed");
    problem.hidden = false;
    if (error instanceof ProblemError && error.status === 401) {
      problem.textContent = "STOP NOT SENT: log in first (the service needs a key to move or stop the rig).";
      return;
    }
    const again = attempt < STOP_RETRIES;
    problem.textContent = `STOP FAILED (${error.message})${again ? `: retrying (${attempt + 1}/${STOP_RETRIES})` : ": press STOP again"}`;
    if (again) stopRig.retry = setTimeout(() => stopRig(attempt + 1), STOP_RETRY_MS);
  }
}

// ---- starting an experiment ---------------------------------------------------------------------

async function loadExperiments() {
  page.experiments = await request("GET", "/experiments");
  const select = $("experiment");
  const chosen = select.value;
  select.replaceChildren(...page.experiments.map((e) => el("option", { value: e.name }, e.name)));
  if (chosen && page.experiments.some((e) => e.name === chosen)) select.value = chosen;
  renderParams();
}

/** "time each pulse is on [s]" → ["time each pulse is on", "s"]. */
function splitUnit(description = "") {
  const match = description.match(/^(.*?)\s*\[([^\]]*)\]\s*$/);
  return match ? [match[1], match[2]] : [description, ""];
}

/** The JSON type of a property, through pydantic's `anyOf: [{type: X}, {type: "null"}]` for optionals. */
function typeOf(schema) {
  if (schema.type) return schema.type;
  const options = schema.anyOf || schema.oneOf || [];
  const first = options.find((o) => o.type && o.type !== "null");
  return first ? first.type : "string";
}

function itemsOf(schema) {
  if (schema.items) return schema.items;
  const options = schema.anyOf || schema.oneOf || [];
  const array = options.find((o) => o.type === "array");
  return (array && array.items) || {};
}

function rangeText(schema) {
  const parts = [];
  if (schema.minimum !== undefined) parts.push(`≥ ${schema.minimum}`);
  if (schema.exclusiveMinimum !== undefined) parts.push(`> ${schema.exclusiveMinimum}`);
  if (schema.maximum !== undefined) parts.push(`≤ ${schema.maximum}`);
  if (schema.exclusiveMaximum !== undefined) parts.push(`< ${schema.exclusiveMaximum}`);
  return parts.join(", ");
}

/** One input per property of the experiment's params_schema, its default filled in. */
function renderParams() {
  const experiment = page.experiments.find((e) => e.name === $("experiment").value);
  $("experiment-summary").textContent = experiment ? experiment.summary : "";
  const properties = (experiment && experiment.params_schema.properties) || {};
  const fields = Object.entries(properties).map(([name, schema]) => paramField(name, schema));
  $("params").replaceChildren(...fields);
  showProblem($("start-problem"), null);
}

function paramField(name, schema) {
  const type = typeOf(schema);
  const [text, unit] = splitUnit(schema.description);
  const input = el("input", { id: `param-${name}`, name, dataset: { param: name, type } });
  if (type === "boolean") {
    input.type = "checkbox";
    input.checked = Boolean(schema.default);
  } else {
    input.type = "text"; // not type=number: a bad value must reach the service, which names the field
    if (type === "number" || type === "integer") input.inputMode = "decimal";
    const value = schema.default;
    input.value = value === undefined || value === null ? "" : Array.isArray(value) ? value.join(", ") : String(value);
    if (type === "array") input.placeholder = "comma separated";
  }
  // The description says what it is in words ("time each pulse is on [s]"); the title is machine-made.
  const words = text ? text.charAt(0).toUpperCase() + text.slice(1) : schema.title || name;
  const hint = [name, rangeText(schema)].filter(Boolean).join(" · ");
  return el(
    "label",
    { dataset: { field: name } },
    el("span", { class: "label-text" }, words),
    input,
    el("span", { class: "unit" }, unit),
    hint ? el("span", { class: "hint" }, hint) : null,
  );
}

/** "1.5" → 1.5; anything not a number stays text, for the service to refuse by name. */
function parseScalar(text, type) {
  const trimmed = text.trim();
  if ((type === "number" || type === "integer") && trimmed !== "" && Number.isFinite(Number(trimmed))) {
    return Number(trimmed);
  }
  return trimmed;
}

/** The form's values as the params object; empty fields are left out (the service's default applies). */
function collectParams() {
  const params = {};
  const experiment = page.experiments.find((e) => e.name === $("experiment").value);
  const properties = (experiment && experiment.params_schema.properties) || {};
  for (const input of $("params").querySelectorAll("input[data-param]")) {
    const name = input.dataset.param;
    const type = input.dataset.type;
    if (type === "boolean") {
      params[name] = input.checked;
    } else if (type === "array") {
      const itemType = typeOf(itemsOf(properties[name] || {}));
      const items = input.value.split(",").map((s) => s.trim()).filter((s) => s !== "");
      params[name] = items.map((s) => parseScalar(s, itemType));
    } else if (input.value.trim() !== "") {
      params[name] = parseScalar(input.value, type);
    }
  }
  return params;
}

async function startRun(event) {
  event.preventDefault();
  const body = { experiment: $("experiment").value, params: collectParams(), queue: $("queue").checked };
  const button = $("start");
  button.disabled = true;
  try {
    const answer = await request("POST", "/runs", body);
    showProblem($("start-problem"), null);
    if (answer.kind) {
      // A campaign answers with its job: its runs are followed one by one as the rig poll finds them.
      showMessage(`Campaign ${answer.id} ${answer.status}.`);
    } else {
      showMessage(`Run ${answer.id} ${answer.status === "queued" ? "queued" : "started"}.`);
      followRun(answer.id);
    }
    refreshRuns().catch(() => {});
  } catch (error) {
    showProblem($("start-problem"), error);
  } finally {
    button.disabled = false;
  }
}

// ---- the live run -------------------------------------------------------------------------------

/** Follow one run's event stream; EventSource sends the cookie and resumes with Last-Event-ID itself. */
function followRun(runId) {
  closeLive();
  const window = new RollingWindow(["t", ...PLOTS.map((p) => p.column)], WINDOW_S);
  const source = new EventSource(`/api/v1/runs/${encodeURIComponent(runId)}/events`);
  // `begun`: this run's own first `run` event has arrived. A stream read from its start also carries the
  // rig-wide events logged before the run began (earlier stops, states): history, not this run's alarms.
  page.live = { runId, source, window, begun: false, ended: false };
  $("live-plots").hidden = false;
  $("live-run").textContent = runId;
  $("live-status").textContent = "";
  $("live-status").dataset.status = "";
  $("abort").hidden = false;
  $("alarms").replaceChildren();
  $("alarms").hidden = true;
  renderProgress({ fraction: 0, phase: "waiting", eta_s: null });
  renderPoints();
  drawPlots();

  const on = (kind, handler) =>
    source.addEventListener(kind, (message) => {
      if (page.live && page.live.source === source) handler(JSON.parse(message.data));
    });
  const afterBegin = (handler) => (data) => page.live.begun && handler(data);
  on("state", afterBegin((data) => renderState(data.state)));
  on("progress", renderProgress);
  on("samples", onSamples);
  on("alarm", afterBegin(showAlarm));
  on("run", onRunDocument);
  on("closed", onServiceClosed);
  source.onerror = () => {
    if (!page.live || page.live.source !== source) return;
    if (page.live.ended) {
      // The service ended the stream after the run's final document: done, no reconnecting.
      source.close();
    } else if (source.readyState === EventSource.CLOSED) {
      // The service refused the stream (401, 404...): it will not retry, the rig poll goes on.
      $("live-status").textContent = "stream closed";
    }
  };
}

/** The stream's last word when the service shuts down (SIGTERM...): why, after the run's final document. */
function onServiceClosed({ why }) {
  page.live.source.close();
  page.closed = why || "no reason given";
  renderClosed(page.closed);
  $("abort").hidden = true;
  showMessage(`The service closed: ${page.closed}.`, 0, "final-bad");
}

function closeLive() {
  if (page.live) page.live.source.close();
  page.live = null;
  $("live-plots").hidden = true; // no run followed yet: nothing to plot, the form comes first
  $("abort").hidden = true;
}

// The error's unit follows the segment's control mode: speed loops track rad/s, position loops rad.
const ERROR_UNITS = { velocity: "rad/s", position: "rad" };

function onSamples(data) {
  page.live.window.push(data);
  const errorPlot = PLOTS.find((p) => p.column === "error");
  const unit = ERROR_UNITS[String(data.mode).toLowerCase().replace(/^.*\./, "")] || "no set-point in this mode";
  if (unit !== errorPlot.unit) {
    errorPlot.unit = unit;
    makeLiveCharts(); // the title and axis carry the unit
  }
  renderPoints();
  drawPlots();
}

function renderPoints() {
  const window = page.live ? page.live.window : null;
  $("live-points").textContent = String(window ? window.length : 0);
  $("live-received").textContent = String(window ? window.received : 0);
}

/** One uPlot per live column, in boxes made here (the page has one container for them). */
function makeLiveCharts() {
  const holder = $("live-plots");
  const boxes = PLOTS.map((plot) => {
    let box = $(plot.id);
    if (!box) {
      box = el("div", { id: plot.id, class: "chart", dataset: { testid: plot.id } });
      holder.append(box);
    }
    return box;
  });
  PLOTS.forEach((plot, i) => {
    const old = page.charts.get(plot.id);
    if (old) old.destroy();
    const chart = makeChart(boxes[i], {
      title: `${plot.title} [${plot.unit}]`,
      xLabel: "t [s]",
      yLabel: `${plot.column === "error" ? "error" : plot.column} [${plot.unit}]`,
      series: [{ label: plot.title, color: plot.color }],
    });
    page.charts.set(plot.id, chart);
  });
  drawNow();
}

function drawNow() {
  const data = page.live ? page.live.window.data : { t: [] };
  for (const plot of PLOTS) {
    const chart = page.charts.get(plot.id);
    if (chart) chart.setData([data.t, data[plot.column] || data.t.map(() => null)]);
  }
}

// Many sample events a second, one redraw per frame at most.
const drawPlots = frameThrottled(drawNow);

function renderProgress({ fraction, phase, eta_s: eta }) {
  $("progress").value = fraction || 0;
  const percent = `${Math.round((fraction || 0) * 100)} %`;
  const left = formatSeconds(eta);
  $("progress-text").textContent = [percent, phase, left && `${left} left`].filter(Boolean).join(" · ");
}

/** Alarms stay on screen (red, on top of the live section) until the next run is followed. */
function showAlarm({ alarm, why }) {
  const box = $("alarms");
  box.append(el("p", { dataset: { alarm } }, `⚠ ${prefixed(alarm, why)}`));
  box.hidden = false;
}

function onRunDocument(run) {
  if (run.id !== page.live.runId) return;
  page.live.begun = true;
  const status = run.status;
  $("live-status").textContent = status;
  $("live-status").dataset.status = status;
  // The notice follows the run: "queued" gives way to "running", then to how it ended.
  if (!FINAL_RUN_STATUSES.has(status)) showMessage(`Run ${run.id} ${status}.`, 0);
  if (FINAL_RUN_STATUSES.has(status)) {
    // Not closed here: a service shutting down sends its `closed` event after this. The service ends the
    // stream after the final document and onerror closes it then, before EventSource reconnects.
    page.live.ended = true;
    $("abort").hidden = true;
    const fraction = status === "complete" ? 1 : $("progress").value;
    renderProgress({ fraction, phase: status, eta_s: null }); // no ETA once it has ended
    const tone = status === "complete" ? "final-ok" : "final-bad";
    showMessage(`Run ${run.id} ${run.reason ? prefixed(status, run.reason) : status}.`, status === "complete" ? 15 : 0, tone);
    // The row says how it ended even when the list cannot be fetched again (a service shutting down).
    const row = [...$("runs").tBodies[0].rows].find((r) => r.dataset.id === run.id);
    if (row) row.replaceWith(runRow(run, "")); // no signature: the next refresh replaces it
    refreshRuns().catch(() => {});
    refreshJobs().catch(() => {});
  }
}

async function abortRun() {
  if (!page.live) return;
  try {
    await request("POST", `/runs/${encodeURIComponent(page.live.runId)}/abort`);
    showMessage(`Abort of ${page.live.runId} sent.`);
  } catch (error) {
    showMessage(`Abort failed: ${error.message}`, 0);
  }
}

// ---- recent runs --------------------------------------------------------------------------------

async function refreshRuns() {
  // One page of the newest runs (and any queued), oldest first: the catalog itself may hold 100,000.
  const runs = await request("GET", `/runs?limit=${RECENT_RUNS}`);
  const recent = runs.slice(-RECENT_RUNS).reverse();
  page.recentRuns = recent;
  const body = $("runs").tBodies[0];
  const rows = new Map([...body.rows].map((row) => [row.dataset.id, row]));
  const wanted = recent.map((run) => {
    const signature = JSON.stringify([run.status, run.samples, run.metrics, run.artifacts, run.reason]);
    const row = rows.get(run.id);
    // Unchanged rows stay as they are, so an opened file list is not closed under the user.
    return row && row.dataset.signature === signature ? row : runRow(run, signature);
  });
  body.replaceChildren(...wanted);
}

function runRow(run, signature) {
  return el(
    "tr",
    { dataset: { id: run.id, status: run.status, signature } },
    el("td", {}, run.id),
    el("td", {}, run.experiment),
    el("td", { class: `status-${run.status}`, title: run.reason || "" }, run.status),
    el("td", {}, run.started ? new Date(run.started).toLocaleString() : "–"),
    el("td", {}, fmt(run.samples)),
    el("td", {}, metricsCell(run.metrics || {})),
    el("td", {}, artifactsCell(run)),
    el("td", {}, downloadLinks(run)),
  );
}

function metricsCell(metrics) {
  const entries = Object.entries(metrics).filter(([, v]) => typeof v !== "object" || v === null);
  const shown = entries.slice(0, 6).map(([k, v]) => `${k} = ${fmt(v)}`);
  const all = Object.entries(metrics).map(([k, v]) => `${k} = ${fmt(v)}`).join("\n");
  return el("span", { class: "metrics", title: all }, shown.join("; ") + (entries.length > 6 ? "; …" : ""));
}

/** Results are shown in the page (tables, plots), below the runs table, when asked for. */
function artifactsCell(run) {
  if (!FINAL_RUN_STATUSES.has(run.status)) return ""; // artifacts are written as a run ends
  const button = el("button", { type: "button", dataset: { results: run.id } }, "Show");
  button.setAttribute("aria-label", `show the results of run ${run.id}`);
  button.addEventListener("click", () => showRunResults(run, page.recentRuns || []));
  return button;
}

function downloadLinks(run) {
  if (!run.samples) return "";
  const base = `/api/v1/runs/${encodeURIComponent(run.id)}/data?format=`;
  return ["csv", "parquet", "mat"].map((format) =>
    el("a", { href: base + format, download: `${run.id}.${format}`, dataset: { format } }, format.toUpperCase()),
  );
}

// ---- fits and gap analyses ----------------------------------------------------------------------

async function refreshJobs() {
  const jobs = await request("GET", "/jobs");
  const analyses = jobs.filter((job) => job.kind === "fit" || job.kind === "gaps").reverse();
  $("jobs").tBodies[0].replaceChildren(...analyses.map(jobRow));
}

function jobRow(job) {
  const progress = job.progress || {};
  const progressText = FINAL_JOB_STATUSES.has(job.status)
    ? ""
    : `${Math.round((progress.fraction || 0) * 100)} % ${progress.phase || ""}`;
  return el(
    "tr",
    { dataset: { id: job.id, kind: job.kind, status: job.status } },
    el("td", {}, job.id),
    el("td", {}, job.kind),
    el("td", { class: `status-${job.status}`, title: job.error || "" }, job.status),
    el("td", {}, progressText),
    el("td", {}, job.error || resultSummary(job)),
    el("td", {}, reportLinks(job)),
  );
}

function resultSummary(job) {
  const result = job.result;
  if (!result || typeof result !== "object") return "";
  if (job.kind === "fit" && result.parameters) {
    const params = Object.values(result.parameters);
    const fitted = params.filter((p) => p.identifiable).length;
    const e = result.fit_error || {};
    const error = Number.isFinite(e.before) && Number.isFinite(e.after) ? `; fit error ${fmt(e.before)} → ${fmt(e.after)}` : "";
    return `${fitted} of ${params.length} parameters determined${error}`;
  }
  if (job.kind === "gaps") {
    const effects = (result.steps || []).map((s) => s.effect).join(", ") || "none";
    return `gap ${fmt(result.initial_gap)} → ${fmt(result.final_gap)}; effects added: ${effects}`;
  }
  return "";
}

/** A finished analysis opens in the page: tables, steps and its report, rendered. */
function reportLinks(job) {
  if (!job.result || typeof job.result !== "object") return "";
  const button = el("button", { type: "button", dataset: { open: job.id } }, "Show");
  button.setAttribute("aria-label", `show ${job.kind} ${job.id}`);
  button.addEventListener("click", () => renderJobResults(job));
  return button;
}

async function startAnalysis(event) {
  event.preventDefault();
  const collection = $("analysis-kind").value;
  const data = $("analysis-data").value.split(",").map((s) => s.trim()).filter(Boolean);
  try {
    await request("POST", `/${collection}`, { data, model: $("analysis-model").value.trim() });
    showProblem($("analysis-problem"), null);
    await refreshJobs();
  } catch (error) {
    showProblem($("analysis-problem"), error);
  }
}

// ---- start --------------------------------------------------------------------------------------

async function main() {
  $("stop").addEventListener("click", () => stopRig(0));
  const bar = $("bar");
  new ResizeObserver(() => document.documentElement.style.setProperty("--bar-h", `${bar.offsetHeight}px`)).observe(bar);
  $("login-form").addEventListener("submit", login);
  $("logout").addEventListener("click", logout);
  $("start-form").noValidate = true; // the service validates; its problem details are shown by the form
  $("start-form").addEventListener("submit", startRun);
  $("experiment").addEventListener("change", renderParams);
  $("abort").addEventListener("click", abortRun);
  $("reset").addEventListener("click", resetRig);
  $("runs-refresh").addEventListener("click", () => refreshRuns().catch(() => {}));
  $("analysis-form").addEventListener("submit", startAnalysis);
  $("overlay-form").addEventListener("submit", overlayRuns);
  whenUnauthorized((problem) => {
    // Only a session that ended under the user is worth a message; a first visit just gets the form.
    const wasIn = page.loggedIn;
    closeLive();
    showLogin(wasIn ? new ProblemError(401, { ...problem, title: "Session ended: log in again" }) : null);
  });
  try {
    await request("GET", "/rig"); // a session cookie from before may still be good
    await enterApp();
  } catch (error) {
    if (!(error instanceof ProblemError && error.status === 401)) showLogin(error);
  }
}

main();
