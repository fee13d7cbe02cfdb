// The photostereo browser app: submit a job, follow it, look at its result. Plain ES
// modules split by concern: this file wires the page; api.js talks to the server;
// form.js builds the options form; maps.js, relight.js and mesh.js draw the result, the
// last two over gl.js.

import { api, setKey, getKey, followJob } from "./api.js";
import { buildOptionsForm, readOptions } from "./form.js";
import { showMaps } from "./maps.js";
import { Relight, lightFromAngles } from "./relight.js";
import { MeshView, parseGlb, gridFromMaps } from "./mesh.js";

const $ = (id) => document.getElementById(id);
const TERMINAL = ["succeeded", "failed", "cancelled"];
const IMAGE = /\.(png|bmp|jpe?g|tiff?|exr)$/i;

// ---------------------------------------------------------------- problems next to fields

const FIELDS = ["key", "files", "lights", "calibration", "options", "submit", "jobs"];

function clearProblems() {
  for (const f of FIELDS) $("problem-" + f).hidden = true;
}

function showProblem(field, title, detail) {
  const el = $("problem-" + field);
  el.replaceChildren();
  const t = document.createElement("strong");
  t.textContent = title;
  const d = document.createElement("span");
  d.textContent = (detail || "").trim();
  el.append(t, d);
  el.hidden = false;
}

// Which field a problem of POST /v1/jobs is about, from the part or option it names.
function fieldOf(problem, optionNames) {
  const d = (problem.detail || "").toLowerCase();
  if (/^options:|unknown field|unknown variant/.test(d)) return "options";
  if (/calibration/.test(d) && !$("calibration-field").hidden) return "calibration";
  if (/light table|^lights|light_directions|intensit/.test(d)) return "lights";
  if (/^mask:|image|archive|file|part|png|zip|pixels|bytes/.test(d)) return "files";
  if (optionNames.some((n) => d.includes(n))) return "options";
  return "submit";
}

// ---------------------------------------------------------------- the upload

const upload = { images: [], mask: null, archive: null };

function isMask(name) {
  return /^mask\.(png|bmp|tiff?)$/i.test(name);
}

async function takeFiles(files) {
  clearProblems();
  $("normals-input").value = ""; // images replace a normal map
  upload.images = [];
  upload.mask = null;
  upload.archive = null;
  let table = null;
  for (const f of files) {
    const name = f.name;
    if (/\.zip$/i.test(name)) upload.archive = f;
    else if (/^light_directions\.(csv|json)$/i.test(name) || (/\.(csv|json)$/i.test(name) && !table)) table = f;
    else if (isMask(name)) upload.mask = f;
    else if (IMAGE.test(name)) upload.images.push(f);
  }
  upload.images.sort((a, b) => a.name.localeCompare(b.name));
  if (table) $("lights").value = (await table.text()).trim() + "\n";
  if (upload.archive && upload.images.length) {
    showProblem("files", "Two kinds of upload", "Drop either a .zip or the folder's files, not both; the .zip is sent.");
    upload.images = [];
  }
  if (!upload.archive && !upload.images.length && files.length) {
    showProblem("files", "No images", "None of the files is an image (PNG, BMP, JPEG, TIFF, EXR) or a .zip.");
  }
  listFiles();
}

function listFiles() {
  const items = [];
  const add = (text) => {
    const li = document.createElement("li");
    li.textContent = text;
    items.push(li);
  };
  if (upload.archive) add(`archive ${upload.archive.name} (${kib(upload.archive.size)})`);
  for (const f of upload.images) add(`${f.name} (${kib(f.size)})`);
  if (upload.mask) add(`mask ${upload.mask.name}`);
  $("file-list").replaceChildren(...items);
}

const kib = (n) => (n < 1 << 20 ? `${Math.ceil(n / 1024)} KiB` : `${(n / (1 << 20)).toFixed(1)} MiB`);

// Files of a drop, folders walked (webkitGetAsEntry works in Chromium and Firefox).
async function droppedFiles(dt) {
  const entries = [...dt.items].map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
  if (!entries.length) return [...dt.files];
  const out = [];
  const walk = async (entry) => {
    if (entry.isFile) {
      out.push(await new Promise((ok, bad) => entry.file(ok, bad)));
    } else if (entry.isDirectory) {
      const reader = entry.createReader();
      for (;;) {
        const batch = await new Promise((ok, bad) => reader.readEntries(ok, bad));
        if (!batch.length) break;
        for (const e of batch) await walk(e);
      }
    }
  };
  for (const e of entries) await walk(e);
  return out;
}

