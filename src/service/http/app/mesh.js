// The surface in 3-D: the job's mesh.glb (positions x right, y up, z the height; vertex
// normals; uvs into the albedo), or when the job wrote none its height map as a grid in
// the same frame, with orbit, zoom and pan, textured with the albedo and lit by the
// relighting's light, which is in the same frame.

import { context, program, texture, mat4 } from "./gl.js";

const VERTEX = `#version 300 es
in vec3 position;
in vec3 normal;
in vec2 uv;
uniform mat4 mvp;
out vec3 n;
out vec2 t;
out vec3 p;
void main() {
  n = normal;
  t = uv;
  p = position;
  gl_Position = mvp * vec4(position, 1);
}`;

const FRAGMENT = `#version 300 es
precision highp float;
in vec3 n;
in vec2 t;
in vec3 p;
out vec4 color;
uniform sampler2D albedo;
uniform vec3 light, eye;
uniform float intensity, specular;
void main() {
  vec3 m = normalize(gl_FrontFacing ? n : -n);
  float a = texture(albedo, t).r;
  float d = max(dot(m, light), 0.0);
  vec3 h = normalize(light + normalize(eye - p));
  float s = d > 0.0 ? specular * pow(max(dot(m, h), 0.0), 48.0) : 0.0;
  color = vec4(vec3(clamp(0.08 * a + intensity * (a * d + s), 0.0, 1.0)), 1);
}`;

// The attributes and indices of a glTF 2.0 binary's first primitive.
export function parseGlb(buffer) {
  const view = new DataView(buffer);
  if (view.getUint32(0, true) !== 0x46546c67) throw new Error("mesh.glb is not a glTF binary");
  const jsonLength = view.getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 20, jsonLength)));
  const binStart = 20 + jsonLength + 8;
  const accessor = (i) => {
    const a = json.accessors[i];
    const bv = json.bufferViews[a.bufferView];
    const offset = binStart + (bv.byteOffset || 0) + (a.byteOffset || 0);
    const size = { SCALAR: 1, VEC2: 2, VEC3: 3 }[a.type];
    const Kind = { 5126: Float32Array, 5125: Uint32Array, 5123: Uint16Array }[a.componentType];
    return new Kind(buffer, offset, a.count * size);
  };
  const prim = json.meshes[0].primitives[0];
  return {
    position: accessor(prim.attributes.POSITION),
    normal: accessor(prim.attributes.NORMAL),
    uv: accessor(prim.attributes.TEXCOORD_0),
    indices: accessor(prim.indices),
    bounds: [json.accessors[prim.attributes.POSITION].min, json.accessors[prim.attributes.POSITION].max],
  };
}

// Vertices of the grid drawn from the maps: at most this many along the longer side.
const GRID = 256;

// A surface like parseGlb's from the maps: heights from height.png (its 0..1 spans the
// result's height_min..height_max, in pixels), normals from normal.png (8 bits of normal
// are smoother than the 8 bits a canvas gives of the 16-bit heights), uvs into the albedo;
// a cell is drawn where all its corners are inside the mask.
export function gridFromMaps(images, result) {
  const h = images["height.png"];
  const w = h.naturalWidth;
  const rows = h.naturalHeight;
  const step = Math.max(1, Math.ceil(Math.max(w, rows) / GRID));
  const nx = Math.ceil(w / step);
  const ny = Math.ceil(rows / step);
  // Drawn at the grid's size: the browser averages each cell's pixels.
  const pixels = (img) => {
    const c = document.createElement("canvas");
    c.width = nx;
    c.height = ny;
    const g = c.getContext("2d", { willReadFrequently: true });
    g.drawImage(img, 0, 0, nx, ny);
    return g.getImageData(0, 0, nx, ny).data;
  };
  const height = pixels(h);
  const normals = images["normal.png"] ? pixels(images["normal.png"]) : null;
  const mask = images["mask.png"] ? pixels(images["mask.png"]) : null;
  const lo = result.height_min ?? 0;
  const span = (result.height_max ?? 1) - lo;
  const n = nx * ny;
  const position = new Float32Array(n * 3);
  const normal = new Float32Array(n * 3);
  const uv = new Float32Array(n * 2);
  const inside = new Uint8Array(n);
  for (let j = 0; j < ny; j++) {
    for (let i = 0; i < nx; i++) {
      const k = j * nx + i;
      const p = k * 4;
      const x = Math.min(w - 1, (i + 0.5) * step - 0.5);
      const y = Math.min(rows - 1, (j + 0.5) * step - 0.5);
      position.set([x, rows - 1 - y, lo + (height[p] / 255) * span], k * 3);
      uv.set([(x + 0.5) / w, (y + 0.5) / rows], k * 2);
      let m = [0, 0, 1];
      if (normals) {
        m = [normals[p] / 127.5 - 1, normals[p + 1] / 127.5 - 1, normals[p + 2] / 127.5 - 1];
        const len = Math.hypot(...m);
        m = len > 0.1 ? m.map((v) => v / len) : [0, 0, 1];
      }
      normal.set(m, k * 3);
      inside[k] = mask ? mask[p] > 127 : normals ? normals[p] + normals[p + 1] + normals[p + 2] > 1 : 1;
    }
  }
  const indices = [];
  for (let j = 0; j + 1 < ny; j++) {
    for (let i = 0; i + 1 < nx; i++) {
      const a = j * nx + i;
      const [b, c, d] = [a + 1, a + nx, a + nx + 1];
      if (inside[a] && inside[b] && inside[c] && inside[d]) indices.push(a, c, b, b, c, d);
    }
  }
  const zs = [lo, lo + span];
  return {
    position,
    normal,
    uv,
    indices: new Uint32Array(indices),
    bounds: [
      [0, 0, Math.min(...zs)],
      [w - 1, rows - 1, Math.max(...zs)],
    ],
  };
}

