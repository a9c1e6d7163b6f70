/* QuickNav's browser view: plain JavaScript over the REST API (the same routes as the SDK), no build
   step. Charts: uPlot (shipped in vendor/). Every request goes to this server; nothing loads from
   elsewhere, so the page works offline. */
"use strict";

const POLL_MS = 1500;
const STATUSES = ["queued", "running", "succeeded", "failed", "cancelled"];
const KINDS = ["train", "sweep", "eval", "trial"];
const RAY_COLOURS = { 0: "#9e9e9e", 1: "#d62728", 2: "#2ca02c" }; // as in the GIFs: none / wall / goal
const main = document.getElementById("main");

// ------------------------------------------------------------------ helpers
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(el.dataset, v);
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/** replaceChildren that skips null and false (the DOM would write them as text). */
function fill(el, ...children) {
  el.replaceChildren(...children.flat().filter((c) => c !== null && c !== undefined && c !== false));
  return el;
}

class ApiError extends Error {
  constructor(status, detail) {
    super(typeof detail === "string" ? detail : JSON.stringify(detail));
    this.status = status;
    this.detail = detail;
  }
}

/** fetch JSON from the API with the session cookie; a 401 shows the sign-in form. */
async function api(path, { method = "GET", body } = {}) {
  const headers = { Accept: "application/json" };
  if (method !== "GET") headers["X-QuickNav-Web"] = "1";
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const resp = await fetch(path, {
    method, headers, credentials: "same-origin",
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (resp.status === 204) return null;
  const text = await resp.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!resp.ok) {
    if (resp.status === 401 && !path.startsWith("/auth/")) showLogin();
    throw new ApiError(resp.status, data && data.detail !== undefined ? data.detail : data);
  }
  return data;
}

const short = (id) => id.slice(0, 8);
const pct = (x) => (x === null || x === undefined || Number.isNaN(x) ? "–" : `${(100 * x).toFixed(1)} %`);
function num(x, digits = 2) {
  if (x === null || x === undefined || Number.isNaN(Number(x))) return "–";
  const v = Number(x);
  if (Math.abs(v) >= 1e6) return `${(v / 1e6).toFixed(2)}M`;
  if (Math.abs(v) >= 1e4) return `${(v / 1e3).toFixed(1)}k`;
  if (Number.isInteger(v)) return String(v);
  if (Math.abs(v) < 1e-3 && v !== 0) return v.toExponential(2);
  return v.toFixed(digits);
}
function age(t) {
  if (!t) return "–";
  const s = Math.max(0, Date.now() / 1000 - t);
  if (s < 60) return `${Math.round(s)} s ago`;
  if (s < 3600) return `${Math.round(s / 60)} min ago`;
  if (s < 86400) return `${(s / 3600).toFixed(1)} h ago`;
  return `${(s / 86400).toFixed(1)} days ago`;
}
function duration(a, b) {
  if (!a) return "–";
  const s = (b || Date.now() / 1000) - a;
  return s < 120 ? `${s.toFixed(1)} s` : `${(s / 60).toFixed(1)} min`;
}
const finished = (job) => ["succeeded", "failed", "cancelled"].includes(job.status);
const badge = (status) => h("span", { class: `badge ${status}`, dataset: { status } }, status);
function progressBar(p) {
  return h("span", { class: "progress" }, h("span", { class: "bar" }, h("span", { style: `width:${Math.round(100 * p)}%` })),
    `${Math.round(100 * p)} %`);
}
const compiling = (job) => job.status === "running" && (job.metrics || {}).phase === "compiling";
/** The last line of an error: the exception, without the traceback above it. */
function reason(error) {
  const lines = String(error || "").trim().split("\n").filter((l) => l.trim());
  return lines.length ? lines[lines.length - 1].trim() : "";
}
/** How far a job got: a bar while it runs, "compiling 12 s" before its first chunk, why it failed. */
function jobProgress(job) {
  if (compiling(job)) {
    const since = job.metrics.phase_since || job.started_at;
    const s = since ? Math.max(0, Math.round(Date.now() / 1000 - since)) : 0;
    return h("span", { class: "progress compiling", dataset: { phase: "compiling" } }, h("span", { class: "bar pulse" }, h("span")),
      `compiling ${s} s`);
  }
  if (job.status === "failed") {
    return h("span", { class: "reason", title: job.error || "" }, reason(job.error) || "failed (no reason given)");
  }
  if (job.status === "cancelled") return h("span", { class: "muted" }, `stopped at ${Math.round(100 * job.progress)} %`);
  if (job.waiting) {
    // the reason in a few words (the whole of it in the title and on the job's page)
    const short = job.waiting.includes("data volume is full") ? "waiting: the data volume is full"
      : "waiting for a worker that can run it";
    return h("span", { class: "reason waiting", title: job.waiting }, short);
  }
  return progressBar(job.progress);
}

/** One line that says how a job is doing, by kind. */
function metricsSummary(job) {
  const m = job.metrics || {};
  if (job.kind === "train") {
    if (m.env_steps === undefined) return "";
    return `success ${pct(m.success_rate)} · return ${num(m.mean_return, 1)} · ${num(m.env_steps)} steps`;
  }
  if (job.kind === "eval") {
    if (m.success_rate !== undefined) return `success ${pct(m.success_rate)} · SPL ${num(m.spl, 3)}`;
    if (m.episodes !== undefined) return `${m.episodes_done} / ${m.episodes} episodes`;
    return "";
  }
  if (job.kind === "trial") {
    const r = job.result || {};
    return `batch ${job.config.batch} of sweep ${short(job.config.parent)}` +
      (r.trials !== undefined ? ` · ${r.trials} trial${r.trials === 1 ? "" : "s"} told` : "");
  }
  if (m.total === undefined) return "";
  const running = m.batches_running ? ` · ${m.batches_running} batch${m.batches_running === 1 ? "" : "es"} running` : "";
  return `${m.finished} / ${m.total} trials${running} · best ${num(m.best_value, 3)}`;
}

let timers = [];
function every(ms, fn) {
  const tick = async () => {
    try { await fn(); } catch (e) { if (!(e instanceof ApiError && e.status === 401)) console.error(e); }
  };
  tick();
  const id = setInterval(tick, ms);
  timers.push(id);
  return id;
}
function stopTimers() { timers.forEach(clearInterval); timers = []; }

function showError(where, e) {
  const box = h("div", { class: "error-box", role: "alert" }, e instanceof ApiError ? describe(e) : String(e));
  where.prepend(box);
  setTimeout(() => box.remove(), 8000);
}
function describe(e) {
  if (Array.isArray(e.detail)) return e.detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("\n");
  return `${e.status}: ${typeof e.detail === "string" ? e.detail : JSON.stringify(e.detail)}`;
}

async function cancelJob(job, where) {
  try { await api(`/jobs/${job.id}/cancel`, { method: "POST" }); } catch (e) { showError(where, e); }
}
async function deleteJob(job, where, after) {
  if (!confirm(`Delete ${job.kind} job ${short(job.id)} and all its files?`)) return;
  try { await api(`/jobs/${job.id}`, { method: "DELETE" }); if (after) after(); } catch (e) { showError(where, e); }
}

// ------------------------------------------------------------------ sign-in
function showLogin(message) {
  stopTimers();
  main.replaceChildren(h("form", { class: "login", id: "login", onsubmit: async (ev) => {
    ev.preventDefault();
    const token = ev.target.querySelector("input").value;
    try {
      await api("/auth/session", { method: "POST", body: { token } });
      location.reload();
    } catch (e) {
      showLogin(e.status === 401 ? "That is not the server's token." : describe(e));
    }
  } },
  h("h1", {}, "Sign in"),
  h("p", {}, "This server has QUICKNAV_API_TOKEN set. Enter the token to see its jobs."),
  message ? h("div", { class: "error-box", role: "alert" }, message) : null,
  h("input", { type: "password", name: "token", autocomplete: "current-password", placeholder: "API token",
    "aria-label": "API token", required: true }),
  h("button", { class: "primary", type: "submit" }, "Sign in")));
}

async function sessionBar() {
  const el = document.getElementById("session");
  try {
    const s = await api("/auth/session");
    if (s.token_required && s.authenticated) {
      el.replaceChildren(h("button", { onclick: async () => {
        await api("/auth/session", { method: "DELETE" }); location.href = "/";
      } }, "Sign out"));
    }
    return s;
  } catch { return { token_required: false, authenticated: true }; }
}

// ------------------------------------------------------------------ jobs page
function jobsPage() {
  const params = new URLSearchParams(location.search);
  const select = (name, values) => h("select", { name, onchange: () => {
    const q = new URLSearchParams();
    for (const s of main.querySelectorAll(".filters select")) if (s.value) q.set(s.name, s.value);
    history.replaceState(null, "", q.toString() ? `/?${q}` : "/");
    refresh();
  } }, h("option", { value: "" }, `all ${name === "status" ? "statuses" : "kinds"}`),
  values.map((v) => h("option", { value: v, selected: params.get(name) === v }, v)));
  const body = h("tbody");
  const count = h("span", { class: "muted" });
  main.replaceChildren(
    h("h1", {}, "Jobs"),
    h("div", { class: "filters" }, select("status", STATUSES), select("kind", KINDS), count,
      h("a", { href: "/ui/submit" }, "+ new training job")),
    h("table", { id: "jobs" }, h("thead", {}, h("tr", {}, ["Job", "Kind", "Status", "Progress",
      "Latest metrics", "Created", ""].map((t) => h("th", {}, t)))), body));

  async function refresh() {
    const q = new URLSearchParams({ limit: "100" });
    for (const s of main.querySelectorAll(".filters select")) if (s.value) q.set(s.name, s.value);
    const page = await api(`/jobs?${q}`);
    count.textContent = page.count > page.data.length ? `showing ${page.data.length} of ${page.count}`
      : `${page.count} job${page.count === 1 ? "" : "s"}`;
    body.replaceChildren(...page.data.map((job) => h("tr", { dataset: { id: job.id, status: job.status } },
      h("td", { class: "mono" }, h("a", { href: `/ui/jobs/${job.id}` }, short(job.id))),
      h("td", {}, job.kind),
      h("td", {}, badge(job.status), job.cancel_requested && !finished(job) ? " cancelling" : ""),
      h("td", { class: "progress-cell" }, jobProgress(job)),
      h("td", {}, metricsSummary(job), (job.warnings || []).length
        ? h("span", { class: "warn", title: job.warnings.join("\n") }, ` ⚠ ${job.warnings.length} warning${job.warnings.length === 1 ? "" : "s"}`) : null),
      h("td", { title: new Date(job.created_at * 1000).toLocaleString() }, age(job.created_at)),
      h("td", {}, finished(job)
        ? h("button", { class: "danger", onclick: () => deleteJob(job, main, refresh) }, "Delete")
        : h("button", { disabled: job.cancel_requested, onclick: async () => { await cancelJob(job, main); refresh(); } },
          "Cancel")))));
    if (!page.data.length) body.append(h("tr", {}, h("td", { colspan: 7, class: "muted" }, "No jobs yet.")));
  }
  every(POLL_MS, refresh);
}

// ------------------------------------------------------------------ job page
function lineChart(title, label, colour, yRange) {
  const box = h("div", { class: "chart", dataset: { points: "0" } }, h("div", { class: "title" }, title));
  const opts = {
    width: 380, height: 220, legend: { show: false },
    scales: { x: { time: false }, y: yRange ? { range: yRange } : {} },
    axes: [{ label: "env steps", values: (u, vals) => vals.map((v) => num(v)) }, { label }],
    series: [{}, { label, stroke: colour, width: 2, points: { show: true, size: 5 } }],
  };
  const plot = new uPlot(opts, [[], []], box);
  return {
    el: box,
    set(xs, ys) {
      plot.setData([xs, ys]);
      box.dataset.points = String(xs.length);
    },
  };
}

function trainSection(job, sec) {
  const charts = [
    lineChart("Success rate", "success rate", "#2ca02c", [0, 1]),
    lineChart("Episode return", "mean return", "#1f77b4"),
    lineChart("Episode length", "mean steps", "#ff7f0e"),
  ];
  sec.append(h("h2", {}, "Learning curve"), h("div", { class: "charts", id: "curve" }, charts.map((c) => c.el)));
  return async () => {
    const { metrics } = await api(`/jobs/${job.id}/metrics`);
    const rows = metrics.filter((r) => r.env_steps !== undefined);
    const xs = rows.map((r) => r.env_steps);
    const col = (k) => rows.map((r) => (r[k] === undefined ? null : r[k]));
    charts[0].set(xs, col("success_rate"));
    charts[1].set(xs, col("mean_return"));
    charts[2].set(xs, col("mean_length"));
  };
}

function evalTable(metrics) {
  const ms = (d) => (d ? `${num(d.mean, 1)} ± ${num(d.std, 1)}` : "–");
  const ci = metrics.success_ci95 || [];
  const rows = [
    ["Episodes", num(metrics.episodes)],
    ["Success rate (95 % Wilson interval)", `${pct(metrics.success_rate)}  [${pct(ci[0])}, ${pct(ci[1])}]`],
    ["SPL", num(metrics.spl, 3)],
    ["Steps to goal (successes)", ms(metrics.steps_to_goal_successes)],
    ["Steps (failures counted as the limit)", ms(metrics.steps_to_goal_failures_as_limit)],
    ["Collisions per episode", num(metrics.collisions_per_episode, 2)],
    ["Success without a collision", pct(metrics.collision_free_success_rate)],
    ["Timeout rate", pct(metrics.timeout_rate)],
    ["Return", ms(metrics.return)],
  ];
  return h("table", { id: "eval-metrics", style: "max-width:640px" },
    h("tbody", {}, rows.map(([k, v]) => h("tr", {}, h("th", {}, k), h("td", { class: "num" }, v)))));
}

function historyChart() {
  const box = h("div", { class: "chart", dataset: { points: "0" } }, h("div", { class: "title" }, "Optimisation history"));
  const plot = new uPlot({
    width: 460, height: 240, legend: { show: true },
    scales: { x: { time: false } },
    axes: [{ label: "trial", incrs: [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000] }, { label: "objective" }],
    series: [{ label: "trial" },
      { label: "value", stroke: "#1f77b4", width: 0, points: { show: true, size: 7, fill: "#1f77b4" } },
      { label: "best so far", stroke: "#d62728", width: 2, points: { show: false } }],
  }, [[], [], []], box);
  return { el: box, set(data) { plot.setData(data); box.dataset.points = String(data[0].length); } };
}

function sweepSection(job, sec) {
  const best = h("div", { id: "best-trial" });
  const chart = historyChart();
  const table = h("table", { id: "trials" });
  sec.append(h("h2", {}, "Best trial"), best, h("h2", {}, "Optimisation history"), chart.el,
    h("h2", {}, "Trials"), table);
  return async () => {
    let study;
    try { study = await api(`/jobs/${job.id}/artifacts/trials.json`); } catch (e) {
      if (e.status !== 404) throw e;
      const why = finished(job) ? "This sweep kept no trials.json (it ran on an older QuickNav)." : "No trial has finished yet.";
      table.replaceChildren(h("tr", {}, h("td", { class: "muted" }, why)));
      return;
    }
    const { trials, objective } = study;
    const maximize = study.direction === "maximize";
    const names = [...new Set(trials.flatMap((t) => Object.keys(t.params || {})))].sort();
    const done = trials.filter((t) => t.state === "COMPLETE" && t.value !== null);
    let top = null;
    for (const t of done) if (!top || (maximize ? t.value > top.value : t.value < top.value)) top = t;
    const xs = [], vals = [], bests = [];
    let running = null;
    for (const t of trials) {
      if (t.state !== "COMPLETE" || t.value === null) continue;
      running = running === null ? t.value : (maximize ? Math.max(running, t.value) : Math.min(running, t.value));
      xs.push(t.number); vals.push(t.value); bests.push(running);
    }
    chart.set([xs, vals, bests]);
    best.replaceChildren(top
      ? h("p", {}, `Trial ${top.number}: ${objective} = ${num(top.value, 4)} with `,
        h("code", {}, Object.entries(top.params).map(([k, v]) => `${k}=${num(v, 4)}`).join("  ")))
      : h("p", { class: "muted" }, "No trial has completed yet."));
    // beside the objective, what each trial's policy did: a success rate bought with collisions
    // (a policy that slides along the walls to the goal) shows here, whatever the objective
    const outcome = [["Success", (m) => pct(m.success_rate)],
      ["Collisions / episode", (m) => num(m.collisions_per_episode, 2)],
      ["Success without a collision", (m) => pct(m.collision_free_success_rate)]];
    const shown = trials.some((t) => t.metrics) ? outcome : [];
    table.replaceChildren(
      h("thead", {}, h("tr", {}, h("th", {}, "#"), h("th", {}, "State"), h("th", { class: "num" }, `Value (${objective})`),
        shown.map(([label]) => h("th", { class: "num" }, label)),
        names.map((n) => h("th", { class: "num" }, n.replace(/^algorithm\./, ""))), h("th", { class: "num" }, "Seconds"),
        h("th", {}, "Error"))),
      h("tbody", {}, trials.map((t) => h("tr", { class: top && t.number === top.number ? "best" : "" },
        h("td", {}, t.number), h("td", {}, t.state.toLowerCase()), h("td", { class: "num" }, num(t.value, 4)),
        shown.map(([, cell]) => h("td", { class: "num" }, t.metrics ? cell(t.metrics) : "–")),
        names.map((n) => h("td", { class: "num" }, num(t.params[n], 4))),
        h("td", { class: "num" }, num(t.seconds, 1)), h("td", { class: "muted" }, t.error || "")))));
  };
}

function artifactsSection(job, sec) {
  const list = h("table", { id: "artifacts" });
  const images = h("div", { class: "images", id: "images" });
  const policy = h("p", { id: "policy-download", hidden: true });
  sec.append(h("h2", {}, "Artifacts"), policy, images, h("div", { style: "height:10px" }), list);
  let shown = "";
  return async () => {
    const { artifacts } = await api(`/jobs/${job.id}/artifacts`);
    const key = artifacts.map((a) => `${a.name}:${a.bytes}`).join("|");
    if (key === shown) return; // unchanged: keep the images as they are (a GIF would restart)
    shown = key;
    const url = (a) => `/jobs/${job.id}/artifacts/${a.name.split("/").map(encodeURIComponent).join("/")}`;
    const exported = ["policy.onnx", "policy.json"].map((n) => artifacts.find((a) => a.name === n));
    policy.hidden = !exported.every(Boolean);
    if (!policy.hidden) {
      // the trained policy as a file a robot runs with onnxruntime alone (docs: Exporting policies)
      policy.replaceChildren("Trained policy, to run without QuickNav: ",
        ...exported.flatMap((a, i) => [i ? " + " : "", h("a", { href: url(a), download: a.name }, a.name)]),
        h("span", { class: "muted" }, ` (${exported[0].bytes.toLocaleString()} bytes; the manifest says what goes in and out)`));
    }
    const pics = artifacts.filter((a) => /\.(png|gif)$/i.test(a.name));
    images.replaceChildren(...pics.map((a) => h("figure", {},
      h("a", { href: url(a), target: "_blank" }, h("img", { src: `${url(a)}?v=${a.bytes}`, alt: a.name })),
      h("figcaption", {}, a.name))));
    list.replaceChildren(h("thead", {}, h("tr", {}, h("th", {}, "File"), h("th", { class: "num" }, "Bytes"))),
      h("tbody", {}, artifacts.length ? artifacts.map((a) => h("tr", {},
        h("td", {}, h("a", { href: url(a), target: "_blank" }, a.name)), h("td", { class: "num" }, a.bytes.toLocaleString())))
        : h("tr", {}, h("td", { class: "muted", colspan: 2 }, "No files yet."))));
  };
}

/** The eval jobs of a trained policy, newest first (their config names the train job's full id). */
async function evalsOf(job) {
  const { data } = await api("/jobs?kind=eval&limit=500");
  return data.filter((e) => e.config && e.config.source === job.id);
}

/** 'map "NAME"' for an eval job that drove a map its policy did not train on (an uploaded map by
    its name in ``maps``, quoted as the replay and the pictures quote it; a file by its name), else
    null. */
function mapOf(e, job, maps) {
  const env = e.config && e.config.env, own = job.config && job.config.env;
  if (!env || env.rooms !== "maps" || !env.maps) return null;
  const names = (env.maps.test && env.maps.test.length ? env.maps.test : env.maps.train) || [];
  const same = own && own.rooms === "maps" && JSON.stringify(own.maps) === JSON.stringify(env.maps);
  const shown = (n) => { const m = maps.find((x) => x.ref === n); return m ? `"${m.name}"` : n.split("/").pop(); };
  return same ? null : `map ${names.map(shown).join(", ")}`;
}

/** A train job's evaluations: run one on held-out rooms or an uploaded map, and the list of those run so far. */
function evalsSection(job, sec) {
  const episodes = h("input", { id: "eval-episodes", type: "number", min: 1, max: 100000, value: 100,
    "aria-label": "episodes", style: "width:90px" });
  // also run the episodes at each fixed level of lidar noise, dropout, bias, latency, wheel asymmetry
  const robust = h("input", { id: "eval-robustness", type: "checkbox" });
  // drive through the safety layer (the collision monitor a robot runs between policy and motors)
  const shield = h("input", { id: "eval-shield", type: "checkbox" });
  // where: the policy's own held-out rooms, or an uploaded map, which the server lays on the grid
  // at the policy's cell size with a step limit from its longest path (POST /jobs/eval "map")
  const where = h("select", { id: "eval-where", "aria-label": "where" }, h("option", { value: "" }, "held-out rooms"));
  let maps = [];
  const run = h("button", { class: "primary", id: "run-eval", onclick: async () => {
    run.disabled = true;
    const body = { job_id: job.id, episodes: Number(episodes.value), split: "test", robustness: robust.checked, shield: shield.checked };
    const map = maps.find((m) => m.id === where.value);
    if (map) body.map = map.ref;
    try {
      const ev = await api("/jobs/eval", { method: "POST", body });
      location.href = `/ui/jobs/${ev.id}`;
    } catch (e) { run.disabled = false; showError(sec, e); }
  } }, "Evaluate");
  // the uploaded maps, read once per page (the section refreshes every few seconds: a list
  // rebuilt under an open drop-down would close it, and each refresh would ask for it again)
  let mapsRead = false;
  const mapOptions = async () => {
    if (mapsRead) return;
    try { maps = (await api("/maps")).data; } catch (e) { return; } // held-out rooms only; asked again next refresh
    mapsRead = true;
    where.append(...maps.map((m) => h("option", { value: m.id }, `map: ${m.name}`)));
  };
  const controls = h("div", { class: "controls", id: "eval-controls" });
  const table = h("table", { id: "evals" });
  sec.append(h("h2", {}, "Evaluations"), controls, table);
  return async () => {
    await mapOptions();  // the choice of where to evaluate, and the names of maps in the list
    fill(controls, job.status === "succeeded" ? [run, episodes, h("span", { class: "muted" }, "episodes, fixed seeds, on"), where,
      h("label", { title: "success and SPL at fixed levels of lidar noise, beam dropout, range bias, latency and wheel asymmetry (robustness.png)" },
        robust, " and at each sensor perturbation"),
      h("label", { title: "each command goes through the safety layer: its forward part is scaled down (0.5, 0.25, 0) where the next control period would bring the robot within 1 cm of a lidar return" },
        shield, " through the safety layer")]
      : h("span", { class: "muted" }, "An evaluation can run once the job has succeeded."));
    const evals = await evalsOf(job);
    table.dataset.pending = String(evals.filter((e) => !finished(e)).length);
    table.dataset.count = String(evals.length);
    fill(table, h("thead", {}, h("tr", {}, ["Eval job", "Status", "Rooms", "Episodes", "Success", "SPL", "Created"]
      .map((t) => h("th", {}, t)))),
    h("tbody", {}, evals.length ? evals.map((e) => {
      const m = (e.result && e.result.metrics) || {};
      return h("tr", { dataset: { id: e.id, status: e.status } },
        h("td", { class: "mono" }, h("a", { href: `/ui/jobs/${e.id}` }, short(e.id))),
        h("td", {}, badge(e.status)), h("td", {}, mapOf(e, job, maps) || (e.config.split === "test" ? "held out" : e.config.split),
          e.config.shield ? h("span", { class: "muted", title: "driven through the safety layer" }, " · safety layer") : null),
        h("td", { class: "num" }, num(e.config.episodes)),
        h("td", { class: "num" }, e.status === "failed" ? h("span", { class: "reason" }, reason(e.error)) : pct(m.success_rate)),
        h("td", { class: "num" }, num(m.spl, 3)), h("td", {}, age(e.created_at)));
    }) : h("tr", {}, h("td", { colspan: 7, class: "muted" }, "No evaluation of this job yet."))));
  };
}

function eventLog(job, sec) {
  const log = h("div", { class: "events", id: "events" });
  sec.append(h("h2", {}, "Events"), log);
  const source = new EventSource(`/jobs/${job.id}/events`);
  const line = (ev) => {
    let data = {};
    try { data = JSON.parse(ev.data); } catch { /* keep-alives carry no data */ }
    const { type, time, metrics, ...rest } = data;
    const when = time ? new Date(time * 1000).toLocaleTimeString() : "";
    const fields = { ...rest, ...(metrics || {}) }; // a progress event's metrics, flattened
    const value = (k, v) => (k.endsWith("_since") && typeof v === "number" // a moment, not a quantity
      ? new Date(v * 1000).toLocaleTimeString() : typeof v === "number" ? num(v, 3) : JSON.stringify(v));
    const text = Object.entries(fields).filter(([, v]) => v !== null)
      .map(([k, v]) => `${k}=${value(k, v)}`).join(" ");
    log.append(h("div", {}, `${when} ${ev.type} ${text}`.trim()));
    log.scrollTop = log.scrollHeight;
    if (["succeeded", "failed", "cancelled", "deleted"].includes(ev.type)) source.close();
  };
  for (const t of ["queued", "started", "progress", "resumed", "succeeded", "failed", "cancelled", "deleted",
    "retry", "requeued", "warning", "message"]) source.addEventListener(t, line);
  source.onerror = () => { if (source.readyState === EventSource.CLOSED) log.append(h("div", { class: "muted" }, "(stream closed)")); };
  return source;
}

async function jobPage(id) {
  let job;
  try { job = await api(`/jobs/${encodeURIComponent(id)}`); } catch (e) {
    if (e.status !== 401) main.replaceChildren(h("h1", {}, "Job not found"), h("p", {}, describe(e)), h("a", { href: "/" }, "All jobs"));
    return;
  }
  const head = h("div", { id: "job-head" });
  const kindSec = h("section");
  const artSec = h("section");
  const logSec = h("section");
  const config = h("section", {}, h("h2", {}, "Config (resolved: what runs)"),
    h("pre", { id: "config" }, JSON.stringify(job.config, null, 2)),
    h("details", {}, h("summary", {}, "Request as sent"), h("pre", {}, JSON.stringify(job.request, null, 2))));
  main.replaceChildren(head, kindSec, artSec, logSec, config);
  const updaters = [];
  if (job.kind === "train") updaters.push(trainSection(job, kindSec));
  if (job.kind === "sweep") updaters.push(sweepSection(job, kindSec));
  const evalBox = h("div");
  if (job.kind === "eval") kindSec.append(h("h2", {}, "Held-out metrics"), evalBox);
  const evalSec = h("section");
  if (job.kind === "train") {
    kindSec.after(evalSec);
    const refreshEvals = evalsSection(job, evalSec);
    updaters.push(refreshEvals); // with the job's own updates while it runs
    // and on their own once it has finished: its evaluations keep changing
    every(2 * POLL_MS, () => (finished(job) ? refreshEvals() : null));
  }
  updaters.push(artifactsSection(job, artSec));
  eventLog(job, logSec);

  function renderHead() {
    const canReplay = (job.kind === "train" && job.status === "succeeded") || (job.kind === "eval" && job.status === "succeeded");
    fill(head,
      h("h1", {}, `${job.kind[0].toUpperCase()}${job.kind.slice(1)} job`, h("span", { class: "mono" }, short(job.id)),
        badge(job.status), job.status === "failed" ? null : jobProgress(job),
        finished(job) ? h("button", { class: "danger", onclick: () => deleteJob(job, head, () => { location.href = "/"; }) }, "Delete")
          : h("button", { id: "cancel", disabled: job.cancel_requested, onclick: () => cancelJob(job, head) },
            job.cancel_requested ? "Cancelling…" : "Cancel"),
        canReplay ? h("a", { href: `/ui/jobs/${job.id}/replay`, id: "replay-link" }, h("button", { class: "primary" }, "▶ Replay")) : null),
      h("dl", { class: "meta" },
        h("dt", {}, "Created"), h("dd", {}, new Date(job.created_at * 1000).toLocaleString()),
        h("dt", {}, "Run time"), h("dd", {}, duration(job.started_at, job.finished_at)),
        h("dt", {}, "Worker"), h("dd", { class: "mono" }, job.worker || "–"),
        h("dt", {}, "Attempts"), h("dd", {}, job.attempts),
        job.kind === "eval" && job.config.source ? [h("dt", {}, "Policy"), h("dd", { style: "grid-column: span 3" },
          "trained by ", h("a", { href: `/ui/jobs/${job.config.source}`, id: "source-job" }, `train job ${short(job.config.source)}`))] : null,
        h("dt", {}, "Latest"), h("dd", { style: "grid-column: span 3" }, metricsSummary(job) || "–")),
      job.error ? h("div", { class: "error-box", id: "job-error" }, job.error) : null,
      job.waiting ? h("div", { class: "note-box", id: "job-waiting" }, job.waiting) : null,
      (job.warnings || []).length ? h("div", { class: "note-box", id: "job-warnings" },
        h("strong", {}, "Warnings: "), "the numbers were kept, but", h("ul", {}, job.warnings.map((w) => h("li", {}, w)))) : null,
      job.result && job.result.note ? h("div", { class: "note-box" }, job.result.note) : null);
    if (job.kind === "eval") {
      const m = job.result ? job.result.metrics : null;
      evalBox.replaceChildren(m ? evalTable(m) : h("p", { class: "muted" }, metricsSummary(job) || "Waiting for the first episodes…"));
    }
  }
  renderHead();
  let last = false;
  const id0 = every(POLL_MS, async () => {
    if (last) return;
    Object.assign(job, await api(`/jobs/${job.id}`)); // the sections hold this same object
    renderHead();
    await Promise.all(updaters.map((u) => u()));
    if (finished(job)) { last = true; clearInterval(id0); }
  });
}

// ------------------------------------------------------------------ submit form
const FORM_FIELDS = [
  ["total_steps", "Env steps", "total env steps to train"],
  ["num_envs", "Parallel envs", "envs stepped in one batch"],
  ["seed", "Seed", "training seed"],
  ["algorithm.learning_rate", "Learning rate", "optimiser step size"],
  ["env.grid_size", "Grid size", "cells per side of a room"],
  ["env.max_steps", "Episode step limit", "truncation limit"],
];

function getPath(obj, dotted) {
  return dotted.split(".").reduce((o, k) => (o && typeof o === "object" ? o[k] : undefined), obj);
}
function parseValue(text) {
  const t = text.trim();
  try { return JSON.parse(t); } catch { return t; }
}

async function submitPage() {
  const [presets, maps] = await Promise.all([api("/presets"), api("/maps")]);
  const names = Object.keys(presets);
  const want = new URLSearchParams(location.search).get("preset");
  const wantMap = new URLSearchParams(location.search).get("map");
  const roomsSel = h("select", { name: "rooms", id: "rooms" },
    h("option", { value: "" }, "the preset's (carved caves unless it says otherwise)"),
    h("option", { value: "floorplan" }, "generated floor plans"),
    maps.data.map((m) => h("option", { value: m.id, selected: m.id === wantMap }, `map: ${m.name} (${metres(m.width_m)} × ${metres(m.height_m)})`)));
  const presetSel = h("select", { name: "preset", id: "preset" }, names.map((n) => h("option", { value: n, selected: n === want }, n)));
  const desc = h("p", { class: "muted", id: "preset-description" });
  const general = h("div");
  const fieldRow = (key, label, help, control) => h("div", { class: "field", dataset: { key } },
    h("label", { for: `f-${key}` }, label, h("small", {}, help)), control, h("div", { class: "field-error" }));
  const inputs = FORM_FIELDS.map(([key, label, help]) => fieldRow(key, label, `${help} (${key})`,
    h("input", { id: `f-${key}`, name: key, inputmode: "decimal", autocomplete: "off" })));
  const extra = fieldRow("overrides", "More overrides", "one key=value per line, e.g. env.lidar_beams=32",
    h("textarea", { id: "f-overrides", name: "overrides", rows: 3, placeholder: "network.hidden_sizes=[128,128]" }));
  const form = h("form", { class: "submit", id: "submit-form", novalidate: true },
    h("div", { class: "field", dataset: { key: "preset" } }, h("label", { for: "preset" }, "Preset"), presetSel,
      h("div", { class: "field-error" })),
    desc,
    fieldRow("env.rooms", "Rooms", "where rooms come from: a map sets env.maps.train, and the grid that holds it at 0.5 m cells", roomsSel),
    inputs, extra, general,
    h("button", { class: "primary", type: "submit", id: "submit" }, "Submit training job"));
  main.replaceChildren(h("h1", {}, "New training job"),
    h("p", { class: "muted" }, "Start from a preset; a field left empty keeps the preset's value (shown greyed)."), form);

  const showPreset = () => {
    const p = presets[presetSel.value];
    desc.textContent = p.description || "";
    for (const [key] of FORM_FIELDS) {
      const v = getPath(p.resolved || p.config, key);
      form.querySelector(`[name="${key}"]`).placeholder = v === undefined ? "" : String(v);
    }
  };
  presetSel.addEventListener("change", showPreset);
  showPreset();

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    for (const f of form.querySelectorAll(".field")) { f.classList.remove("invalid"); f.querySelector(".field-error").textContent = ""; }
    general.replaceChildren();
    const overrides = {};
    const origin = {};
    for (const [key] of FORM_FIELDS) {
      const v = form.querySelector(`[name="${key}"]`).value;
      if (v.trim() !== "") { overrides[key] = parseValue(v); origin[key] = key; }
    }
    if (roomsSel.value === "floorplan") { overrides["env.rooms"] = "floorplan"; origin["env.rooms"] = "env.rooms"; }
    else if (roomsSel.value) {
      const m = maps.data.find((x) => x.id === roomsSel.value);
      // the map's suggested grid unless the form sets its own (a non-square map's rows and
      // columns go with its suggested grid, never with a grid size the form sets)
      const shape = "env.grid_size" in overrides ? [] : ["grid_rows", "grid_cols"]
        .filter((k) => k in m.suggested_env).map((k) => [`env.${k}`, m.suggested_env[k]]);
      for (const [k, v] of [["env.rooms", "maps"], ["env.maps.train", [m.ref]],
        ["env.grid_size", m.suggested_env.grid_size], ...shape, ["env.room_size", m.suggested_env.room_size]]) {
        if (!(k in overrides)) { overrides[k] = v; origin[k] = "env.rooms"; }
      }
    }
    let malformed = false;
    for (const [i, raw] of form.querySelector("[name=overrides]").value.split("\n").entries()) {
      if (!raw.trim()) continue;
      const at = raw.indexOf("=");
      if (at < 1) { markField("overrides", `line ${i + 1}: write key=value (got ${JSON.stringify(raw.trim())})`); malformed = true; continue; }
      const key = raw.slice(0, at).trim();
      overrides[key] = parseValue(raw.slice(at + 1));
      origin[key] = "overrides";
    }
    if (malformed) return; // every malformed line is marked; nothing is sent
    const button = form.querySelector("#submit");
    button.disabled = true;
    try {
      const job = await api("/jobs/train", { method: "POST", body: { preset: presetSel.value, overrides } });
      location.href = `/ui/jobs/${job.id}`;
    } catch (e) {
      button.disabled = false;
      if (e.status === 422 && Array.isArray(e.detail)) {
        for (const d of e.detail) {
          const loc = (d.loc || []).slice(d.loc[0] === "body" ? 1 : 0);
          let key = loc[0] === "overrides" ? loc[1] : loc.join(".");
          if (origin[key] === "overrides") key = "overrides";
          else if (origin[key] !== undefined && origin[key] !== key) key = origin[key]; // set by the rooms choice
          else if (origin[key] === undefined && loc[0] === "overrides") {
            // an error inside a value (e.g. a list element) names a longer path: find its field
            const hit = Object.keys(origin).find((k) => String(loc[1]).startsWith(k));
            key = hit ? origin[hit] : "overrides";
          }
          if (!markField(key, origin[key] === "overrides" || key === "overrides" ? `${loc.slice(1).join(".")}: ${d.msg}` : d.msg)) {
            general.append(h("div", { class: "error-box", role: "alert" }, `${loc.join(".")}: ${d.msg}`));
          }
        }
      } else {
        general.append(h("div", { class: "error-box", role: "alert" }, describe(e)));
      }
    }
  });

  function markField(key, msg) {
    const f = form.querySelector(`.field[data-key="${CSS.escape(key)}"]`);
    if (!f) return false;
    f.classList.add("invalid");
    const err = f.querySelector(".field-error");
    err.textContent = err.textContent ? `${err.textContent}\n${msg}` : msg;
    return true;
  }
}