function wireDrop() {
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => {
    e.preventDefault();
    drop.classList.add("over");
  });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", async (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    takeFiles(await droppedFiles(e.dataTransfer));
  });
  // A normal map replaces the images (a dropped mask goes with it).
  $("normals-input").addEventListener("change", () => {
    clearProblems();
    upload.images = [];
    upload.archive = null;
    listFiles();
  });
  for (const id of ["file-input", "folder-input"]) {
    $(id).addEventListener("change", async (e) => {
      await takeFiles([...e.target.files]);
      e.target.value = ""; // so that picking the same files again is a change too
    });
  }
}

let optionSchema = null;

async function submit(e) {
  e.preventDefault();
  clearProblems();
  const form = new FormData();
  const calibration = $("calibration-field").hidden ? "" : $("calibration").value;
  const normals = $("normals-input").files[0];
  if (normals) {
    form.append("normals", normals, normals.name);
    if ($("convention").value !== "opengl") form.append("convention", $("convention").value);
  } else if (upload.archive) {
    form.append("archive", upload.archive, upload.archive.name);
  } else {
    if (!upload.images.length) {
      showProblem("files", "No images", "Drop or pick the images of a set (or a .zip of its folder).");
      return;
    }
    if (calibration) form.append("calibration", calibration);
    else {
      const lights = $("lights").value.trim();
      if (!lights) {
        showProblem("lights", "No light table", "Type or paste one row per image, or drop the folder's light_directions.csv.");
        return;
      }
      form.append("lights", lights);
    }
    for (const f of upload.images) form.append("images", f, f.name);
  }
  if (upload.mask) form.append("mask", upload.mask, upload.mask.name);
  let options;
  try {
    options = readOptions($("options"), optionSchema);
  } catch (err) {
    showProblem("options", "Invalid option", err.message);
    return;
  }
  if (Object.keys(options).length) form.append("options", JSON.stringify(options));
  $("submit").disabled = true;
  try {
    const job = await api("POST", "/v1/jobs", form);
    jobs.upsert(job);
    jobs.watch(job, true);
  } catch (err) {
    const names = optionSchema ? Object.keys(optionSchema.properties || {}) : [];
    if (err.status === 401) askForKey(err);
    else showProblem(err.problem ? fieldOf(err.problem, names) : "submit", err.title, err.detail);
  } finally {
    $("submit").disabled = false;
  }
}

// ---------------------------------------------------------------- the jobs list

