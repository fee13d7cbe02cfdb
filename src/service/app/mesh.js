// The surface in 3-D: the job's mesh.glb (positions x right, y up, z the height; vertex
// normals; uvs into the albedo) with orbit, zoom and pan, textured with the albedo and lit
// by the relighting's light, which is in the same frame.

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
    const gl = this.gl;
    gl.clearColor(0.07, 0.07, 0.08, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
  }

  setMesh(buffer, albedo) {
    const gl = this.gl;
    const m = parseGlb(buffer);
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