// ------------------------------------------------------------------ maps
/** POST a form with files (multipart); errors as api() gives them. */
async function upload(path, formData) {
  const resp = await fetch(path, { method: "POST", body: formData, credentials: "same-origin",
    headers: { Accept: "application/json", "X-QuickNav-Web": "1" } });
  const text = await resp.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!resp.ok) {
    if (resp.status === 401) showLogin();
    throw new ApiError(resp.status, data && data.detail !== undefined ? data.detail : data);
  }
  return data;
}

const metres = (x) => `${Number(x.toFixed(2))} m`;

function mapCard(m, refresh) {
  const status = h("div", { class: "field-error" });
  const del = h("button", { class: "danger", onclick: async () => {
    if (!confirm(`Delete map ${m.name}?`)) return;
    try { await api(`/maps/${m.id}`, { method: "DELETE" }); refresh(); } catch (e) { status.textContent = describe(e); }
  } }, "Delete");
  return h("figure", { class: "map-card", dataset: { map: m.id } },
    h("img", { src: m.preview_url, alt: `map ${m.name}` }),
    h("figcaption", {},
      h("strong", {}, m.name), " ", h("span", { class: "mono muted" }, m.ref), h("br"),
      `${m.width_px} × ${m.height_px} px at ${m.resolution} m: ${metres(m.width_m)} × ${metres(m.height_m)}, `
        + `free ${Math.round(100 * m.free_fraction)} %, unknown ${Math.round(100 * m.unknown_fraction)} %`, h("br"),
      m.used_by.length ? h("span", {}, "in use by ", m.used_by.map((j) => h("a", { href: `/ui/jobs/${j}`, class: "mono" }, short(j), " "))) : null,
      (m.notes || []).map((n) => h("p", { class: "note-box map-note" }, n)),
      h("div", { class: "controls" },
        h("a", { href: `/ui/submit?map=${m.id}` }, h("button", { class: "primary" }, "Train on this map")), del),
      status));
}

