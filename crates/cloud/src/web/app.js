// canlift web UI: formats values from their NXg metadata (form type, list, hints, unit),
// keeps them live from the lift's Server-Sent Events, shows times in local time and runs the
// edit dialog (put, and privilege elevation when the gateway asks for it). No build step.
"use strict";

const csrf = document.querySelector('meta[name="csrf"]')?.content ?? "";

// The page's texts in its language (the server's catalogue, web/i18n.rs); the arguments after
// the English text fill its `{}` in turn.
const TEXTS = JSON.parse(document.getElementById("texts")?.textContent || "{}");
function t(english, ...args) {
  let i = 0;
  return (TEXTS[english] ?? english).replace(/\{\}/g, () => String(args[i++] ?? ""));
}

function normalMplex(m) {
  const hex = String(m).replace(/^0x/i, "");
  return "0x" + hex.toUpperCase();
}

function parse(text, fallback) {
  try {
    return text ? JSON.parse(text) : fallback;
  } catch {
    return fallback;
  }
}

// The text an operator reads for a raw value (NXg §6.1: list, hints, min/max).
// Whether the object's hints say zero means off.
function offAtZero(d) {
  return Boolean((parse(d.hints, {}) ?? {}).show_off_at_zero);
}

function formatted(d, raw) {
  const text = String(raw ?? "");
  const v = Number(text);
  if (text === "" || Number.isNaN(v)) return text;
  const hints = parse(d.hints, {}) ?? {};
  const list = parse(d.list, []) ?? [];
  if (hints.show_off_at_zero && v === 0) return t("off");
  if (d.max !== "" && v === Number(d.max)) {
    if (hints.show_unlimited_at_max) return t("unlimited");
    if (hints.show_undefined_at_max) return t("undefined");
  }
  if (d.form === "15" && list.length) {
    const item = list[v - Number(d.min || 0)];
    if (item !== undefined) return item;
  }
  if (d.form === "4" && list.length) {
    const on = list.filter((_, i) => (v >>> i) & 1);
    return on.length ? on.join(", ") : t("none");
  }
  return text;
}

// CiA 417 and CiA 301 values whose meaning the NXg form types cannot carry: the door
// statusword (bits 12–15 an enumeration, bit 0 the safety contact) and the error register.
const DOOR_STATES = {
  0: t("closed"), 2: t("closing"), 3: t("opened"), 5: t("opening"), 6: t("re-opening"),
  7: t("stopped"), 14: t("error"), 15: t("not installed"),
};
const ERROR_BITS = [
  t("generic"), t("current"), t("voltage"), t("temperature"), t("communication"),
  t("device profile"), t("reserved"), t("manufacturer"),
];

function profileText(mplex, v) {
  const index = String(mplex).slice(2, 6).toUpperCase();
  if (index === "6301") {
    const state = (v >>> 12) & 15;
    const text = DOOR_STATES[state] ?? t("state {}", state);
    return v & 1 && state !== 15 ? t("{}, contact closed", text) : text;
  }
  if (index === "1001") {
    const on = ERROR_BITS.filter((_, i) => (v >>> i) & 1);
    return on.length ? on.join(", ") : t("no error");
  }
  return null;
}

const locale = document.documentElement.lang || undefined;

// The value and unit a person reads: words without a unit, millimetres from a metre on as
// metres, numbers with the locale's separators.
function reading(d, raw) {
  const text = formatted(d, raw);
  const v = Number(text);
  if (text === "" || Number.isNaN(v)) return { text, unit: "" };
  const words = profileText(d.mplex, v);
  if (words !== null) return { text: words, unit: "" };
  if (d.unit === "mm" && Math.abs(v) >= 1000) {
    const m = (v / 1000).toLocaleString(locale, { minimumFractionDigits: 3, maximumFractionDigits: 3 });
    return { text: m, unit: "m" };
  }
  const digits = text.includes(".") ? text.split(".")[1].length : 0;
  return { text: v.toLocaleString(locale, { maximumFractionDigits: digits }), unit: d.unit ?? "" };
}

function show(el, raw) {
  el.dataset.raw = raw;
  const { text, unit } = reading(el.dataset, raw);
  const v = el.querySelector(".v");
  if (v) v.textContent = text;
  const u = el.querySelector(".u");
  if (u) u.textContent = unit;
}

function localTimes(root) {
  for (const el of root.querySelectorAll("time[data-ms], svg [data-ms]")) {
    el.textContent = new Date(Number(el.dataset.ms)).toLocaleString(locale);
  }
  const zone = Intl.DateTimeFormat().resolvedOptions().timeZone;
  for (const el of root.querySelectorAll("p.zone")) el.textContent = t("times in {}", zone);
}

