// canlift web UI: formats values from their NXg metadata (form type, list, hints, unit),
// keeps them live from the lift's Server-Sent Events, shows times in local time and runs the
// edit dialog (put, and privilege elevation when the gateway asks for it). No build step.
"use strict";

const csrf = document.querySelector('meta[name="csrf"]')?.content ?? "";

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
function formatted(d, raw) {
  const text = String(raw ?? "");
  const v = Number(text);
  if (text === "" || Number.isNaN(v)) return text;
  const hints = parse(d.hints, {}) ?? {};
  const list = parse(d.list, []) ?? [];
  if (hints.show_off_at_zero && v === 0) return "off";
  if (d.max !== "" && v === Number(d.max)) {
    if (hints.show_unlimited_at_max) return "unlimited";
    if (hints.show_undefined_at_max) return "undefined";
  }
  if (d.form === "15" && list.length) {
    const item = list[v - Number(d.min || 0)];
    if (item !== undefined) return item;
  }
  if (d.form === "4" && list.length) {
    const on = list.filter((_, i) => (v >>> i) & 1);
    return on.length ? on.join(", ") : "none";
  }
  return text;
}

function show(el, raw) {
  el.dataset.raw = raw;
  const v = el.querySelector(".v");
  if (v) v.textContent = formatted(el.dataset, raw);
  const u = el.querySelector(".u");
  if (u) u.textContent = el.dataset.unit ?? "";
}

function localTimes(root) {
  for (const t of root.querySelectorAll("time[data-ms]")) {
    t.textContent = new Date(Number(t.dataset.ms)).toLocaleString();
  }
}

function setOnline(lift, online) {
  for (const b of document.querySelectorAll("[data-online]")) {
    if (b.dataset.online !== lift) continue;
    b.textContent = online ? "online" : "offline";
    b.classList.toggle("online", online);
    b.classList.toggle("offline", !online);
  }
}

function liveValues(lift) {
  const events = new EventSource(`/api/v1/lifts/${encodeURIComponent(lift)}/events`);
  events.addEventListener("value", (e) => {
    const object = parse(e.data, {}).object ?? {};
    if (object.node) return; // pushes from other nodes are not on this page
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
  return (e.message ?? "failed") + code;
}

function editDialog(lift) {
  const dialog = document.getElementById("edit");
  if (!dialog) return;
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
        input.min = d.min;
        input.max = d.max;
        input.step = d.form === "11" ? "any" : "1";
      }
    }
    input.name = "value";
    input.required = true;
    input.value = d.raw ?? "";
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
      const range = d.min !== "" ? `${d.min} … ${d.max} ${d.unit}` : "";
      dialog.querySelector(".range").textContent = range;
      field(d);
      elevate.hidden = true;
      elevate.querySelector("select").value = d.privilege === "2" ? "2" : "1";
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
    status.textContent = "saving…";
    if (!elevate.hidden) {
      const grant = await api("POST", `${base}/privilege`, {
        privilege: Number(form.elements.namedItem("privilege").value),
        password: form.elements.namedItem("password").value,
      });
      if (!grant.ok) {
        status.textContent = `Elevation refused: ${describe(grant.answer)}`;
        status.className = "status error";
        return;
      }
    }
    const value = form.elements.namedItem("value").value;
    const put = await api("PUT", `${base}/objects/${d.mplex}`, {
      value,
      datatype: Number(d.datatype),
      physunit: Number(d.physunit),
    });
    if (put.ok) {
      for (const el of document.querySelectorAll(`[data-mplex="${d.mplex}"]`)) show(el, value);
      status.textContent = "saved";
      status.className = "status ok";
      dialog.close();
      return;
    }
    // A gateway's privilege refusal (not the portal's own 403) opens the elevation fields.
    if (put.status === 403 && put.answer.code > 999) {
      elevate.hidden = false;
      status.textContent = `${describe(put.answer)} — elevate and save again.`;
    } else {
      status.textContent = describe(put.answer);
    }
    status.className = "status error";
  });
}

document.addEventListener("DOMContentLoaded", () => {
  for (const el of document.querySelectorAll("[data-mplex]")) show(el, el.dataset.raw);
  localTimes(document);
  const lift = document.body.dataset.lift;
  if (lift) {
    liveValues(lift);
    editDialog(lift);
  } else if (document.querySelector("table.fleet")) {
    refreshFleet();
  }
});