async function mapsPage() {
  const list = h("div", { class: "images", id: "maps" });
  const files = h("input", { type: "file", id: "map-files", name: "files", multiple: true, accept: ".yaml,.yml,.pgm,.png" });
  const name = h("input", { id: "map-name", name: "name", autocomplete: "off", placeholder: "the image's name" });
  const resolution = h("input", { id: "map-resolution", name: "resolution", inputmode: "decimal", placeholder: "a .yaml names its own" });
  const negate = h("input", { type: "checkbox", id: "map-negate", name: "negate" });
  const occupied = h("input", { id: "map-occupied_thresh", name: "occupied_thresh", inputmode: "decimal", placeholder: "0.65" });
  const free = h("input", { id: "map-free_thresh", name: "free_thresh", inputmode: "decimal", placeholder: "0.196" });
  const errors = h("div", { id: "map-errors" });
  const field = (id, label, help, control) => h("div", { class: "field" },
    h("label", { for: id }, label, h("small", {}, help)), control);
  const form = h("form", { class: "submit", id: "map-form", novalidate: true },
    field("map-files", "Map files", "a ROS map_server .yaml with its .pgm, or one .png/.pgm image", files),
    field("map-name", "Name", "a label", name),
    field("map-resolution", "Resolution", "metres per pixel: plain images only", resolution),
    field("map-negate", "Negate", "plain images: white is occupied", negate),
    field("map-occupied_thresh", "Occupied above", "plain images: darkness from 0 to 1 above which a pixel is a wall", occupied),
    field("map-free_thresh", "Free below", "plain images: darkness from 0 to 1 below which a pixel is free", free),
    errors, h("button", { class: "primary", type: "submit", id: "upload" }, "Upload map"));
  const refresh = async () => {
    const maps = await api("/maps");
    fill(list, maps.count ? maps.data.map((m) => mapCard(m, refresh))
      : h("p", { class: "muted" }, "No maps yet: upload one above."));
  };
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    errors.replaceChildren();
    const data = new FormData();
    for (const f of files.files) data.append("files", f, f.name);
    if (name.value.trim()) data.append("name", name.value.trim());
    if (resolution.value.trim()) data.append("resolution", resolution.value.trim());
    if (negate.checked) data.append("negate", "true");
    if (occupied.value.trim()) data.append("occupied_thresh", occupied.value.trim());
    if (free.value.trim()) data.append("free_thresh", free.value.trim());
    const button = form.querySelector("#upload");
    button.disabled = true;
    try {
      const m = await upload("/maps", data);
      form.reset();
      await refresh();
      errors.append(h("p", { class: "note-box", id: "map-uploaded" }, `Stored map ${m.name} as ${m.ref}.`));
    } catch (e) {
      const items = e.status === 422 && Array.isArray(e.detail) ? e.detail.map((d) => `${(d.loc || []).slice(1).join(".")}: ${d.msg}`) : [describe(e)];
      for (const msg of items) errors.append(h("div", { class: "error-box", role: "alert" }, msg));
    } finally { button.disabled = false; }
  });
  main.replaceChildren(h("h1", {}, "Maps"),
    h("p", { class: "muted" }, "Maps of your buildings, to train and evaluate on. A config names one as map:<id> in env.maps.train."),
    form, h("h2", {}, "Uploaded maps"), list);
  await refresh();
}