// A history chart: the stored value in force at the pointer (a choice by its name) with its
// local time; dragging across selects a period to zoom into.
function chartHover(svg) {
  const d = svg.dataset;
  const points = (d.points || "").split(",").filter(Boolean).map((p) => p.split(":").map(Number));
  const names = parse(d.labels, null);
  const cursor = svg.querySelector("line.cursor");
  const label = svg.querySelector("text.hover");
  const band = svg.querySelector("rect.zoom");
  if (!points.length || !cursor || !label || !band) return;
  const [from, to, left, right] = [d.from, d.to, d.left, d.right].map(Number);
  const xOf = (e) => {
    const box = svg.getBoundingClientRect();
    return Math.min(right, Math.max(left, ((e.clientX - box.left) / box.width) * svg.viewBox.baseVal.width));
  };
  const timeOf = (x) => from + ((x - left) / (right - left)) * (to - from);
  let start = null;
  svg.addEventListener("pointerdown", (e) => {
    start = xOf(e);
  });
  svg.addEventListener("pointermove", (e) => {
    const x = xOf(e);
    const at = timeOf(x);
    let now = points[0];
    for (const p of points) if (p[0] <= at) now = p;
    const shown = names ? (names[now[1] - Number(d.min || 0)] ?? String(now[1])) : now[1].toLocaleString(locale);
    cursor.setAttribute("x1", x);
    cursor.setAttribute("x2", x);
    cursor.setAttribute("visibility", "visible");
    label.textContent = t("{} at {}", shown, new Date(now[0]).toLocaleString(locale));
    if (start !== null) {
      band.setAttribute("x", Math.min(start, x));
      band.setAttribute("width", Math.abs(x - start));
      band.setAttribute("visibility", "visible");
    }
  });
  svg.addEventListener("pointerleave", () => {
    cursor.setAttribute("visibility", "hidden");
    band.setAttribute("visibility", "hidden");
    label.textContent = "";
    start = null;
  });
  svg.addEventListener("pointerup", (e) => {
    const x = xOf(e);
    if (start !== null && Math.abs(x - start) > 8) {
      const url = new URL(location.href);
      url.searchParams.set("from", Math.round(timeOf(Math.min(start, x))));
      url.searchParams.set("to", Math.round(timeOf(Math.max(start, x))));
      url.searchParams.delete("minutes");
      location.href = url.toString();
    }
    start = null;
    band.setAttribute("visibility", "hidden");
  });
}

// A history page whose period ends now follows the lift: a pushed value of a charted object
// redraws the charts (at most every 2 s).
function liveCharts(mplex) {
  const charts = document.querySelector("#charts[data-live]");
  if (!charts || !charts.dataset.live.split(",").includes(normalMplex(mplex))) return;
  clearTimeout(liveCharts.pending);
  liveCharts.pending = setTimeout(async () => {
    await refreshParts(["#charts"]);
    for (const svg of document.querySelectorAll("svg.chart")) chartHover(svg);
  }, 2000);
}

function setOnline(lift, online) {
  for (const b of document.querySelectorAll("[data-online]")) {
    if (b.dataset.online !== lift) continue;
    b.textContent = online ? t("online") : t("offline");
    b.classList.toggle("online", online);
    b.classList.toggle("offline", !online);
  }
}

function liveValues(lift) {
  const events = new EventSource(`/api/v1/lifts/${encodeURIComponent(lift)}/events`);
  events.addEventListener("value", (e) => {
    const object = parse(e.data, {}).object ?? {};
    if (object.node) return; // pushes from other nodes are not on this page
    liveCharts(object.mplex);
    const value = Array.isArray(object.value) ? object.value.join(", ") : object.value;
    for (const el of document.querySelectorAll(`[data-mplex="${normalMplex(object.mplex)}"]`)) {
      show(el, value);
      el.classList.remove("fresh");
      void el.offsetWidth; // restart the highlight
      el.classList.add("fresh");
    }
  });
  events.addEventListener("online", (e) => {
    const d = parse(e.data, {});
    setOnline(d.lift, Boolean(d.online));
  });
  // Alarm changes and bus events: the page's alarm and event sections are fetched anew.
  let pending = null;
  const later = () => {
    clearTimeout(pending);
    pending = setTimeout(() => refreshParts(["#alarms", "#events"]), 300);
  };
  events.addEventListener("alarm", later);
  events.addEventListener("event", later);
}

