// OCC staff console: renders /api/events (server-sent events) and posts the buttons' commands.
"use strict";

const cards = new Map();

function esc(value) {
  return String(value ?? "").replace(/[&<>"']/g, (c) => (
    { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}

function num(value, digits = 1) {
  if (value === null || value === undefined || value === "") return "–";
  if (typeof value !== "number") return esc(value);
  return Number.isInteger(value) ? String(value) : value.toFixed(digits);
}

function when(t) {
  return t ? new Date(t * 1000).toLocaleTimeString() : "";
}

function kvTable(rows) {
  return "<table class=\"kv\">" + rows.map(([k, v]) =>
    `<tr><td>${esc(k)}</td><td>${v}</td></tr>`).join("") + "</table>";
}

function plain(value) {
  if (Array.isArray(value)) return value.map((v) => num(v, 3)).join(", ");
  if (value && typeof value === "object") return esc(JSON.stringify(value));
  return num(value, 3);
}

function histogramSvg(h) {
  if (!h) return "<p class=\"muted\">waiting for the first statistics…</p>";
  const counts = h.counts;
  const W = 40, H = 110;  // one bin's width and the bars' height, in viewBox units
  const top = Math.log10(1 + Math.max(1, ...counts));
  const label = (e) => (e === null ? "∞" : e >= 1000 ? `${e / 1000}k` : `${e}`);
  let bars = "";
  counts.forEach((n, i) => {
    const hgt = n ? Math.max(1, (Math.log10(1 + n) / top) * H) : 0;
    const late = h.edges_us[i] >= 1000 ? " late" : "";
    bars += `<rect class="bar${late}" x="${i * W + 2}" y="${H - hgt}" width="${W - 4}" ` +
      `height="${hgt}"><title>${label(h.edges_us[i])} to ${label(h.edges_us[i + 1])} µs: ${n} ticks</title></rect>`;
    bars += `<text x="${i * W}" y="${H + 16}" text-anchor="middle">${label(h.edges_us[i])}</text>`;
  });
  const s = h.summary || {};
  const span = h.window_s === null ? "since start" : `last ${num(h.window_s)} s`;
  return `<svg viewBox="-14 0 ${counts.length * W + 20} ${H + 22}" role="img" ` +
    `aria-label="lateness histogram">${bars}</svg>` +
    `<div class="muted">tick lateness, µs (log counts), ${span}: ${num(h.ticks)} ticks, ` +
    `p50 ${num(s.p50)} · p99 ${num(s.p99)} · max ${num(s.max)}</div>`;
}

function vec(v) {
  return Array.isArray(v) ? `(${v.map((c) => num(c, 3)).join(", ")})` : "–";
}

// the forces panel: a slave's contact force, a master's displayed force and its passivity
function forcesHtml(f) {
  if (!f) return "<p class=\"muted\">no force reported</p>";
  const rows = [];
  if (f.contact) {
    const c = f.contact;
    rows.push(["contact force (instrument)", `<b>${num(c.magnitude_n, 2)} N</b> ${vec(c.force_n)}`]);
    rows.push(["source", `${esc(c.source)}${c.tared ? " · tared" : ""}`]);
  }
  if (f.hand) {
    const h = f.hand, p = h.passivity || {};
    rows.push(["displayed (hand)", `<b>${num(h.displayed_magnitude_n, 2)} N</b> ${vec(h.displayed_n)}`]);
    rows.push(["feedback (slave)", h.force_feedback
      ? `${num(h.feedback_magnitude_n, 2)} N ${vec(h.feedback_n)} · scale ${num(h.force_scale, 2)}`
      : "off"]);
    rows.push(["fixtures", vec(h.fixture_n)]);
    rows.push(["clamped ticks", num(h.clamped_ticks)]);
    const state = !p.on ? "off (observer only)" : p.engaged ? "<b>damping</b>" : "on, idle";
    rows.push(["passivity", `${state} · energy ${num(p.energy_mj, 2)} mJ · ` +
      `dissipated ${num(p.dissipated_mj, 2)} mJ · damping ${num(p.damping, 2)}`]);
  }
  return kvTable(rows);
}

// the cell panel: the members around the patient, what holds this one, the last stop's origin
function cellHtml(c) {
  if (!c) return "<p class=\"muted\">in no cell</p>";
  const rows = [["cell · policy", `${esc(c.name)} · ${esc(c.policy)}${c.left ? " · <b>left</b>" : ""}`]];
  rows.push([`${esc(c.me)} (this)`, c.cause ? `<b>stopped</b>: ${esc(c.cause)}` +
    (c.origin && c.origin !== c.me ? ` (origin ${esc(c.origin)})` : "") : "no stop"]);
  for (const m of c.members) {
    const heard = m.heard_ms_ago === null ? "not heard yet" : `heard ${num(m.heard_ms_ago)} ms ago`;
    const chain = m.chain_ok === false ? " · <b>chain mismatch</b>" : "";
    const stop = m.cause ? ` · ${esc(m.cause)}` : "";
    rows.push([esc(m.name), `${esc(m.state || "?")} · ${heard}${m.left ? " · left" : ""}${chain}${stop}`]);
  }
  const held = Object.entries(c.latched || {});
  rows.push(["holding for", held.length ? held.map(([o, w]) => `<b>${esc(o)}</b>: ${esc(w)}`).join("<br>") : "nobody"]);
  if (c.last_stop) {
    const p = c.last_stop.propagation_ms;
    rows.push(["last stop", `${esc(c.last_stop.origin)}: ${esc(c.last_stop.cause)} · ${when(c.last_stop.wall)}` +
      (p === null || p === undefined ? "" : ` · ${num(p, 1)} ms after it`)]);
  }
  return kvTable(rows);
}

// the drives panel: each CANopen node's CiA 402 state, NMT state and last EMCY, per driver
function drivesHtml(drives) {
  if (!drives) return "<p class=\"muted\">no drive reports its nodes</p>";
  return drives.map((drv) => {
    const load = drv.bus_load === null ? "" : ` · bus load ${num(drv.bus_load * 100, 0)} %`;
    const fault = drv.last_fault ? `<div class="alert">last fault: ${esc(drv.last_fault)}</div>` : "";
    const rows = drv.nodes.map((n) => {
      const e = n.last_emcy;
      const emcy = e ? `<b>${esc(e.code)}</b> ${esc(e.meaning)} (register ${esc(e.register)})` : "none";
      const enabled = n.state === "OPERATION ENABLED" ? "" : " class=\"off\"";
      return `<tr><td>${esc(n.joint)}</td><td>${num(n.node_id)}</td><td${enabled}>${esc(n.state)}</td>` +
        `<td>${esc(n.statusword)}</td><td>${esc(n.nmt)}</td><td>${emcy} · ${num(n.emcys)} in all</td></tr>`;
    }).join("");
    return `<div class="muted">${esc(drv.driver)}${load}</div>${fault}` +
      "<table><tr><th>joint</th><th>node</th><th>CiA 402 state</th><th>statusword</th>" +
      `<th>NMT</th><th>last EMCY</th></tr>${rows}</table>`;
  }).join("");
}

function render(card, d) {
  const el = (sel) => card.querySelector(sel);
  card.classList.toggle("stale", !d.connected);
  el(".name").textContent = d.name;
  el(".address").textContent = d.address;
  const link = el(".link-badge");
  // statistics older than a few polls: the daemon (or its worker) is not answering
  const stale = d.connected && (d.stats_age_s === null || d.stats_age_s > 3);
  link.textContent = !d.connected ? `disconnected${d.link.error ? ": " + d.link.error : ""}`
    : d.stats_age_s === null ? "connected, no statistics yet"
      : `connected · statistics ${num(d.stats_age_s)} s old`;
  link.className = "link-badge" + (d.connected && !stale ? "" : " down");
  const state = el(".state");
  state.textContent = d.state || "?";
  state.className = "state " + (d.state || "");
  el(".cause").textContent = (d.reason ? `cause: ${d.reason}` : "") +
    (d.state_since ? ` (since ${when(d.state_since)})` : "");
  el(".alert").textContent = d.last_alert ? `alert: ${d.last_alert}` : "";
  card.querySelectorAll("button").forEach((b) => { b.disabled = !d.connected; });

  const lp = d.loop || {};
  const lat = lp.lateness_us || {}, comp = lp.compute_us || {};
  el(".loop").innerHTML = kvTable([
    ["rate / CPU", `${num(lp.rate_hz)} Hz · ${num(lp.cpu_percent)} %`],
    ["lateness p50 / p99 / max", `${num(lat.p50)} / ${num(lat.p99)} / ${num(lat.max)} µs`],
    ["compute p50 / p99", `${num(comp.p50)} / ${num(comp.p99)} µs`],
    ["overruns · late > 1 ms · missed", `${num(lp.overruns)} · ${num(lp.late_over_1ms)} · ${num(lp.missed_ticks)}`],
  ]);
  el(".hist").innerHTML = histogramSvg(d.histogram);

  el(".streams").innerHTML = d.streams.length
    ? "<table><tr><th>interface</th><th>role</th><th>peers</th><th>rx/s</th><th>tx/s</th>" +
      "<th>dropped</th></tr>" + d.streams.map((s) =>
        `<tr><td title="${esc(s.transport)}">${esc(s.interface)}</td>` +
        `<td>${esc(s.role)}</td><td>${num(s.peers)}</td><td>${num(s.rx_per_s)}</td>` +
        `<td>${num(s.tx_per_s)}</td><td>${num(s.dropped)}</td></tr>`
      ).join("") + "</table>"
    : "<p class=\"muted\">no statistics yet</p>";

  const loss = d.loss;
  el(".loss").innerHTML = loss
    ? kvTable([
      ["now", loss.tripped ? "<b>tripped</b>" : loss.holding ? "<b>holding</b>" : "following"],
      ["holds · resumes · trips", `${num(loss.holds)} · ${num(loss.resumes)} · ${num(loss.trips)}`],
      ["lost packets · longest run", `${num(loss.lost_total)} · ${num(loss.max_run)}`],
      ["duplicates · reordered · stale", `${num(loss.duplicates)} · ${num(loss.reordered)} · ${num(loss.stale)}`],
      ["accepted / received", `${num(loss.accepted)} / ${num(loss.received)}`],
    ])
    : "<p class=\"muted\">no loss monitor on this daemon</p>";

  el(".forces").innerHTML = forcesHtml(d.forces);
  el(".cell").innerHTML = cellHtml(d.cell);
  el(".drives").innerHTML = drivesHtml(d.drives);

  const hl = Object.entries(d.highlights || {});
  el(".highlights").innerHTML = hl.length
    ? kvTable(hl.map(([k, v]) => [k, plain(v)]))
    : "<p class=\"muted\">none reported</p>";

  const more = [];
  for (const [title, obj] of [["controller", d.controller], ["watchdog", d.watchdog],
    ["supervisor", d.supervisor], ["commands", d.commands]]) {
    if (obj && typeof obj === "object") {
      for (const [k, v] of Object.entries(obj)) more.push([`${title}.${k}`, plain(v)]);
    }
  }
  el(".details").innerHTML = more.length ? kvTable(more) : "";

  const log = el(".log");
  log.innerHTML = d.log.length
    ? "<table>" + d.log.slice().reverse().map((e) =>
      `<tr class="${esc(e.kind)}"><td>${when(e.t)}</td><td>${esc(e.name)}</td><td>${esc(e.text)}</td></tr>`
    ).join("") + "</table>"
    : "<p class=\"muted\">nothing yet</p>";
}

async function send(card, id, command) {
  const reply = card.querySelector(".reply");
  reply.textContent = `${command}…`;
  reply.className = "reply";
  try {
    const res = await fetch(`/api/daemons/${encodeURIComponent(id)}/${command}`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: "{}",
    });
    const body = await res.json();
    reply.textContent = `${command}: ${body.ok ? "OK" : "FAIL"} ${body.message || body.error || ""}`;
    reply.className = "reply" + (body.ok ? "" : " fail");
  } catch (err) {
    reply.textContent = `${command}: ${err}`;
    reply.className = "reply fail";
  }
}

function cardFor(d) {
  let card = cards.get(d.id);
  if (!card) {
    const tpl = document.getElementById("daemon-card");
    card = tpl.content.firstElementChild.cloneNode(true);
    card.dataset.daemon = d.id;
    card.querySelectorAll("button[data-command]").forEach((b) => {
      b.addEventListener("click", () => send(card, d.id, b.dataset.command));
    });
    document.getElementById("daemons").appendChild(card);
    cards.set(d.id, card);
  }
  return card;
}

function connect() {
  const feed = document.getElementById("feed");
  const source = new EventSource("/api/events");
  source.addEventListener("open", () => { feed.textContent = "live"; feed.className = "feed live"; });
  source.addEventListener("error", () => { feed.textContent = "console unreachable, retrying…"; feed.className = "feed"; });
  source.addEventListener("daemons", (ev) => {
    for (const d of JSON.parse(ev.data)) render(cardFor(d), d);
    feed.textContent = `live · ${new Date().toLocaleTimeString()}`;
  });
}

connect();