// ------------------------------------------------------------------ replay
const PLAN_COLOUR = "#17becf", BOX_COLOUR = "#8c564b", PERSON_COLOUR = "#9467bd"; // as the GIFs

// what the canvas shows of an episode's room, {x0, y0, w, h} in metres: a map's own extent (its
// free cells and the ring of wall around them), as the GIFs show it (render.map_view): a map lies
// in the smallest square grid that holds it, the rest wall. The canvas takes the view's shape
const CANVAS_PX = 520; // the longer side (of most views: canvasScale)
// a long narrow map (a corridor) gets a longer side, up to twice, so its short side keeps at least
// this many pixels where it can (a 5 m x 30 m corridor: about 180 x 1040 rather than 90 x 520)
const CANVAS_MIN_SIDE_PX = 200;

function canvasScale(view) {
  const long = Math.max(view.w, view.h), short = Math.min(view.w, view.h);
  return Math.max(CANVAS_PX / long, Math.min(CANVAS_MIN_SIDE_PX / short, 2 * CANVAS_PX / long));
}

function roomView(data, ep) {
  if (ep.view) return ep.view;
  const cell = data.room_size / data.grid_size;
  let view = { x0: 0, y0: 0, w: data.room_size, h: data.room_size };
  if (ep.map) {
    let r0 = Infinity, r1 = -1, c0 = Infinity, c1 = -1;
    ep.walls.forEach((row, r) => {
      for (let c = 0; c < row.length; c++) {
        if (row[c] !== "#") { r0 = Math.min(r0, r); r1 = Math.max(r1, r); c0 = Math.min(c0, c); c1 = Math.max(c1, c); }
      }
    });
    if (r1 >= 0) {
      r0 = Math.max(r0 - 1, 0); c0 = Math.max(c0 - 1, 0);
      r1 = Math.min(r1 + 2, ep.walls.length); c1 = Math.min(c1 + 2, ep.walls[0].length);
      view = { x0: c0 * cell, y0: r0 * cell, w: (c1 - c0) * cell, h: (r1 - r0) * cell };
    }
  }
  ep.view = view;
  return view;
}

