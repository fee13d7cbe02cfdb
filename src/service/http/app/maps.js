// The maps side by side (albedo, normals, heights in colour with their scale, confidence,
// mask), every one drawn at full resolution into a canvas and moved by one shared
// zoom/pan, so the same pixel is under the same spot in each.

const view = { scale: 1, x: 0, y: 0, width: 1, height: 1 };
const frames = [];

// A perceptual blue-to-yellow ramp (viridis, 5 stops), t in 0..1.
const RAMP = [
  [68, 1, 84],
  [59, 82, 139],
  [33, 145, 140],
  [94, 201, 98],
  [253, 231, 37],
];
function ramp(t) {
  const f = Math.min(0.9999, Math.max(0, t)) * (RAMP.length - 1);
  const i = Math.floor(f);
  const u = f - i;
  return RAMP[i].map((a, k) => a + (RAMP[i + 1][k] - a) * u);
}

function canvasOf(img, colour) {
  const c = document.createElement("canvas");
  c.width = img.naturalWidth;
  c.height = img.naturalHeight;
  const g = c.getContext("2d", { willReadFrequently: !!colour });
  g.drawImage(img, 0, 0);
  if (colour) {
    const data = g.getImageData(0, 0, c.width, c.height);
    const p = data.data;
    for (let i = 0; i < p.length; i += 4) {
      const inside = colour.mask ? colour.mask[i] > 127 : true;
      const [r, gr, b] = inside ? ramp(p[i] / 255) : [17, 17, 17];
      p[i] = r;
      p[i + 1] = gr;
      p[i + 2] = b;
    }
    g.putImageData(data, 0, 0);
  }
  return c;
}

function pixelsOf(img) {
  const c = document.createElement("canvas");
  c.width = img.naturalWidth;
  c.height = img.naturalHeight;
  const g = c.getContext("2d", { willReadFrequently: true });
  g.drawImage(img, 0, 0);
  return g.getImageData(0, 0, c.width, c.height).data;
}

// The height scale: the ramp with its end values in pixels, or metres with a pixel size.
function scaleBar(job) {
  const r = job.result || {};
  const size = job.options && job.options.mesh && job.options.mesh.pixel_size;
  const unit = size ? "m" : "px";
  const k = size || 1;
  const fmt = (v) => (v == null ? "?" : (v * k).toPrecision(3));
  const div = document.createElement("div");
  div.className = "scale";
  const bar = document.createElement("canvas");
  bar.width = 128;
  bar.height = 1;
  const g = bar.getContext("2d");
  for (let x = 0; x < 128; x++) {
    const [a, b, c] = ramp(x / 127);
    g.fillStyle = `rgb(${a},${b},${c})`;
    g.fillRect(x, 0, 1, 1);
  }
  bar.setAttribute("role", "img");
  bar.setAttribute("aria-label", `colour scale from ${fmt(r.height_min)} to ${fmt(r.height_max)} ${unit}`);
  const lo = document.createElement("span");
  lo.textContent = `${fmt(r.height_min)}`;
  const hi = document.createElement("span");
  hi.textContent = `${fmt(r.height_max)} ${unit}`;
  div.append(lo, bar, hi);
  return div;
}

function apply() {
  for (const { frame, canvas } of frames) {
    const box = frame.clientWidth;
    const fit = box / Math.max(view.width, view.height);
    const s = fit * view.scale;
    canvas.style.transform = `translate(${view.x * box}px, ${view.y * box}px) scale(${s})`;
  }
}

// Zoom by `k` about the point (fx, fy) of the frame (fractions of its width).
function zoom(k, fx = 0.5, fy = 0.5) {
  const next = Math.min(64, Math.max(0.25, view.scale * k));
  const r = next / view.scale;
  view.x = fx - (fx - view.x) * r;
  view.y = fy - (fy - view.y) * r;
  view.scale = next;
  apply();
}

function fitView() {
  view.scale = 1;
  view.x = (1 - view.width / Math.max(view.width, view.height)) / 2;
  view.y = (1 - view.height / Math.max(view.width, view.height)) / 2;
  apply();
}

// One image pixel per screen pixel, centred.
function fullView() {
  const box = frames.length ? frames[0].frame.clientWidth : 1;
  const fit = box / Math.max(view.width, view.height);
  zoom(1 / fit / view.scale / (window.devicePixelRatio || 1));
}

let wired = false;
function wireToolbar() {
  if (wired) return;
  wired = true;
  document.getElementById("zoom-in").addEventListener("click", () => zoom(1.5));
  document.getElementById("zoom-out").addEventListener("click", () => zoom(1 / 1.5));
  document.getElementById("zoom-fit").addEventListener("click", fitView);
  document.getElementById("zoom-full").addEventListener("click", fullView);
  window.addEventListener("resize", apply);
}

function wireFrame(frame) {
  frame.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      const b = frame.getBoundingClientRect();
      zoom(Math.exp(-e.deltaY * 0.002), (e.clientX - b.left) / b.width, (e.clientY - b.top) / b.height);
    },
    { passive: false },
  );
  let last = null;
  frame.addEventListener("pointerdown", (e) => {
    frame.setPointerCapture(e.pointerId);
    last = [e.clientX, e.clientY];
  });
  frame.addEventListener("pointermove", (e) => {
    if (!last || !frame.hasPointerCapture(e.pointerId)) return;
    const w = frame.clientWidth;
    view.x += (e.clientX - last[0]) / w;
    view.y += (e.clientY - last[1]) / w;
    last = [e.clientX, e.clientY];
    apply();
  });
  frame.addEventListener("pointerup", () => (last = null));
  frame.addEventListener("keydown", (e) => {
    const d = 0.05;
    const moves = { ArrowLeft: [d, 0], ArrowRight: [-d, 0], ArrowUp: [0, d], ArrowDown: [0, -d] };
    if (moves[e.key]) {
      view.x += moves[e.key][0];
      view.y += moves[e.key][1];
      apply();
    } else if (e.key === "+" || e.key === "=") zoom(1.5);
    else if (e.key === "-") zoom(1 / 1.5);
    else return;
    e.preventDefault();
  });
}

export function showMaps(root, images, job) {
  wireToolbar();
  frames.length = 0;
  const mask = images["mask.png"] ? pixelsOf(images["mask.png"]) : null;
  const panels = [
    ["albedo.png", "Albedo"],
    ["normal.png", "Normals (RGB = x, y up, z)"],
    ["height.png", "Height"],
    ["confidence.png", "Confidence"],
    ["mask.png", "Mask"],
  ];
  const figures = [];
  for (const [name, title] of panels) {
    const img = images[name];
    if (!img) continue;
    view.width = img.naturalWidth;
    view.height = img.naturalHeight;
    const fig = document.createElement("figure");
    fig.className = "map";
    const frame = document.createElement("div");
    frame.className = "frame";
    frame.tabIndex = 0;
    frame.setAttribute("role", "img");
    frame.setAttribute("aria-label", `${title}, ${img.naturalWidth} × ${img.naturalHeight} pixels`);
    const canvas = canvasOf(img, name === "height.png" ? { mask } : null);
    frame.append(canvas);
    wireFrame(frame);
    const cap = document.createElement("figcaption");
    cap.textContent = title;
    fig.append(frame, cap);
    if (name === "height.png") fig.append(scaleBar(job));
    figures.push(fig);
    frames.push({ frame, canvas });
  }
  root.replaceChildren(...figures);
  requestAnimationFrame(fitView);
}