// Each table cell learns its column's heading (data-label): phones show rows as cards.
function labelCells(root) {
  for (const table of root.querySelectorAll("table")) {
    const heads = [...table.querySelectorAll("thead th")].map((th) => th.textContent.trim());
    for (const row of table.querySelectorAll("tbody tr")) {
      [...row.children].forEach((td, i) => {
        if (heads[i]) td.dataset.label = heads[i];
      });
    }
  }
}

// Replace `parts` (selectors) of the page with their current rendering.
async function refreshParts(parts) {
  const r = await fetch(location.href);
  if (!r.ok) return;
  const fresh = new DOMParser().parseFromString(await r.text(), "text/html");
  for (const part of parts) {
    const now = document.querySelector(part);
    const next = fresh.querySelector(part);
    if (now && next) now.replaceWith(next);
  }
  localTimes(document);
  labelCells(document);
}

// The fleet page refreshes its own table (this page of lifts, alarms and faults included)
// every 10 s.
function refreshFleet() {
  setInterval(() => refreshParts(["table.fleet tbody", "p.summary"]), 10000);
}

async function api(method, path, body) {
  const r = await fetch(path, {
    method,
    headers: { "content-type": "application/json", "x-csrf-token": csrf },
    body: JSON.stringify(body),
  });
  const answer = await r.json().catch(() => ({}));
  return { ok: r.ok, status: r.status, answer };
}

function describe(e) {
  const code = typeof e.code === "number" && e.code > 999 ? ` (${e.code.toString(16).toUpperCase().padStart(8, "0")}h)` : "";
  return (e.message ?? t("failed")) + code;
}

const LEVELS = { 1: t("service"), 2: t("setup") };

// The rights this browser tab was granted on the lift (the gateway grants them per connection
// and for a time, NXg §6.4): level, until (ms), and how long the last grant lasted (s).
function rights(lift) {
  return parse(sessionStorage.getItem(`rights:${lift}`), {}) ?? {};
}

function held(lift, level) {
  const r = rights(lift);
  return r.level >= level && r.until > Date.now();
}

// "service rights for 4:59 more", counting down; hidden when none are held.
function showRights(lift) {
  const line = document.querySelector("p.rights");
  if (!line) return;
  const tick = () => {
    const r = rights(lift);
    const left = Math.round(((r.until ?? 0) - Date.now()) / 1000);
    line.hidden = !(left > 0);
    if (left > 0) {
      const mm = Math.floor(left / 60), ss = String(left % 60).padStart(2, "0");
      line.textContent = t("{} rights for {} more", LEVELS[r.level] ?? t("elevated"), `${mm}:${ss}`);
    }
  };
  tick();
  clearInterval(showRights.timer);
  showRights.timer = setInterval(tick, 1000);
}

