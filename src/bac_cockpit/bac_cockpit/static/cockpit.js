/* bac cockpit: follows the campaign over server-sent events and draws it (plotly.js, served by the cockpit). */
(function () {
  "use strict";

  const S = {};                      // the state, as the server sends it (snapshot, then patches)
  const T = {};                      // how long each drawing took here, ms (the last 50 of each)
  const L = [];                      // what the page did, in order: [kind, what, start ms, end ms] (the last 5,000-6,000)
  const note = (kind, what, t0, t1) => { L.push([kind, what, t0, t1]); if (L.length > 6000) L.splice(0, 1000); };
  const $ = (id) => document.getElementById(id);
  const token = new URLSearchParams(location.search).get("token");
  const withToken = (p) => (token ? p + (p.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : p);
  const PLOT_CONFIG = { responsive: true, displaylogo: false, displayModeBar: "hover",
    modeBarButtonsToRemove: ["select2d", "lasso2d", "autoScale2d"] };
  const COLORS = { last: "#1d4ed8", best: "#0b7a35", pred: "#9ca3af", rec: "#5b21b6", conf: "#65a30d" };
  let connected = false;
  let pending = new Set();
  let timer = null;

  const ok = (x) => x !== null && x !== undefined && isFinite(x);
  const fj = (x) => (ok(x) ? Number(x).toFixed(4) : "–");
  const fp = (x) => (ok(x) ? Number(x).toPrecision(3) : "–");
  const params = (p) => Object.entries(p || {}).map(([k, v]) => `${k}=${fp(v)}`).join("  ");
  const esc = (s) => String(s === null || s === undefined ? "" : s).replace(/[&<>"']/g,
    (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
  const setText = (id, text) => { const el = $(id); if (el.textContent !== text) el.textContent = text; };

  // --- connection ----------------------------------------------------------------------------------------
  function setConn(kind, text) {
    const el = $("conn");
    el.className = "badge conn-" + kind;
    el.textContent = text;
    connected = kind === "ok";
    renderBanner();
  }

  function connect() {
    const es = new EventSource(withToken("events"));
    es.addEventListener("snapshot", (e) => {
      const d = JSON.parse(e.data);
      for (const k of Object.keys(S)) delete S[k];
      Object.assign(S, d);
      setConn("ok", "connected");
      update(Object.keys(d));
    });
    es.addEventListener("patch", (e) => {
      window.bacCockpit.received = Date.now();  // when this page had it (the tests compare with the server's time)
      const d = JSON.parse(e.data);
      const now = performance.now();
      note("patch", Object.keys(d).join(","), now, now);
      Object.assign(S, d);
      update(Object.keys(d));
    });
    es.onopen = () => setConn("ok", "connected");
    es.onerror = () => setConn(es.readyState === EventSource.CLOSED ? "lost" : "wait",
      es.readyState === EventSource.CLOSED ? "connection lost" : "reconnecting…");
  }

  // the banner and the cards at once (what the driver reads), then the J plot and the table; the heavy plots
  // (contour, signals, spectra) a moment later, so that a state change arriving meanwhile is never held back by them
  const SLOW = new Set(["model", "signals", "spectra", "diagnostics", "campaign"]);
  let slowPending = new Set();
  let slowTimer = null;

  function update(keys) {
    renderBanner();
    renderCards();
    for (const k of keys) (SLOW.has(k) ? slowPending : pending).add(k);
    if (timer === null) timer = setTimeout(flush, 0);
    if (slowTimer === null && slowPending.size) slowTimer = setTimeout(flushSlow, 150);
  }

  // what the plots were last drawn with: a state change redraws only what it changes
  let drawnTrial = "", drawnMarker = "";

  function flush() {
    timer = null;
    const k = pending;
    pending = new Set();
    const t = S.trial || {};
    const trialKey = `${t.trial_id}/${t.state_name === "DONE"}`;
    if (k.has("trials") || k.has("recommendation")) renderJ();
    if (k.has("trials") || trialKey !== drawnTrial) { renderTable(); drawnTrial = trialKey; }
    const markerKey = t.state_name === "DONE" ? "" : JSON.stringify(t.params || {});
    if (markerKey !== drawnMarker) slowPending.add("marker");
    if (slowTimer === null && slowPending.size) slowTimer = setTimeout(flushSlow, 150);
  }

  // one heavy drawing per task. A change that came in during a heavy drawing (its J and table: the banner and the
  // cards are drawn in the message's handler) is drawn before the next one: the drawing queued this task as it
  // ended, before the browser ran the message's handler, whose own task would otherwise come after this heavy
  // drawing; the heavy drawing follows in the next task (the browser may paint the change in between). Once per
  // heavy drawing: a change that comes in meanwhile waits for it, and changes that keep coming can never hold the
  // plots back for good
  let slowGaveWay = false;
  function flushSlow() {
    slowTimer = null;
    if (timer !== null && pending.size && !slowGaveWay) {
      clearTimeout(timer);
      try {
        flush();
      } finally {  // a drawing that threw must not stop the heavy plots
        slowGaveWay = true;
        if (slowTimer !== null) clearTimeout(slowTimer);  // flush() put it 150 ms off: it is due
        slowTimer = slowPending.size ? setTimeout(flushSlow, 0) : null;
      }
      return;
    }
    slowGaveWay = false;
    const k = slowPending;
    const order = ["model", "marker", "signals", "spectra", "diagnostics", "campaign"];
    const next = order.find((x) => k.has(x));
    if (next === undefined) { slowPending = new Set(); return; }
    k.delete(next);
    try {
      if (next === "model" || next === "marker") {
        k.delete("marker");
        if (next === "model") renderJ();  // the model's recommendation band while there is no final one
        if (next === "model" || !timed("moveMarker", moveMarker)) renderGP();
        const t = S.trial || {};
        drawnMarker = t.state_name === "DONE" ? "" : JSON.stringify(t.params || {});
      } else if (next === "signals") renderSignals();
      else if (next === "spectra") renderSpectra();
      else if (next === "diagnostics") renderDiag();
      else if (next === "campaign") renderCampaign();
    } finally {  // a drawing that threw must not stop the others
      if (k.size && slowTimer === null) slowTimer = setTimeout(flushSlow, 0);
    }
  }

  // --- the banner ----------------------------------------------------------------------------------------
  function renderBanner() { timed("renderBanner", () => renderBanner_()); }
  function renderBanner_() {
    const t = S.trial || { state_name: "IDLE", headline: "WAITING FOR THE CAMPAIGN", tone: "idle", trial_id: 0 };
    const b = $("banner");
    const live = S.mode !== "offline";
    let tone = t.tone, headline = t.headline, instruction = t.instruction || "";
    if (live && !connected && S.trial) {   // never leave READY TO DRIVE on a screen that lost the graph
      tone = "idle stale";
      headline = "NO CONNECTION";
      instruction = "This screen lost the cockpit: do not rely on it until it reconnects.";
    }
    b.className = "banner tone-" + tone.split(" ").join(" tone-");
    b.dataset.state = live && !connected && S.trial ? "DISCONNECTED" : t.state_name;
    b.dataset.trial = String(t.trial_id || 0);
    b.dataset.attempt = String(t.attempt || 0);
    setText("headline", headline);
    setText("instruction", instruction || (t.state_name === "IDLE" ? "The page follows the campaign as soon as the agent starts." : ""));
    let trialOf = "";
    if (t.state_name === "DONE") trialOf = `${t.trials_done} of ${t.budget} trials done`;
    else if (t.confirmation) trialOf = `confirmation run (after ${t.budget} trials)`;
    else if (t.trial_id) trialOf = `trial ${t.trial_id} of ${t.budget}`;
    setText("trial-of", trialOf);
    setText("run-of", t.attempt > 1 && t.state_name !== "DONE" ? `run ${t.attempt}` : "");
    const sp = S.speed || {};
    let target = "";
    if (ok(sp.target_kmh)) {
      target = `target speed ${Number(sp.target_kmh).toFixed(0)} km/h`;
      if (sp.mode === "event") target += " (speed bump)";
      else if (sp.mode === "distance" && sp.section_m) target += ` (section ${sp.section_m[0]}–${sp.section_m[1]} m)`;
    }
    setText("target-speed", target);
    setText("last-speed", ok(sp.last_mean_kmh) ? `last run ${Number(sp.last_mean_kmh).toFixed(1)} km/h` : "");
    const r = $("reason");
    const why = t.reason ? (t.state_name === "READY_TO_DRIVE" ? "last run rejected: " : "why: ") + t.reason : "";
    r.hidden = !why;
    setText("reason", why);
    document.title = `${headline} · bac cockpit`;
  }

  // --- cards ---------------------------------------------------------------------------------------------------
  function kv(pairs) {
    return '<div class="kv">' + pairs.filter((p) => p[1] !== "" && p[1] !== undefined && p[1] !== null)
      .map(([k, v]) => `<span>${esc(k)}</span><span>${esc(v)}</span>`).join("") + "</div>";
  }

  function renderCards() { timed("renderCards", () => renderCards_()); }
  function renderCards_() {
    const best = S.best;
    setText("best", best ? `J ${fj(best.j)}` : "–");
    setText("best-params", best ? `trial ${best.trial_id}: ${params(best.params)}` : "no scored run yet");

    const finalRec = S.recommendation && S.recommendation.params ? S.recommendation : null;
    const modelRec = S.model && S.model.recommendation ? S.model.recommendation : null;
    const rec = finalRec || modelRec;
    const rc = $("rec-card");
    rc.dataset.final = finalRec ? "true" : "false";
    setText("rec-title", finalRec ? "recommendation (final)" : "model's current best calibration");
    setText("rec", rec && ok(rec.predicted_j) ? `J ${fj(rec.predicted_j)} ± ${fj(2 * (rec.predicted_std || 0))}` : "–");
    setText("rec-params", rec ? params(rec.params) + "  (predicted, ±2σ)" : "after the first runs");

    const ecu = S.ecu || {};
    const link = ecu.link;
    const la = ecu.last_apply;
    const holds = ecu.holds;
    $("ecu-card").dataset.level = link ? link.level : "";
    const said = (d) => (d.message.toUpperCase().startsWith(d.level) ? d.message : `${d.level}: ${d.message}`);
    setText("ecu-main", link ? said(link) : (S.mode === "offline" ? "not recorded" : "no diagnostics yet"));
    const ep = [];
    if (la) {
      ep.push(["last apply", `${la.success ? "✓ confirmed" : "✗ failed"} (trial ${la.trial_id}, try ${la.apply_try}` +
        (la.attempts ? `, ${la.attempts} transaction${la.attempts > 1 ? "s" : ""}` : "") + ")"]);
      ep.push(["latency", ok(la.latency_s) ? `${(1000 * la.latency_s).toFixed(1)} ms` : "–"]);
      if (!la.success && la.message) ep.push(["error", la.message]);
    }
    if (holds) ep.push(["ECU holds", `trial ${holds.trial_id}: ${params(holds.params)} (CRC ${holds.crc32})`]);
    if (link && link.values) {
      const v = link.values;
      if (v.applies_ok !== undefined) ep.push(["applies", `${v.applies_ok} ok, ${v.applies_failed} failed, ${v.retransmissions || 0} resent`]);
      if (v.bus_state) ep.push(["bus", `${v.interface || ""} ${v.channel || ""} ${v.bus_state}`]);
    }
    $("ecu-detail").innerHTML = kv(ep);

    const imu = (S.imu || {}).stream;
    $("imu-card").dataset.level = imu ? imu.level : "";
    setText("imu-main", imu ? said(imu) : (S.mode === "offline" ? "not recorded" : "no diagnostics yet"));
    const iv = imu ? imu.values : {};
    $("imu-detail").innerHTML = imu ? kv([
      ["rate", iv.rate_hz ? `${Number(iv.rate_hz).toFixed(1)} Hz (nominal ${Number(iv.nominal_rate_hz).toFixed(1)})` : ""],
      ["jitter", iv.jitter_ms ? `${Number(iv.jitter_ms).toFixed(2)} ms` : ""],
      ["gaps", iv.gaps !== undefined ? `${iv.gaps} (longest ${Number(iv.longest_gap_s || 0).toFixed(3)} s)` : ""],
      ["saturated", iv.saturated], ["NaN/inf", iv.nonfinite], ["samples", iv.samples_in],
    ]) : "";
  }

  function renderCampaign() {
    const c = S.campaign || {};
    setText("campaign-id", c.campaign_id ? `${c.campaign_id} · ${c.description || ""}` : "no campaign yet");
    setText("mode", S.mode === "offline" ? "campaign folder (offline)" : "live");
    setText("campaign-status", c.status ? `${c.status} Folder: ${c.path}` : "");
  }

  // --- J per trial -------------------------------------------------------------------------------------------
  let drawnJ = null;

  function renderJ() { timed("renderJ", () => renderJ_()); }
  function renderJ_() {
    const rows = S.trials || [];
    const scored = rows.filter((r) => r.status === "scored" && ok(r.j) && r.kind !== "confirmation");
    const conf = rows.filter((r) => r.status === "scored" && ok(r.j) && r.kind === "confirmation");
    const xs = scored.map((r) => r.trial_id), ys = scored.map((r) => r.j);
    const bestSoFar = []; let m = Infinity;
    for (const y of ys) { m = Math.min(m, y); bestSoFar.push(m); }
    const pred = rows.filter((r) => ok(r.predicted_j));
    const data = [
      { x: xs, y: ys, mode: "markers", type: "scatter", name: "J of the trial's run", marker: { size: 10, color: COLORS.last },
        text: scored.map((r) => `trial ${r.trial_id}: ${params(r.params)}`), hovertemplate: "%{text}<br>J=%{y:.4f}<extra></extra>" },
      { x: xs, y: bestSoFar, mode: "lines", type: "scatter", name: "best so far", line: { shape: "hv", color: COLORS.best, width: 2.5 } },
      { x: pred.map((r) => r.trial_id), y: pred.map((r) => r.predicted_j), mode: "markers", type: "scatter",
        name: "predicted before the run (±2σ)", marker: { symbol: "circle-open", size: 9, color: COLORS.pred },
        error_y: { type: "data", array: pred.map((r) => 2 * (r.predicted_std || 0)), color: COLORS.pred, thickness: 1 } },
    ];
    if (conf.length) data.push({ x: conf.map((r) => r.trial_id), y: conf.map((r) => r.j), mode: "markers", type: "scatter",
      name: "confirmation run", marker: { symbol: "cross", size: 13, color: COLORS.conf, line: { width: 1, color: "#000" } } });
    const rec = (S.recommendation && S.recommendation.params ? S.recommendation : null) || (S.model && S.model.recommendation);
    const nmax = Math.max(1, ...rows.map((r) => r.trial_id), (S.trial && S.trial.budget) || 1);
    if (rec && ok(rec.predicted_j)) {
      const lo = rec.predicted_j - 2 * (rec.predicted_std || 0), hi = rec.predicted_j + 2 * (rec.predicted_std || 0);
      data.push({ x: [0.5, nmax + 0.5], y: [lo, lo], mode: "lines", line: { width: 0 }, hoverinfo: "skip", showlegend: false, type: "scatter" });
      data.push({ x: [0.5, nmax + 0.5], y: [hi, hi], mode: "lines", line: { width: 0 }, fill: "tonexty",
        fillcolor: "rgba(91,33,182,0.15)", hoverinfo: "skip", showlegend: false, type: "scatter" });
      data.push({ x: [0.5, nmax + 0.5], y: [rec.predicted_j, rec.predicted_j], mode: "lines", type: "scatter",
        name: (S.recommendation && S.recommendation.params ? "recommendation" : "model's best") + ": predicted J ±2σ",
        line: { color: COLORS.rec, dash: "dash" } });
    }
    const shapes = [];
    for (const r of rows) {
      if (r.status === "failed") shapes.push({ type: "rect", xref: "x", yref: "paper", x0: r.trial_id - 0.4, x1: r.trial_id + 0.4, y0: 0, y1: 1, fillcolor: "rgba(185,28,28,0.18)", line: { width: 0 } });
      else if (r.rejected && r.rejected.length) shapes.push({ type: "rect", xref: "x", yref: "paper", x0: r.trial_id - 0.4, x1: r.trial_id + 0.4, y0: 0, y1: 1, fillcolor: "rgba(217,72,15,0.15)", line: { width: 0 } });
    }
    const el = $("jplot");
    const key = JSON.stringify([xs, ys, pred.map((r) => [r.trial_id, r.predicted_j, r.predicted_std]), conf.map((r) => r.j),
      rec ? [rec.predicted_j, rec.predicted_std] : null, nmax, shapes.length, rows.map((r) => r.status)]);
    if (key === drawnJ) return;
    drawnJ = key;
    Plotly.react(el, data, {
      margin: { l: 56, r: 10, t: 8, b: 40 }, uirevision: "j", shapes,
      xaxis: { title: { text: "trial" }, range: [0.5, nmax + 0.5], dtick: nmax > 30 ? undefined : 1 },
      yaxis: { title: { text: "J" }, zeroline: false },
      legend: { orientation: "h", y: -0.22, font: { size: 11 } }, showlegend: true,
    }, PLOT_CONFIG);
    el.dataset.points = String(scored.length + conf.length);
    setText("j-caption", scored.length ? `(${scored.length} scored, best J ${fj(bestSoFar[bestSoFar.length - 1])})` : "");
  }

  // --- GP posterior mean ---------------------------------------------------------------------------------------------
  // the calibration driven now: a red ring drawn as a layout shape (moved by a cheap relayout, the contour stays)
  function nowShapes(md) {
    const t = S.trial;
    const [d0, d1] = md.dims || [];
    if (!t || !t.params || t.state_name === "DONE" || !d1 || t.params[d0.name] === undefined) return [];
    const x = t.params[d0.name], y = t.params[d1.name];
    return [{ type: "circle", xref: "x", yref: "y", xsizemode: "pixel", ysizemode: "pixel", xanchor: x, yanchor: y,
      x0: -11, x1: 11, y0: -11, y1: 11, line: { color: "#ef4444", width: 3 } }];
  }

  let drawnModel = null;

  function moveMarker() {  // the contour as it is, the red ring on the calibration driven now
    const el = $("gpplot");
    const md = S.model;
    if (!md || md.kind !== "contour" || drawnModel !== md || !el.layout) return false;
    Plotly.relayout(el, { shapes: nowShapes(md) });
    return true;
  }

  function renderGP() { timed("renderGP", () => renderGP_()); }
  function renderGP_() {
    const md = S.model;
    const el = $("gpplot");
    const cap = $("gp-caption");
    if (!md || !md.kind) {
      cap.textContent = md && md.status ? md.status : "GP posterior mean: no model yet (after the first J)";
      return;
    }
    const fixed = Object.keys(md.fixed || {}).length ? ` · others at the recommendation (${params(md.fixed)})` : "";
    cap.textContent = md.status + fixed;
    cap.dataset.runs = String(md.n_runs);
    el.dataset.runs = String(md.n_runs);
    const t = S.trial;
    const data = [];
    let layout;
    if (md.kind === "contour") {
      const [d0, d1] = md.dims;
      data.push({ type: "contour", x: md.x, y: md.y, z: md.mean, colorscale: "Viridis", ncontours: 20,
        colorbar: { title: { text: "J" }, thickness: 12 },
        hovertemplate: `${d0.name}=%{x:.3f}<br>${d1.name}=%{y:.3f}<br>mean J=%{z:.4f}<extra></extra>` });
      const tr = md.trials || [];
      // each label dark on the light (high J) part of the map, white on the dark part
      const flat = md.mean.flat().filter(ok);
      const mid = (Math.min(...flat) + Math.max(...flat)) / 2;
      const near = (v, axis) => Math.max(0, Math.min(axis.length - 1, Math.round((v - axis[0]) / (axis[axis.length - 1] - axis[0]) * (axis.length - 1))));
      const labelColor = (p) => { const z = md.mean[near(p.params[d1.name], md.y)][near(p.params[d0.name], md.x)]; return ok(z) && z > mid ? "#111" : "#fff"; };
      data.push({ type: "scatter", mode: "markers+text", name: "trials", x: tr.map((p) => p.params[d0.name]), y: tr.map((p) => p.params[d1.name]),
        text: tr.map((p) => String(p.trial_id)), textposition: "top right", textfont: { color: tr.map(labelColor), size: 11 },
        marker: { size: 9, color: "#fff", line: { color: "#000", width: 1 } },
        hovertemplate: "trial %{text}<extra></extra>" });
      if ((md.failed || []).length) data.push({ type: "scatter", mode: "markers", name: "failed", x: md.failed.map((p) => p.params[d0.name]),
        y: md.failed.map((p) => p.params[d1.name]), marker: { symbol: "x", size: 11, color: "#dc2626" } });
      const r = md.recommendation;
      if (r) data.push({ type: "scatter", mode: "markers", name: r.final ? "recommendation" : "model's best", x: [r.params[d0.name]], y: [r.params[d1.name]],
        marker: { symbol: "star", size: 20, color: "#fde047", line: { color: "#000", width: 1.5 } } });
      layout = { margin: { l: 56, r: 10, t: 8, b: 40 }, uirevision: "gp", shapes: nowShapes(md),
        xaxis: { title: { text: d0.name }, range: [d0.lower, d0.upper] }, yaxis: { title: { text: d1.name }, range: [d1.lower, d1.upper] },
        legend: { orientation: "h", y: -0.22, font: { size: 11 } } };
    } else {
      const d0 = md.dims[0];
      const lo = md.mean.map((m, i) => m - 2 * md.std[i]), hi = md.mean.map((m, i) => m + 2 * md.std[i]);
      data.push({ x: md.x, y: lo, mode: "lines", line: { width: 0 }, showlegend: false, hoverinfo: "skip", type: "scatter" });
      data.push({ x: md.x, y: hi, mode: "lines", line: { width: 0 }, fill: "tonexty", fillcolor: "rgba(29,78,216,0.15)", name: "±2σ", type: "scatter" });
      data.push({ x: md.x, y: md.mean, mode: "lines", name: "posterior mean", line: { color: COLORS.last }, type: "scatter" });
      const tr = md.trials || [];
      data.push({ x: tr.map((p) => p.params[d0.name]), y: tr.map((p) => p.j), mode: "markers+text", name: "trials", type: "scatter",
        text: tr.map((p) => String(p.trial_id)), textposition: "top center", marker: { size: 8, color: "#111" } });
      layout = { margin: { l: 56, r: 10, t: 8, b: 40 }, uirevision: "gp", xaxis: { title: { text: d0.name } }, yaxis: { title: { text: "J" } },
        legend: { orientation: "h", y: -0.22 } };
    }
    Plotly.react(el, data, layout, PLOT_CONFIG);
    drawnModel = md;
  }

  // --- signals and spectra -----------------------------------------------------------------------------------------
  function twoPanels(yt0, yt1, xt, log) {
    return { margin: { l: 64, r: 10, t: 8, b: 40 }, uirevision: "sig" + (log ? "l" : ""),
      grid: { rows: 2, columns: 1, subplots: [["xy"], ["xy2"]], roworder: "top to bottom" },
      xaxis: { title: { text: xt } },
      yaxis: { title: { text: yt0 }, type: log ? "log" : "linear", exponentformat: "power" },
      yaxis2: { title: { text: yt1 }, type: log ? "log" : "linear", exponentformat: "power" },
      legend: { orientation: "h", y: -0.2, font: { size: 11 } } };
  }

  function sigTraces(s, key, color, dash, axis, showlegend, xkey) {
    return { x: s[xkey], y: s[key], type: "scatter", mode: "lines", yaxis: axis, showlegend, legendgroup: s.label,
      name: s.label + (ok(s.j) ? ` (J ${fj(s.j)})` : ""), line: { color, dash, width: 1.4 } };
  }

  function renderSignals() { timed("renderSignals", () => renderSignals_()); }
  const sigKey = (v) => JSON.stringify(["last", "best"].map((k) => v && v[k] ? [v[k].label, v[k].trial_id, v[k].attempt, v[k].j, v[k].source, (v[k].t || v[k].f || []).length] : null));
  let drawnSignals = null, drawnSpectra = null;

  function renderSignals_() {
    const sg = S.signals || {};
    const key = sigKey(sg);
    if (key === drawnSignals) return;
    drawnSignals = key;
    const data = [];
    for (const [k, color, dash] of [["best", COLORS.best, "dash"], ["last", COLORS.last, "solid"]]) {
      const s = sg[k];
      if (!s || !s.t || !s.t.length) continue;
      data.push(sigTraces(s, "accel_z", color, dash, "y", true, "t"));
      data.push(sigTraces(s, "pitch_rate", color, dash, "y2", false, "t"));
    }
    const last = sg.last;
    let cap = "";
    if (last && !last.valid) cap = `(last run rejected: ${last.reason})`;
    else if (last && last.mode === "distance") cap = "(distance grid shown as time at the target speed)";
    setText("sig-caption", cap);
    Plotly.react($("sigplot"), data, twoPanels("a_z, m/s²", "pitch rate, rad/s", "time in the aligned window, s", false), PLOT_CONFIG);
  }

  function renderSpectra() { timed("renderSpectra", () => renderSpectra_()); }
  function renderSpectra_() {
    const sp = S.spectra || {};
    const key = sigKey(sp);
    if (key === drawnSpectra) return;
    drawnSpectra = key;
    const data = [];
    for (const [k, color, dash] of [["best", COLORS.best, "dash"], ["last", COLORS.last, "solid"]]) {
      const s = sp[k];
      if (!s || !s.f || !s.f.length) continue;
      data.push(sigTraces(s, "accel_z", color, dash, "y", true, "f"));
      data.push(sigTraces(s, "pitch_rate", color, dash, "y2", false, "f"));
    }
    setText("spec-caption", sp.last ? `(${sp.last.source})` : "");
    Plotly.react($("specplot"), data, twoPanels("PSD a_z, (m/s²)²/Hz", "PSD pitch rate, (rad/s)²/Hz", "frequency, Hz", true), PLOT_CONFIG);
  }

  // --- tables -----------------------------------------------------------------------------------------------------
  function renderTable() { timed("renderTable", () => renderTable_()); }
  function renderTable_() {
    const rows = S.trials || [];
    const names = ((S.campaign || {}).dimensions || []).map((d) => d.name);
    if (!names.length && rows.length) names.push(...Object.keys(rows[0].params));
    const head = ["trial", "kind", ...names, "J", "predicted J ±2σ", "runs", "status"];
    const hh = head.map((h) => `<th>${esc(h)}</th>`).join("");
    if ($("trials-head").innerHTML !== hh) $("trials-head").innerHTML = hh;
    const best = S.best ? S.best.trial_id : -1;
    const cur = S.trial && S.trial.state_name !== "DONE" ? S.trial.trial_id : -1;
    $("trials-body").innerHTML = rows.slice().reverse().map((r) => {
      const cls = [r.trial_id === best ? "best" : "", r.trial_id === cur ? "current" : "", r.status === "failed" ? "failed" : ""].join(" ").trim();
      const rej = (r.rejected || []).map(([a, why]) => `run ${a} rejected: ${why}`).join("; ");
      const status = r.status + (r.reason ? `: ${r.reason}` : "") + (rej ? ` (${rej})` : "");
      return `<tr data-trial="${r.trial_id}" class="${cls}"><td>${r.trial_id}</td><td>${esc(r.kind)}</td>` +
        names.map((n) => `<td>${fp(r.params[n])}</td>`).join("") +
        `<td class="j">${fj(r.j)}</td><td>${ok(r.predicted_j) ? fj(r.predicted_j) + " ± " + fj(2 * (r.predicted_std || 0)) : "–"}</td>` +
        `<td>${r.attempts}</td><td class="reason-cell">${esc(status)}</td></tr>`;
    }).join("");
  }

  function renderDiag() {
    const list = S.diagnostics || [];
    $("diag-body").innerHTML = list.length ? list.map((d) =>
      `<tr><td>${esc(d.name)}</td><td class="lvl lvl-${esc(d.level)}">${esc(d.level)}</td><td>${esc(d.message)}</td>` +
      `<td>${ok(d.received_wall) ? Math.max(0, Date.now() / 1000 - d.received_wall).toFixed(0) + " s" : ""}</td></tr>`).join("")
      : `<tr><td colspan="4" class="muted">${S.mode === "offline" ? "diagnostics are not recorded in the campaign folder" : "no /diagnostics yet"}</td></tr>`;
  }

  function timed(name, fn) {
    const t0 = performance.now();
    try { return fn(); } finally {
      const t1 = performance.now();
      (T[name] = T[name] || []).push(+(t1 - t0).toFixed(1)); if (T[name].length > 50) T[name].shift();
      note("draw", name, t0, t1);
    }
  }

  window.bacCockpit = { state: S, timings: T, log: L };
  // plotly's first contour and first log axis cost more than later ones (its code warms up; on an idle machine the
  // first GP drawing took 74 ms without this, 50 ms with it, one run each, 2026-11-29): paid here, off screen,
  // while the page waits for its first data, not when the first GP view arrives mid-campaign
  function warmUp() {
    const div = document.createElement("div");
    div.style.cssText = "position:absolute;left:-10000px;top:0;width:320px;height:240px";
    document.body.appendChild(div);
    const layout = (extra) => Object.assign({ showlegend: false, margin: { l: 20, r: 0, t: 0, b: 20 } }, extra);
    const done = () => { try { Plotly.purge(div); } finally { div.remove(); } };
    // one after the other, each finished (plotly finishes a drawing asynchronously: a purge under it throws)
    Promise.resolve()
      .then(() => Plotly.newPlot(div, [
        { type: "contour", x: [0, 1], y: [0, 1], z: [[0, 1], [1, 0]], ncontours: 4, showscale: false },
        { type: "scatter", mode: "markers+text", x: [0.5], y: [0.5], text: ["1"] },
      ], layout({}), PLOT_CONFIG))
      .then(() => Plotly.react(div, [{ type: "scatter", mode: "lines", x: [1, 2], y: [1e-3, 1] }],
        layout({ yaxis: { type: "log" } }), PLOT_CONFIG))
      .then(() => setTimeout(done, 1000), () => setTimeout(done, 1000));
  }

  warmUp();
  renderBanner();
  connect();
})();
