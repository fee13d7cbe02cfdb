// Relighting: the albedo shaded with the normal map under a movable light, Lambertian
// plus an optional Blinn-Phong term that exaggerates fine relief (specular enhancement).
// Normals are normal.png's: the camera frame with y up, as the light is given.

import { context, program, texture, FULL_SCREEN_VERTEX } from "./gl.js";

const FRAGMENT = `#version 300 es
precision highp float;
in vec2 uv;
out vec4 color;
uniform sampler2D albedo, normals, mask;
uniform bool hasMask;
uniform vec3 light;
uniform float intensity, specular;
void main() {
  vec3 t = texture(normals, uv).rgb;
  float inside = hasMask ? step(0.5, texture(mask, uv).r) : step(0.004, t.r + t.g + t.b);
  if (inside < 0.5) { color = vec4(0.07, 0.07, 0.08, 1); return; }
  vec3 n = normalize(t * 2.0 - 1.0);
  float a = texture(albedo, uv).r;
  float d = max(dot(n, light), 0.0);
  vec3 h = normalize(light + vec3(0, 0, 1));
  float s = d > 0.0 ? specular * pow(max(dot(n, h), 0.0), 48.0) : 0.0;
  color = vec4(vec3(clamp(intensity * (a * d + s), 0.0, 1.0)), 1);
}`;

// Azimuth (0° = image right, 90° = image top) and elevation above the image plane.
export function lightFromAngles(azimuth, elevation) {
  const a = (azimuth * Math.PI) / 180;
  const e = (elevation * Math.PI) / 180;
  return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
}

export class Relight {
  constructor(canvas) {
    this.canvas = canvas;
    this.gl = context(canvas);
    this.prog = program(this.gl, FULL_SCREEN_VERTEX, FRAGMENT);
    this.ready = false;
    this.params = null;
  }

  setImages(images) {
    const gl = this.gl;
    const albedo = images["albedo.png"];
    const normals = images["normal.png"];
    if (!albedo || !normals) {
      this.ready = false;
      return;
    }
    const w = albedo.naturalWidth;
    const h = albedo.naturalHeight;
    const k = Math.min(1, 1024 / Math.max(w, h));
    this.canvas.width = Math.round(w * k);
    this.canvas.height = Math.round(h * k);
    for (const t of this.textures || []) gl.deleteTexture(t);
    this.textures = [texture(gl, albedo, 0), texture(gl, normals, 1)];
    this.hasMask = !!images["mask.png"];
    if (this.hasMask) this.textures.push(texture(gl, images["mask.png"], 2));
    this.ready = true;
    if (this.params) this.draw(this.params);
  }

  draw(params) {
    this.params = params;
    if (!this.ready) return;
    const gl = this.gl;
    const { p, u } = this.prog;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.useProgram(p);
    gl.uniform1i(u.albedo, 0);
    gl.uniform1i(u.normals, 1);
    gl.uniform1i(u.mask, 2);
    gl.uniform1i(u.hasMask, this.hasMask ? 1 : 0);
    gl.uniform3fv(u.light, params.dir);
    gl.uniform1f(u.intensity, params.intensity);
    gl.uniform1f(u.specular, params.specular);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  }
}