function editDialog(lift) {
  const dialog = document.getElementById("edit");
  if (!dialog) return;
  showRights(lift);
  const form = dialog.querySelector("form");
  const status = dialog.querySelector(".status");
  const elevate = dialog.querySelector(".elevate");
  let target = null;

  function field(d) {
    const holder = dialog.querySelector(".field");
    holder.replaceChildren();
    const list = parse(d.list, []) ?? [];
    let input;
    if (d.form === "15" && list.length) {
      input = document.createElement("select");
      list.forEach((text, i) => {
        const o = document.createElement("option");
        o.value = String(Number(d.min || 0) + i);
        o.textContent = `${o.value}: ${text}`;
        input.append(o);
      });
    } else {
      input = document.createElement("input");
      const numeric = d.min !== "" && d.form !== "1";
      input.type = numeric ? "number" : "text";
      if (numeric) {
        // Where the catalog says zero means off, 0 is offered below the range.
        const off = offAtZero(d);
        input.min = off ? Math.min(0, Number(d.min)) : d.min;
        input.max = d.max;
        input.step = d.form === "11" ? "any" : "1";
        if (off) input.placeholder = t("0 = off");
      }
    }
    input.name = "value";
    input.required = true;
    // The current value, unless it is outside what may be written (a passenger call reads 0).
    const raw = d.raw ?? "";
    const outside = input.type === "number" && raw !== "" &&
      (Number(raw) < Number(input.min) || (input.max !== "" && Number(raw) > Number(input.max)));
    input.value = outside ? "" : raw;
    holder.append(input);
    return input;
  }

  dialog.querySelector("button.cancel")?.addEventListener("click", () => dialog.close());

  for (const button of document.querySelectorAll("button.edit")) {
    button.addEventListener("click", () => {
      target = button.closest("[data-mplex]");
      const d = target.dataset;
      dialog.querySelector(".title").textContent = `${d.name} (${d.mplex})`;
      dialog.querySelector(".hint").textContent = target.querySelector("[title]")?.title ?? "";
      const off = offAtZero(d);
      const range = d.min !== "" ? `${off ? t("0 (off) or ") : ""}${d.min} … ${d.max} ${d.unit}` : "";
      dialog.querySelector(".range").textContent = range;
      field(d);
      // An object above privilege 0 asks for the lift's password before the first save,
      // unless this tab holds the rights already.
      const level = Number(d.privilege || 0);
      const needed = level >= 1 && level <= 2 && !held(lift, level);
      elevate.hidden = !needed;
      elevate.querySelector("select").value = level === 2 ? "2" : "1";
      const lasts = rights(lift).duration;
      elevate.querySelector(".why").textContent = needed
        ? t("Changing this needs {} rights: enter the lift's {} password. ", LEVELS[level], LEVELS[level]) +
          (lasts ? t("The rights then last {} min.", Math.round(lasts / 60)) : t("The rights then last as long as the lift grants them."))
        : "";
      form.elements.namedItem("password").value = "";
      status.textContent = "";
      status.className = "status";
      dialog.showModal();
    });
  }

  form.addEventListener("submit", async (e) => {
    if (e.submitter?.value !== "save" || !target) return;
    e.preventDefault();
    const d = target.dataset;
    const base = `/api/v1/lifts/${encodeURIComponent(lift)}`;
    status.textContent = t("saving…");
    if (!elevate.hidden) {
      const grant = await api("POST", `${base}/privilege`, {
        privilege: Number(form.elements.namedItem("privilege").value),
        password: form.elements.namedItem("password").value,
      });
      if (!grant.ok) {
        status.textContent = t("Elevation refused: {}", describe(grant.answer));
        status.className = "status error";
        return;
      }
      const level = Number(form.elements.namedItem("privilege").value);
      const duration = Number(grant.answer.duration ?? 0);
      sessionStorage.setItem(`rights:${lift}`, JSON.stringify({ level, duration, until: Date.now() + duration * 1000 }));
      elevate.hidden = true;
      showRights(lift);
    }
    const value = form.elements.namedItem("value").value;
    const put = await api("PUT", `${base}/objects/${d.mplex}`, {
      value,
      datatype: Number(d.datatype),
      physunit: Number(d.physunit),
    });
    if (put.ok) {
      for (const el of document.querySelectorAll(`[data-mplex="${d.mplex}"]`)) show(el, value);
      status.textContent = t("saved");
      status.className = "status ok";
      dialog.close();
      return;
    }
    // A gateway's privilege refusal (not the portal's own 403) opens the elevation fields: the
    // rights this tab had are gone (expired, or the gateway reconnected).
    if (put.status === 403 && put.answer.code > 999) {
      sessionStorage.removeItem(`rights:${lift}`);
      showRights(lift);
      elevate.hidden = false;
      status.textContent = t("{} — elevate and save again.", describe(put.answer));
    } else {
      status.textContent = describe(put.answer);
    }
    status.className = "status error";
  });
}

// The floor buttons: a passenger call (privilege 0) to the floor pressed.
function callButtons(lift) {
  const holder = document.querySelector("div.floors");
  const status = document.querySelector("p.call-status");
  if (!holder || !status) return;
  for (const button of holder.querySelectorAll("button.floor")) {
    button.addEventListener("click", async () => {
      const floor = button.value;
      const d = holder.dataset;
      const put = await api("PUT", `/api/v1/lifts/${encodeURIComponent(lift)}/objects/${d.mplex}`, {
        value: floor,
        datatype: Number(d.datatype),
        physunit: Number(d.physunit),
      });
      status.textContent = put.ok ? t("called to floor {}", floor) : describe(put.answer);
      status.className = put.ok ? "call-status ok" : "call-status error";
    });
  }
}

document.addEventListener("DOMContentLoaded", () => {
  for (const el of document.querySelectorAll("[data-mplex]")) show(el, el.dataset.raw);
  localTimes(document);
  labelCells(document);
  for (const svg of document.querySelectorAll("svg.chart")) chartHover(svg);
  const lift = document.body.dataset.lift;
  if (lift) {
    liveValues(lift);
    editDialog(lift);
    callButtons(lift);
  } else if (document.querySelector("table.fleet")) {
    refreshFleet();
  }
});