function drawFrame(canvas, data, ep, t) {
  const ctx = canvas.getContext("2d");
  const view = roomView(data, ep);
  const scale = canvasScale(view); // pixels per metre
  const width = Math.round(view.w * scale), height = Math.round(view.h * scale);
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  canvas.dataset.view = `${view.x0},${view.y0},${view.w},${view.h}`;
  const px = (x) => (x - view.x0) * scale;
  const py = (y) => height - (y - view.y0) * scale; // y up, as in the GIFs
  const len = (m) => m * scale; // a length, not a place
  const cellM = data.room_size / data.grid_size, cell = len(cellM);
  const size = Math.max(width, height);
  ctx.fillStyle = "#3b3b3b"; // the grid's wall, where the room does not reach
  ctx.fillRect(0, 0, size, size);
  ctx.fillStyle = "#f4f1ea";
  ctx.fillRect(px(0), py(data.room_size), len(data.room_size), len(data.room_size));
  // an uploaded map: its own picture where it lies in the room, the grid's walls over it, lighter
  const place = ep.map && data.maps && data.maps[ep.map];
  const picture = place && data.pictures && data.pictures[ep.map];
  ctx.fillStyle = "#3b3b3b";
  if (picture) {
    ctx.fillRect(0, 0, size, size); // beyond the map: the grid's wall
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(picture, px(place.x0), py(place.y0 + place.height_m), len(place.width_m), len(place.height_m));
    ctx.fillStyle = "rgba(59,59,59,0.35)";
  }
  // one path filled once: translucent cells do not darken where they overlap
  ctx.beginPath();
  ep.walls.forEach((row, r) => {
    for (let c = 0; c < row.length; c++) if (row[c] === "#") ctx.rect(px(c * cellM), py((r + 1) * cellM), cell + 0.5, cell + 0.5);
  });
  ctx.fill("nonzero");
  // goal disc
  ctx.fillStyle = "rgba(44,160,44,0.35)";
  ctx.beginPath(); ctx.arc(px(ep.goal[0]), py(ep.goal[1]), len(data.goal_radius), 0, 2 * Math.PI); ctx.fill();
  // the global plan from the start (an env that observes it), dashed
  if (ep.plan && ep.plan.length > 1) {
    ctx.strokeStyle = PLAN_COLOUR; ctx.lineWidth = 1.5; ctx.setLineDash([5, 4]); ctx.beginPath();
    ep.plan.forEach(([x, y], i) => ctx[i === 0 ? "moveTo" : "lineTo"](px(x), py(y)));
    ctx.stroke(); ctx.setLineDash([]);
  }
  // obstacles the map does not show: boxes where they stand, people where they are at step t
  const disc = (x, y, r, colour) => { ctx.fillStyle = colour; ctx.beginPath(); ctx.arc(px(x), py(y), Math.max(len(r), 2), 0, 2 * Math.PI); ctx.fill(); };
  (ep.boxes || []).forEach(([x, y, r]) => disc(x, y, r, BOX_COLOUR));
  (ep.people || []).forEach((p) => disc(p.x[t], p.y[t], p.radius, PERSON_COLOUR));
  // path so far
  ctx.strokeStyle = "#ff7f0e"; ctx.lineWidth = 2; ctx.beginPath();
  for (let i = 0; i <= t; i++) { const f = i === 0 ? "moveTo" : "lineTo"; ctx[f](px(ep.x[i]), py(ep.y[i])); }
  ctx.stroke();
  // lidar rays coloured by what they hit
  const x = ep.x[t], y = ep.y[t], th = ep.theta[t];
  ctx.lineWidth = 1;
  data.beam_angles.forEach((a, b) => {
    const r = ep.ranges[t][b];
    ctx.strokeStyle = RAY_COLOURS[ep.hits[t][b]] || "#9e9e9e";
    ctx.beginPath(); ctx.moveTo(px(x), py(y));
    ctx.lineTo(px(x + r * Math.cos(th + a)), py(y + r * Math.sin(th + a))); ctx.stroke();
  });
  // robot and heading
  const rr = len(data.robot_radius);
  ctx.fillStyle = "#1f77b4"; ctx.beginPath(); ctx.arc(px(x), py(y), rr, 0, 2 * Math.PI); ctx.fill();
  ctx.strokeStyle = "#fff"; ctx.lineWidth = Math.max(1.5, rr / 3); ctx.beginPath(); ctx.moveTo(px(x), py(y));
  ctx.lineTo(px(x + 1.5 * data.robot_radius * Math.cos(th)), py(y + 1.5 * data.robot_radius * Math.sin(th))); ctx.stroke();
}