const jobs = {
  rows: new Map(), // id -> { job, tr, stop }
  selected: null,

  async load() {
    clearProblemsOf("jobs");
    if (access.keyRequired && !getKey()) return askForKey();
    try {
      const page = await api("GET", "/v1/jobs?limit=20");
      clearProblemsOf("key");
      for (const job of page.jobs.reverse()) {
        this.upsert(job);
        if (!TERMINAL.includes(job.status)) this.watch(job, false);
      }
    } catch (err) {
      if (err.status === 401) askForKey(err);
      else showProblem("jobs", err.title, err.detail);
    }
  },

  upsert(job) {
    let row = this.rows.get(job.id);
    if (!row) {
      const tr = document.createElement("tr");
      tr.innerHTML = `<td><code></code></td><td></td><td data-testid="job-status"></td><td></td>
        <td><progress max="1" value="0"></progress></td><td class="actions"></td>`;
      $("jobs").tBodies[0].prepend(tr);
      row = { job, tr, stop: null };
      this.rows.set(job.id, row);
    }
    row.job = job;
    const [idCell, created, status, stage, progress, actions] = row.tr.cells;
    idCell.firstChild.textContent = job.id.slice(0, 8);
    idCell.firstChild.title = job.id;
    created.textContent = new Date(job.created_at).toLocaleTimeString();
    status.textContent = job.status;
    status.className = "status-" + job.status;
    if (job.status === "failed" && job.error) status.title = `${job.error.title}: ${job.error.detail}`;
    stage.textContent = job.stage || "";
    const bar = progress.firstChild;
    bar.value = job.progress;
    bar.setAttribute("aria-label", `progress of job ${job.id.slice(0, 8)}`);
    const buttons = [];
    const button = (text, fn) => {
      const b = document.createElement("button");
      b.type = "button";
      b.textContent = text;
      b.setAttribute("aria-label", `${text} job ${job.id.slice(0, 8)}`);
      b.addEventListener("click", fn);
      buttons.push(b);
    };
    if (job.status === "succeeded") button("View", () => this.show(job.id));
    if (job.status === "failed" && job.error) button("Why", () => showProblem("jobs", job.error.title, " " + job.error.detail));
    if (TERMINAL.includes(job.status)) button("Delete", () => this.remove(job.id));
    else button("Cancel", () => this.remove(job.id));
    actions.replaceChildren(...buttons);
  },

  // Follow a job's events (polling when the stream cannot be had); open its result when
  // `open` and it succeeds.
  watch(job, open) {
    const row = this.rows.get(job.id);
    if (row.stop) row.stop();
    row.stop = followJob(job.id, (next) => {
      if (!this.rows.has(job.id)) return;
      if (next === null) return this.drop(job.id);
      this.upsert(next);
      if (open && next.status === "succeeded") this.show(job.id);
    });
  },

  async remove(id) {
    clearProblemsOf("jobs");
    try {
      const job = await api("DELETE", `/v1/jobs/${id}`);
      if (job) this.upsert(job);
      else this.drop(id);
    } catch (err) {
      showProblem("jobs", err.title, " " + err.detail);
    }
  },

  drop(id) {
    const row = this.rows.get(id);
    if (!row) return;
    if (row.stop) row.stop();
    row.tr.remove();
    this.rows.delete(id);
    if (this.selected === id) {
      $("result").hidden = true;
      this.selected = null;
    }
  },

  show(id) {
    for (const [other, row] of this.rows) row.tr.classList.toggle("selected", other === id);
    this.selected = id;
    showResult(this.rows.get(id).job);
  },
};

function clearProblemsOf(field) {
  $("problem-" + field).hidden = true;
}

// ---------------------------------------------------------------- the result view

let relight = null;
let meshView = null;
let shown = 0; // the result shown last; older loads give way

async function showResult(job) {
  const token = ++shown;
  $("result").hidden = false;
  $("result-title").textContent = `Result of job ${job.id.slice(0, 8)}`;
  showSummary(job);
  showDownloads(job);
  const a = job.artifacts || {};
  const images = {};
  await Promise.all(
    ["albedo.png", "normal.png", "height.png", "confidence.png", "mask.png", "specular.png", "roughness.png"]
      .filter((n) => a[n])
      .map(async (n) => {
        images[n] = await loadImage(a[n]);
      }),
  );
  if (token !== shown) return;
  showMaps($("maps"), images, job);
  // A normal map's job has no albedo: its surface is white on the mask.
  const surface = { ...images, "albedo.png": images["albedo.png"] || images["mask.png"] };
  relight ??= new Relight($("relight-canvas"));
  relight.setImages(surface);
  // The switch between the fitted highlights and Lambertian shading, where there are any.
  $("material-switch").hidden = !relight.hasGloss;
  light.apply();
  meshView ??= new MeshView($("mesh-canvas"));
  if (a["mesh.glb"]) {
    const glb = await (await api.raw("GET", a["mesh.glb"])).arrayBuffer();
    if (token !== shown) return;
    meshView.setSurface(parseGlb(glb), surface["albedo.png"], "mesh");
  } else if (images["height.png"] && surface["albedo.png"]) {
    meshView.setSurface(gridFromMaps(surface, job.result || {}), surface["albedo.png"], "grid");
  } else {
    meshView.setMessage("This job wrote neither mesh.glb nor height.png and albedo.png (choose them in the outputs to see the surface).");
  }
  light.apply();
}

async function loadImage(url) {
  const blob = await (await api.raw("GET", url)).blob();
  const img = new Image();
  img.src = URL.createObjectURL(blob);
  await img.decode();
  return img;
}