export class MeshView {
  constructor(canvas) {
    this.canvas = canvas;
    this.gl = context(canvas);
    this.prog = program(this.gl, VERTEX, FRAGMENT);
    this.mesh = null;
    this.params = null;
    this.orbit = { yaw: 0, pitch: -0.6, zoom: 1, pan: [0, 0] };
    this.wire();
  }

  setMessage(text) {
    this.mesh = null;
    this.canvas.setAttribute("aria-description", text);
    delete this.canvas.dataset.surface;
    const gl = this.gl;
    gl.clearColor(0.07, 0.07, 0.08, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
  }

  // `surface`: what parseGlb or gridFromMaps return; `kind` names it on the canvas
  // (data-surface: "mesh" or "grid").
  setSurface(m, albedo, kind) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const attribute = (name, data, size) => {
      const loc = gl.getAttribLocation(this.prog.p, name);
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
    };
    attribute("position", m.position, 3);
    attribute("normal", m.normal, 3);
    attribute("uv", m.uv, 2);
    const ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, m.indices, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    if (this.tex) gl.deleteTexture(this.tex);
    this.tex = texture(gl, albedo, 0);
    const [lo, hi] = m.bounds;
    this.centre = lo.map((v, i) => (v + hi[i]) / 2);
    this.radius = Math.hypot(...hi.map((v, i) => v - lo[i])) / 2 || 1;
    this.mesh = {
      vao,
      count: m.indices.length,
      type: m.indices instanceof Uint32Array ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT,
    };
    this.canvas.removeAttribute("aria-description");
    this.canvas.dataset.surface = kind;
    this.draw();
  }

  setLight(params) {
    this.params = params;
    this.draw();
  }

  draw() {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(0.07, 0.07, 0.08, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!this.mesh || !this.params) return;
    const o = this.orbit;
    const dist = (this.radius * 1.9) / o.zoom;
    // Camera: back along z, tilted by pitch about x, turned by yaw about the model's z.
    const model = mat4.multiply(mat4.rotateZ(o.yaw), mat4.translate(this.centre.map((v) => -v)));
    const viewM = mat4.multiply(
      mat4.translate([o.pan[0] * this.radius, o.pan[1] * this.radius, -dist]),
      mat4.rotateX(o.pitch),
    );
    const proj = mat4.perspective(0.7, this.canvas.width / this.canvas.height, dist / 50, dist * 4);
    const mvp = mat4.multiply(proj, mat4.multiply(viewM, model));
    // The eye in model space, for the highlight: invert the rotations.
    const c = Math.cos(o.pitch);
    const s = Math.sin(o.pitch);
    const e = [0, s * dist, c * dist];
    const eye = [
      Math.cos(-o.yaw) * e[0] - Math.sin(-o.yaw) * e[1] + this.centre[0],
      Math.sin(-o.yaw) * e[0] + Math.cos(-o.yaw) * e[1] + this.centre[1],
      e[2] + this.centre[2],
    ];
    const { p, u } = this.prog;
    gl.useProgram(p);
    gl.enable(gl.DEPTH_TEST);
    gl.uniformMatrix4fv(u.mvp, false, mvp);
    gl.uniform3fv(u.light, this.params.dir);
    gl.uniform3fv(u.eye, eye);
    gl.uniform1f(u.intensity, this.params.intensity);
    gl.uniform1f(u.specular, this.params.specular);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.tex);
    gl.uniform1i(u.albedo, 0);
    gl.bindVertexArray(this.mesh.vao);
    gl.drawElements(gl.TRIANGLES, this.mesh.count, this.mesh.type, 0);
    gl.bindVertexArray(null);
  }

  wire() {
    const c = this.canvas;
    const o = this.orbit;
    let last = null;
    c.addEventListener("pointerdown", (e) => {
      c.setPointerCapture(e.pointerId);
      last = [e.clientX, e.clientY];
    });
    c.addEventListener("pointermove", (e) => {
      if (!last || !c.hasPointerCapture(e.pointerId)) return;
      const dx = (e.clientX - last[0]) / c.clientWidth;
      const dy = (e.clientY - last[1]) / c.clientHeight;
      last = [e.clientX, e.clientY];
      if (e.shiftKey || e.buttons === 4) {
        o.pan[0] += dx * 2 / o.zoom;
        o.pan[1] -= dy * 2 / o.zoom;
      } else {
        o.yaw += dx * 4;
        o.pitch = Math.max(-1.5, Math.min(1.5, o.pitch + dy * 4));
      }
      this.draw();
    });
    c.addEventListener("pointerup", () => (last = null));
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        o.zoom = Math.max(0.2, Math.min(20, o.zoom * Math.exp(-e.deltaY * 0.002)));
        this.draw();
      },
      { passive: false },
    );
    c.addEventListener("keydown", (e) => {
      const k = { ArrowLeft: [-0.1, 0], ArrowRight: [0.1, 0], ArrowUp: [0, -0.1], ArrowDown: [0, 0.1] }[e.key];
      if (k) {
        o.yaw += k[0];
        o.pitch = Math.max(-1.5, Math.min(1.5, o.pitch + k[1]));
      } else if (e.key === "+" || e.key === "=") o.zoom *= 1.25;
      else if (e.key === "-") o.zoom /= 1.25;
      else return;
      e.preventDefault();
      this.draw();
    });
  }
}