// how an episode ended, as the pictures' titles say it (eval.episodes.outcome; a replay.json
// written before it carried the outcome says reached or not)
function episodeEnd(ep) {
  const how = ep.outcome || (ep.success ? "reached" : "failed");
  if (how === "reached") return `reached the goal in ${ep.steps} steps`;
  if (how === "collided") return `collided after ${ep.steps} steps`;
  if (how === "timed out") return `timed out after ${ep.steps} steps`;
  return `${how} after ${ep.steps} steps`;
}

function player(data, into) {
  const canvas = h("canvas", { width: CANVAS_PX, height: CANVAS_PX, id: "replay-canvas" });
  const epSel = h("select", { id: "episode" }, data.episodes.map((ep, i) => h("option", { value: i },
    `episode ${ep.index + 1}: ${episodeEnd(ep)}`)));
  const slider = h("input", { type: "range", min: 0, max: 0, value: 0, id: "step-slider", "aria-label": "step" });
  const label = h("span", { class: "mono", id: "step-label" });
  const play = h("button", { id: "play", class: "primary" }, "Pause");
  const speed = h("select", { id: "speed" }, [["1", "1× (real time)"], ["2", "2×"], ["4", "4×"], ["0.5", "½×"]]
    .map(([v, t]) => h("option", { value: v }, t)));
  let ep = data.episodes[0], t = 0, playing = true, timer = null;
  const show = () => {
    slider.max = String(ep.x.length - 1); slider.value = String(t);
    label.textContent = `step ${t} / ${ep.x.length - 1}`;
    canvas.dataset.step = String(t);
    // what the frame shows beyond the room and the robot (read by the browser tests)
    canvas.dataset.plan = String(ep.plan ? ep.plan.length : 0);
    canvas.dataset.boxes = String((ep.boxes || []).length);
    canvas.dataset.people = String((ep.people || []).length);
    drawFrame(canvas, data, ep, t);
  };
  const schedule = () => {
    clearInterval(timer);
    if (!playing) return;
    timer = setInterval(() => {
      if (t >= ep.x.length - 1) { t = 0; } else { t += 1; }
      show();
    }, 1000 * data.dt / Number(speed.value));
  };
  play.addEventListener("click", () => { playing = !playing; play.textContent = playing ? "Pause" : "Play"; schedule(); });
  slider.addEventListener("input", () => { t = Number(slider.value); show(); });
  epSel.addEventListener("change", () => { ep = data.episodes[Number(epSel.value)]; t = 0; show(); });
  speed.addEventListener("change", schedule);
  into.replaceChildren(h("div", { class: "player" }, canvas, h("div", {},
    h("p", {}, `Agent: ${data.agent}`), epSel,
    h("div", { class: "controls" }, play, slider, label), h("div", { class: "controls" }, "Speed", speed),
    h("div", { class: "legend" }, h("span", {}, h("i", { style: "background:#d62728" }), "lidar hit a wall"),
      h("span", {}, h("i", { style: "background:#2ca02c" }), "hit the goal"),
      h("span", {}, h("i", { style: "background:#9e9e9e" }), "nothing in range"),
      h("span", {}, h("i", { style: "background:#ff7f0e" }), "path"),
      ...(data.episodes.some((e) => e.plan) ? [h("span", {}, h("i", { style: `background:${PLAN_COLOUR}` }), "global plan")] : []),
      ...(data.episodes.some((e) => (e.boxes || []).length) ? [h("span", {}, h("i", { style: `background:${BOX_COLOUR}` }), "box (not on the map)")] : []),
      ...(data.episodes.some((e) => (e.people || []).length) ? [h("span", {}, h("i", { style: `background:${PERSON_COLOUR}` }), "person walking")] : [])))));
  show(); schedule();
}