const mapCounts = (c) =>
  `${c.used} used (${c.back_facing} back-facing, ${c.not_unit} renormalised); off the mask: ` +
  `${c.black} black, ${c.zero_length} zero-length, ${c.non_finite} NaN or infinite, ` +
  `${c.transparent} transparent, ${c.outside_mask} outside the mask`;

function showSummary(job) {
  const r = job.result || {};
  const ms = (a, b) => (a && b ? `${((new Date(b) - new Date(a)) / 1000).toFixed(2)} s` : "–");
  const rows = [
    ["size", r.width ? `${r.width} × ${r.height} px` : "–"],
    ["lights", r.light_count ?? "–"],
    ["light condition number", fmt(r.light_condition_number)],
    ["object pixels", r.object_pixels ?? "–"],
    // A normals job's: what the reader did with each pixel of the map.
    ...(r.counts ? [["normal map pixels", mapCounts(r.counts)]] : []),
    r.depth_min != null
      ? ["depth", `${fmt(r.depth_min)} to ${fmt(r.depth_max)}${r.unit ? ` ${r.unit}` : ""}`]
      : ["heights", r.height_min != null ? `${fmt(r.height_min)} to ${fmt(r.height_max)} px` : "–"],
    // A near-light job's alternations of solve and integration.
    ...(r.iterations != null
      ? [["near-light iterations", `${r.iterations}${r.converged === false ? " (the normals had not settled)" : ""}`]]
      : []),
    ...(r.estimated_intensities
      ? [["estimated intensities", `${r.estimated_intensities.map((e) => fmt(e.intensity)).join(", ")} (as a light table: lights.json)`]]
      : []),
    ["mean confidence", fmt(r.confidence_mean)],
    ["reprojection RMS", fmt(r.reprojection_rms)],
    // The glossy solver's: where its lobe was kept, the residual it leaves there, and
    // the lobe the pixels shared.
    ...(r.glossy_pixels != null
      ? [["glossy pixels", `${r.glossy_pixels}${r.glossy_residual_rms != null ? ` (residual RMS ${fmt(r.glossy_residual_rms)}, Lambertian ${fmt(r.glossy_lambertian_rms)})` : ""}`]]
      : []),
    ...(r.glossy_material
      ? [["shared lobe", `${r.glossy_material.facets === "beckmann" ? "Beckmann" : "GGX"}, roughness ${fmt(r.glossy_material.roughness)}`]]
      : []),
    ["unreliable pixels", r.unreliable_pixels ?? "–"],
    ["queued", ms(job.created_at, job.started_at)],
    ["ran", ms(job.started_at, job.finished_at)],
  ];
  const dl = document.createElement("dl");
  for (const [k, v] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    dl.append(dt, dd);
  }
  $("summary").replaceChildren(dl);
  // Timings and warnings are in result.json.
  const report = job.artifacts && job.artifacts["result.json"];
  if (!report) return;
  api("GET", report)
    .then((rep) => {
      const add = (k, v, cls) => {
        const dt = document.createElement("dt");
        dt.textContent = k;
        const dd = document.createElement("dd");
        dd.textContent = v;
        if (cls) dd.className = cls;
        dl.append(dt, dd);
      };
      const t = rep.timings_ms || [];
      if (t.length) add("timings", t.map((x) => `${x.stage} ${x.ms.toFixed(1)} ms`).join(", "));
      const w = rep.warnings || [];
      add("warnings", w.length ? w.join("; ") : "none", w.length ? "warnings" : "");
    })
    .catch(() => {});
}

const fmt = (v) => (typeof v === "number" ? (Math.abs(v) >= 100 ? v.toFixed(0) : v.toPrecision(3)) : "–");

function showDownloads(job) {
  const items = Object.entries(job.artifacts || {}).map(([name, url]) => {
    const li = document.createElement("li");
    const a = document.createElement("a");
    a.href = url;
    a.textContent = name;
    a.download = name;
    // With an API key a plain link would be refused: fetch with the key, save the blob.
    a.addEventListener("click", async (e) => {
      if (!getKey()) return;
      e.preventDefault();
      const blob = await (await api.raw("GET", url)).blob();
      const tmp = document.createElement("a");
      tmp.href = URL.createObjectURL(blob);
      tmp.download = name;
      tmp.click();
      setTimeout(() => URL.revokeObjectURL(tmp.href), 10000);
    });
    li.append(a);
    return li;
  });
  $("downloads").replaceChildren(...items);
}

