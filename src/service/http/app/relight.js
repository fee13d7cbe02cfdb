// Relighting: the albedo shaded with the normal map under a movable light, Lambertian
// plus an optional Blinn-Phong term that exaggerates fine relief (specular enhancement).
// With the glossy solver's material maps (specular.png, roughness.png) the highlights are
// the fitted ones: the core's GGX lobe, π·D·G/(4 n·v) per unit specular albedo, seen from
// the camera (v = +z), which the viewer can switch off for Lambertian shading. Pixels the
// core fitted with a Beckmann lobe are shaded with the GGX lobe of the same width (the
// roughness map's), whose peak matches and whose tail is longer.
// Normals are normal.png's: the camera frame with y up, as the light is given.

import { context, program, texture, FULL_SCREEN_VERTEX } from "./gl.js";

const FRAGMENT = `#version 300 es
precision highp float;
in vec2 uv;
out vec4 color;
uniform sampler2D albedo, normals, mask, specularMap, roughnessMap;
uniform bool hasMask, material;
uniform vec3 light;
uniform float intensity, specular;
const float PI = 3.14159265;
// The core's lobe (src/core/reflectance/lobe.rs): GGX with separable Smith shadowing.
float ggx(vec3 n, vec3 l, float alpha) {
  float nl = dot(n, l);
  if (nl <= 0.0 || n.z <= 0.0) return 0.0;
  float nv = max(n.z, 0.05);
  float nh = dot(n, normalize(l + vec3(0, 0, 1)));
  if (nh <= 0.0) return 0.0;
  float a2 = alpha * alpha;
  float d = nh * nh * (a2 - 1.0) + 1.0;
  float D = a2 / (PI * d * d);
  float gl = 2.0 * nl / (nl + sqrt(a2 + (1.0 - a2) * nl * nl));
  float gv = 2.0 * nv / (nv + sqrt(a2 + (1.0 - a2) * nv * nv));
  return PI * D * gl * gv / (4.0 * nv);
}
void main() {
  vec3 t = texture(normals, uv).rgb;
  float inside = hasMask ? step(0.5, texture(mask, uv).r) : step(0.004, t.r + t.g + t.b);
  if (inside < 0.5) { color = vec4(0.07, 0.07, 0.08, 1); return; }
  vec3 n = normalize(t * 2.0 - 1.0);
  float a = texture(albedo, uv).r;
  float d = max(dot(n, light), 0.0);
  vec3 h = normalize(light + vec3(0, 0, 1));
  float s = d > 0.0 ? specular * pow(max(dot(n, h), 0.0), 48.0) : 0.0;
  if (material) {
    float rough = texture(roughnessMap, uv).r;
    if (rough > 0.0) s += texture(specularMap, uv).r * ggx(n, light, rough * rough);
  }
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
    // The material maps, when the job fitted them (the glossy solver).
    this.hasGloss = !!(images["specular.png"] && images["roughness.png"]);
    if (this.hasGloss) {
      this.textures.push(texture(gl, images["specular.png"], 3), texture(gl, images["roughness.png"], 4));
    }
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
    gl.uniform1i(u.specularMap, 3);
    gl.uniform1i(u.roughnessMap, 4);
    gl.uniform1i(u.material, this.hasGloss && params.material ? 1 : 0);
    gl.uniform3fv(u.light, params.dir);
    gl.uniform1f(u.intensity, params.intensity);
    gl.uniform1f(u.specular, params.specular);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  }
}