/** The pictures of the uploaded maps a replay drove in (map:<id> -> a bitmap); a map deleted since
    (or a map file read by the CLI) is drawn from the grid alone. */
async function mapPictures(data) {
  const out = {};
  for (const ref of Object.keys(data.maps || {})) {
    if (!ref.startsWith("map:")) continue;
    try {
      const resp = await fetch(`/maps/${ref.slice(4)}/preview.png`, { credentials: "same-origin" });
      if (resp.ok) out[ref] = await createImageBitmap(await resp.blob());
    } catch { /* drawn without it */ }
  }
  return out;
}

// the maps an eval job drove in: an uploaded map or file it was asked to drive, or the maps of a
// policy trained on maps (the held-out ones where it ran on them); none for a room bank
function evalMaps(evalJob) {
  const map = evalJob.request && evalJob.request.map;
  if (map) return [map];
  const env = evalJob.config.env || {};
  if (env.rooms !== "maps" || !env.maps) return [];
  return evalJob.config.split === "test" && env.maps.test ? env.maps.test : env.maps.train;
}

// the names of the uploaded maps among an eval job's first three (map:<id> -> its name); a map
// deleted since keeps its reference
async function mapNames(evalJob) {
  const out = {};
  await Promise.all(evalMaps(evalJob).slice(0, 3).filter((r) => r.startsWith("map:")).map(async (ref) => {
    try { out[ref] = (await api(`/maps/${encodeURIComponent(ref.slice(4))}`)).name; } catch { /* its ref */ }
  }));
  return out;
}