// ---------------------------------------------------------------- the light

const light = {
  azimuth: 135,
  elevation: 45,

  set(azimuth, elevation) {
    this.azimuth = ((azimuth + 540) % 360) - 180;
    this.elevation = Math.min(90, Math.max(0, elevation));
    this.apply();
  },

  apply() {
    $("azimuth").value = this.azimuth;
    $("elevation").value = this.elevation;
    $("azimuth-out").textContent = `${Math.round(this.azimuth)}°`;
    $("elevation-out").textContent = `${Math.round(this.elevation)}°`;
    $("intensity-out").textContent = (+$("intensity").value).toFixed(2);
    $("specular-out").textContent = (+$("specular").value).toFixed(2);
    const params = {
      dir: lightFromAngles(this.azimuth, this.elevation),
      intensity: +$("intensity").value,
      specular: +$("specular").value,
      material: $("material").checked,
    };
    drawWidget(params.dir);
    if (relight) relight.draw(params);
    if (meshView) meshView.setLight(params);
  },
};

// The hemisphere seen from above (from the camera): a point at (x, y) inside the unit
// disc is the direction (x, y, sqrt(1 - x² - y²)).
function drawWidget([x, y]) {
  const c = $("light-widget");
  const g = c.getContext("2d");
  const r = c.width / 2 - 6;
  g.clearRect(0, 0, c.width, c.height);
  g.save();
  g.translate(c.width / 2, c.height / 2);
  g.fillStyle = "#f0f2f6";
  g.strokeStyle = "#889";
  g.beginPath();
  g.arc(0, 0, r, 0, 2 * Math.PI);
  g.fill();
  g.stroke();
  for (const el of [15, 45]) {
    g.beginPath();
    g.arc(0, 0, r * Math.cos((el * Math.PI) / 180), 0, 2 * Math.PI);
    g.setLineDash([3, 3]);
    g.stroke();
  }
  g.setLineDash([]);
  g.fillStyle = "#f0a500";
  g.strokeStyle = "#553";
  g.beginPath();
  g.arc(x * r, -y * r, 7, 0, 2 * Math.PI);
  g.fill();
  g.stroke();
  g.restore();
}

// Dragging on `canvas` moves the light: the pointer's place in the canvas, as a point of
// the unit disc (radius the canvas's half width less `inset` of its pixels), is the light
// seen from the camera, as on the hemisphere widget and in relighting viewers.
function dragsLight(canvas, inset) {
  const fromPointer = (e) => {
    const box = canvas.getBoundingClientRect();
    const rx = box.width / 2 - inset * (box.width / canvas.width);
    const ry = box.height / 2 - inset * (box.height / canvas.height);
    let x = (e.clientX - box.left - box.width / 2) / rx;
    let y = -(e.clientY - box.top - box.height / 2) / ry;
    const len = Math.hypot(x, y);
    if (len > 1) {
      x /= len;
      y /= len;
    }
    const el = (Math.acos(Math.min(1, Math.hypot(x, y))) * 180) / Math.PI;
    const az = (Math.atan2(y, x) * 180) / Math.PI;
    light.set(az, el);
  };
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    fromPointer(e);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (canvas.hasPointerCapture(e.pointerId)) fromPointer(e);
  });
}

function wireLight() {
  const c = $("light-widget");
  dragsLight(c, 6);
  dragsLight($("relight-canvas"), 0);
  c.addEventListener("keydown", (e) => {
    const step = e.shiftKey ? 10 : 2;
    const moves = { ArrowLeft: [step, 0], ArrowRight: [-step, 0], ArrowUp: [0, step], ArrowDown: [0, -step] };
    const m = moves[e.key];
    if (!m) return;
    e.preventDefault();
    light.set(light.azimuth + m[0], light.elevation + m[1]);
  });
  $("azimuth").addEventListener("input", (e) => light.set(+e.target.value, light.elevation));
  $("elevation").addEventListener("input", (e) => light.set(light.azimuth, +e.target.value));
  for (const id of ["intensity", "specular", "material"]) $(id).addEventListener("input", () => light.apply());
  for (const b of document.querySelectorAll(".presets button")) {
    b.addEventListener("click", () => light.set(+b.dataset.azimuth, +$("rake").value));
  }
}