// where an eval job's episodes were driven, in words: an uploaded map by its name, a map file by
// its file name, or a room bank (the same words as the pictures' titles: eval.pictures.rooms_in_words)
function evalWhere(evalJob, names = {}) {
  const label = (n) => (names[n] ? `"${names[n]}"` : n.startsWith("map:") ? n : n.split("/").pop());
  const maps = evalMaps(evalJob).map(label);
  if (evalJob.request && evalJob.request.map) return `the map ${maps[0]}`;
  if (maps.length === 1) return `map ${maps[0]}`;
  if (maps.length) return `${maps.length} maps (${maps.slice(0, 3).join(", ")}${maps.length > 3 ? ", ..." : ""})`;
  return evalJob.config.split === "test" ? "held-out test rooms" : "training rooms";
}

// names: the eval job's map names where the caller has fetched them already (mapNames)
async function replayOf(evalJob, into, names = null) {
  try {
    const data = await api(`/jobs/${evalJob.id}/artifacts/replay.json`);
    data.pictures = await mapPictures(data);
    player(data, into);
    const where = evalWhere(evalJob, names || await mapNames(evalJob));
    into.prepend(h("p", { class: "muted", id: "replay-source" }, `Episodes of eval job `,
      h("a", { href: `/ui/jobs/${evalJob.id}` }, short(evalJob.id)), ` on ${where} (seed ${evalJob.config.seed}).`));
  } catch (e) {
    if (e.status === 404) into.replaceChildren(h("p", { class: "muted" }, "This evaluation kept no episodes to replay."));
    else throw e;
  }
}

async function replayPage(id) {
  const job = await api(`/jobs/${encodeURIComponent(id)}`);
  const stage = h("div", { id: "replay" });
  const chooser = h("div", { class: "controls" });
  main.replaceChildren(h("h1", {}, "Replay of ", h("a", { class: "mono", href: `/ui/jobs/${job.id}` }, `${job.kind} job ${short(job.id)}`)),
    chooser, stage);
  if (job.kind === "eval") {
    const names = await mapNames(job);
    chooser.append(h("span", { class: "muted" }, `${evalWhere(job, names)}, ${job.config.policy === "trained" ? "trained policy" : job.config.policy}`));
    if (job.status !== "succeeded") { stage.append(h("p", {}, `This eval job is ${job.status}.`)); return; }
    return replayOf(job, stage, names);
  }
  if (job.kind !== "train") { stage.append(h("p", {}, "Only train and eval jobs have episodes to replay.")); return; }
  // a trained policy: replay its newest finished held-out eval, or run one
  const { data: evals } = await api("/jobs?kind=eval&limit=500");
  const mine = evals.filter((e) => e.config && e.config.source === job.id && e.status !== "failed" && e.status !== "cancelled")
    .sort((a, b) => b.created_at - a.created_at);
  const run = h("button", { class: "primary", id: "new-replay", onclick: async () => {
    run.disabled = true;
    try {
      const ev = await api("/jobs/eval", { method: "POST", body: { job_id: job.id, episodes: 20, split: "test" } });
      follow(ev);
    } catch (e) { run.disabled = false; showError(stage, e); }
  } }, "Evaluate on 20 held-out rooms and replay");
  chooser.append(run);
  // newest first (the list's order); an eval that kept no replay.json (a picture that failed, an
  // older server) is skipped rather than shown as "nothing to replay"
  const succeeded = mine.filter((e) => e.status === "succeeded");
  const ready = [];
  for (const e of succeeded) {
    const { artifacts } = await api(`/jobs/${e.id}/artifacts`);
    if (artifacts.some((a) => a.name === "replay.json")) ready.push(e);
  }
  if (ready.length) {
    const sel = h("select", { id: "eval-source", onchange: () => replayOf(ready.find((e) => e.id === sel.value), stage) },
      ready.map((e) => h("option", { value: e.id }, `eval ${short(e.id)} (${e.request && e.request.map ? e.request.map : `${e.config.split} rooms`}, seed ${e.config.seed}, ${age(e.created_at)})`)));
    chooser.prepend(h("span", {}, "From "), sel);
    return replayOf(ready[0], stage);
  }
  const pending = mine.find((e) => !finished(e));
  if (pending) return follow(pending);
  stage.append(h("p", { class: "muted" }, "This policy has no held-out evaluation yet: run one (a few seconds) to watch it drive."));

  function follow(ev) {
    const status = h("p", { id: "replay-status" });
    stage.replaceChildren(status);
    const tid = every(1000, async () => {
      const e = await api(`/jobs/${ev.id}`);
      status.replaceChildren(`Evaluating on held-out rooms (job `, h("a", { href: `/ui/jobs/${e.id}` }, short(e.id)), `): `, badge(e.status), " ", progressBar(e.progress));
      if (finished(e)) {
        clearInterval(tid);
        run.disabled = false;
        if (e.status === "succeeded") replayOf(e, stage);
        else status.append(h("div", { class: "error-box" }, e.error || `the eval job was ${e.status}`));
      }
    });
  }
}

async function replayIndex() {
  const { data } = await api("/jobs?kind=train&status=succeeded&limit=500");
  main.replaceChildren(h("h1", {}, "Replay a trained policy"),
    data.length ? h("table", { id: "replay-jobs" }, h("thead", {}, h("tr", {}, ["Job", "Algorithm", "Network", "Final success", "Created"].map((t) => h("th", {}, t)))),
      h("tbody", {}, data.map((j) => h("tr", {},
        h("td", { class: "mono" }, h("a", { href: `/ui/jobs/${j.id}/replay` }, short(j.id))),
        h("td", {}, getPath(j.config, "algorithm.name") || ""), h("td", {}, getPath(j.config, "network.kind") || ""),
        h("td", {}, pct((j.metrics || {}).success_rate)), h("td", {}, age(j.created_at))))))
      : h("p", { class: "muted" }, "No trained job has succeeded yet. ", h("a", { href: "/ui/submit" }, "Train one.")));
}

// ------------------------------------------------------------------ router
async function route() {
  const s = await sessionBar();
  if (s.token_required && !s.authenticated) { showLogin(); return; }
  const path = location.pathname;
  // a replay of a job is under /ui/jobs/ but belongs to Replay; links without data-nav (API
  // docs) are never the current page (toggle with an undefined force would flip them on)
  const current = /^\/ui\/jobs\/[^/]+\/replay\/?$/.test(path) || path.startsWith("/ui/replay") ? "replay"
    : path.startsWith("/ui/submit") ? "submit" : path.startsWith("/ui/maps") ? "maps" : path === "/" || path.startsWith("/ui/jobs") || path === "/ui/" ? "jobs" : null;
  for (const a of document.querySelectorAll("header nav a")) {
    const on = Boolean(a.dataset.nav) && a.dataset.nav === current;
    a.classList.toggle("active", on);
    if (on) a.setAttribute("aria-current", "page"); else a.removeAttribute("aria-current");
  }
  let m;
  try {
    if (path === "/" || path === "/ui/" || path === "/ui/jobs") jobsPage();
    else if ((m = path.match(/^\/ui\/jobs\/([^/]+)\/replay\/?$/))) await replayPage(decodeURIComponent(m[1]));
    else if ((m = path.match(/^\/ui\/jobs\/([^/]+)\/?$/))) await jobPage(decodeURIComponent(m[1]));
    else if (path.startsWith("/ui/submit")) await submitPage();
    else if (path.startsWith("/ui/replay")) await replayIndex();
    else if (path.startsWith("/ui/maps")) await mapsPage();
    else main.replaceChildren(h("h1", {}, "Not found"), h("a", { href: "/" }, "All jobs"));
  } catch (e) {
    if (!(e instanceof ApiError && e.status === 401)) main.replaceChildren(h("div", { class: "error-box" }, e instanceof ApiError ? describe(e) : String(e)));
  }
}
route();