// ---------------------------------------------------------------- the API key

// Whether the server needs a key (from /app/auth.json, which needs none): with no key
// yet, the page asks for one instead of calling the API and being refused.
const access = { keyRequired: false };

// Ask for the key beside its field: the server's 401 problem when there is one (a wrong
// or revoked key), else that one is needed.
function askForKey(err) {
  for (const id of [...jobs.rows.keys()]) jobs.drop(id);
  if (err) showProblem("key", err.title, ` ${err.detail}`);
  else showProblem("key", "This server needs an API key", " Enter yours here (it is kept for this tab only).");
  $("api-key").focus();
}

// ---------------------------------------------------------------- start

// Calibrations are offered only when the server documents the route.
let hasCalibrations = false;
// The listed calibrations by id, for the positions of the one picked.
const calibrations = new Map();

// With several balls a calibration places its lights: list them under the picker.
function showPositions() {
  const table = $("calibration-positions");
  const c = calibrations.get($("calibration").value);
  table.hidden = !(c && c.position_unit);
  if (table.hidden) return;
  const unit = c.position_unit === "ball_diameter" ? `the unit of the balls' diameter, ${c.ball_diameter}` : "ball radii";
  const origin = c.position_origin === "camera" ? "the camera" : "the first ball's centre";
  table.caption.textContent = `Light positions in ${unit}, from ${origin}`;
  const fmt = (v) => v.toFixed(3);
  const rows = c.lights.map((l) => {
    const tr = document.createElement("tr");
    const p = l.position;
    const cells = p ? [l.name, fmt(p.x), fmt(p.y), fmt(p.z), fmt(p.residual)] : [l.name, "rays parallel", "", "", ""];
    for (const text of cells) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    return tr;
  });
  table.tBodies[0].replaceChildren(...rows);
}

async function loadCalibrations() {
  if (!hasCalibrations || (access.keyRequired && !getKey())) return;
  try {
    const answer = await api("GET", "/v1/calibrations");
    const list = answer.calibrations || [];
    const select = $("calibration");
    select.replaceChildren(select.options[0]);
    calibrations.clear();
    for (const c of list) {
      calibrations.set(c.id, c);
      const o = document.createElement("option");
      o.value = c.id;
      // e.g. "2025-11-25 19:34 · 12 lights, least confidence 0.78 (5d1c2f0a)"
      const when = c.created_at.slice(0, 16).replace("T", " ");
      const confidences = c.lights
        .map((l) => l.highlight && l.highlight.confidence)
        .filter((v) => typeof v === "number");
      const least = confidences.length ? `, least confidence ${Math.min(...confidences).toFixed(2)}` : "";
      const balls = c.more_circles && c.more_circles.length ? `, ${c.more_circles.length + 1} balls` : "";
      o.textContent = `${when} · ${c.lights.length} lights${balls}${least} (${c.id.slice(0, 8)})`;
      select.append(o);
    }
    $("calibration-field").hidden = false;
    showPositions();
  } catch {
    $("calibration-field").hidden = true;
  }
}

async function start() {
  const key = $("api-key");
  key.value = getKey();
  key.addEventListener("change", () => {
    setKey(key.value.trim());
    clearProblemsOf("key");
    jobs.load();
    loadCalibrations();
  });
  wireDrop();
  wireLight();
  $("job-form").addEventListener("submit", submit);
  $("calibration").addEventListener("change", showPositions);
  $("refresh-jobs").addEventListener("click", () => jobs.load());
  light.apply();
  try {
    access.keyRequired = (await api("GET", "/app/auth.json")).api_key_required;
  } catch {
    // the server does not answer: the calls below say so
  }
  try {
    const doc = await api("GET", "/openapi.json");
    optionSchema = buildOptionsForm($("options"), doc);
    hasCalibrations = !!doc.paths["/v1/calibrations"];
  } catch (err) {
    showProblem("options", "The option set could not be read", ` ${err.detail}; jobs get the defaults.`);
  }
  $("options-loading").remove();
  await Promise.all([jobs.load(), loadCalibrations()]);
}

start();
