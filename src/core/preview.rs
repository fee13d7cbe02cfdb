//! `preview.png`: the reconstructed surface from an oblique view, like MATLAB's `surf`.
//!
//! The height map is laid out as a landscape in the mesh's frame (x = column, y = −row,
//! z = height; under a camera, the unprojected points with y flipped, which is the same
//! orientation), so the top of the object is the far side and appears at the top of the
//! picture. An orthographic camera raised 40° above that plane and turned 30° looks at
//! it; a light above-left of the camera shades it (Lambert, times the albedo). A small
//! z-buffered rasteriser draws a decimated mesh with 2×2 supersampling.

use image::{Rgb, RgbImage};
use rayon::prelude::*;

use super::mesh;
use super::options::{MeshNormals, MeshOptions};
use super::reconstruction::Reconstruction;
use crate::core::vec3::{cross, dot};

/// Camera elevation above the image plane and turn about its normal, in degrees.
const ELEVATION_DEG: f64 = 40.0;
const AZIMUTH_DEG: f64 = -30.0;
/// ≈ 250k triangles: finer than that is invisible at preview sizes and only costs time.
const MAX_VERTICES: usize = 125_000;
/// Light neutral grey with a hint of blue: a gray surface never matches it exactly.
pub const BACKGROUND: [u8; 3] = [217, 222, 230];
/// Share of light that reaches surfaces facing away from the lamp, so they stay legible.
const AMBIENT: f32 = 0.15;
/// Free border around the object, as a fraction of each side.
const MARGIN: f64 = 0.05;
/// Rows of supersampled pixels per parallel band.
const BAND_ROWS: usize = 32;
/// Supersampled pixels above this are not worth the memory; render 1×1 instead.
const MAX_SUPERSAMPLED: u64 = 16_000_000;

/// Render the shaded surface into a `width`×`height` picture; just the background when
/// there is nothing to draw (empty mask, no triangles).
pub fn preview(rec: &Reconstruction, width: u32, height: u32) -> RgbImage {
    let opts = MeshOptions {
        max_vertices: MAX_VERTICES,
        step: None,
        height_scale: 1.0,
        pixel_size: None,
        normals: MeshNormals::Photometric,
    };
    let background = Rgb(BACKGROUND);
    let mesh = match mesh::triangulate_with(rec, &opts, rec.camera()) {
        Ok(m) if width > 0 && height > 0 => m,
        _ => return RgbImage::from_pixel(width, height, background),
    };
    let ss = if u64::from(width) * u64::from(height) * 4 <= MAX_SUPERSAMPLED {
        2
    } else {
        1
    };
    let (w, h) = ((width * ss) as usize, (height * ss) as usize);

    // Camera basis: `back` points from the scene to the camera, `right` stays level.
    let (el, az) = (ELEVATION_DEG.to_radians(), AZIMUTH_DEG.to_radians());
    let back = [az.sin() * el.cos(), -az.cos() * el.cos(), el.sin()];
    let right = unit([-back[1], back[0], 0.0]);
    let up = cross(back, right);
    let light = unit([
        back[0] + 0.6 * up[0] - 0.4 * right[0],
        back[1] + 0.6 * up[1] - 0.4 * right[1],
        back[2] + 0.6 * up[2] - 0.4 * right[2],
    ]);

    // Project, then fit the projected bounding box into the frame (y grows downwards).
    let view: Vec<[f64; 3]> = (mesh.positions.iter())
        .map(|p| {
            let p = p.map(f64::from);
            [dot(p, right), dot(p, up), dot(p, back)]
        })
        .collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for v in &view {
        for k in 0..2 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let span = |k: usize| (hi[k] - lo[k]).max(f64::EPSILON);
    let scale = ((w as f64 * (1.0 - 2.0 * MARGIN)) / span(0))
        .min((h as f64 * (1.0 - 2.0 * MARGIN)) / span(1));
    let screen: Vec<[f64; 3]> = (view.iter())
        .map(|v| {
            [
                w as f64 / 2.0 + (v[0] - (lo[0] + hi[0]) / 2.0) * scale,
                h as f64 / 2.0 - (v[1] - (lo[1] + hi[1]) / 2.0) * scale,
                v[2],
            ]
        })
        .collect();
    let albedo: Vec<[f32; 3]> = (mesh.pixels.iter())
        .map(|&[r, c]| {
            let (r, c) = (r as usize, c as usize);
            let a = match &rec.albedo_rgb {
                Some(rgb) => [rgb[[r, c, 0]], rgb[[r, c, 1]], rgb[[r, c, 2]]],
                None => [rec.albedo[[r, c]]; 3],
            };
            a.map(|v| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) })
        })
        .collect();

    // Bands of rows are drawn in parallel, each from the triangles whose bounding box
    // reaches it, in mesh order (so ties in depth resolve as in a serial pass).
    let band = BAND_ROWS.min(h.max(1));
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); h.div_ceil(band)];
    let mut boxes = Vec::with_capacity(mesh.triangles.len());
    for (k, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|i| screen[i as usize]);
        let x0 = a[0].min(b[0]).min(c[0]).floor().max(0.0) as usize;
        let y0 = a[1].min(b[1]).min(c[1]).floor().max(0.0) as usize;
        let x1 = (a[0].max(b[0]).max(c[0]).ceil() as usize).min(w);
        let y1 = (a[1].max(b[1]).max(c[1]).ceil() as usize).min(h);
        boxes.push([x0, y0, x1, y1]);
        if y0 < y1 && x0 < x1 {
            for bin in &mut bins[y0 / band..y1.div_ceil(band)] {
                bin.push(k as u32);
            }
        }
    }
    // Visibility first (depth, and which triangle at which barycentrics), shading after:
    // a sample hidden by later, nearer triangles is never shaded.
    let mut depth = vec![f64::NEG_INFINITY; w * h];
    let mut hit = vec![Hit::NONE; w * h];
    depth
        .par_chunks_mut(band * w)
        .zip(hit.par_chunks_mut(band * w))
        .zip(bins.par_iter())
        .enumerate()
        .for_each(|(bi, ((depth, hit), bin))| {
            let first = bi * band;
            for &k in bin {
                let t = mesh.triangles[k as usize];
                let [a, b, c] = t.map(|i| screen[i as usize]);
                let area = edge(a, b, c);
                if area.abs() < 1e-12 {
                    continue;
                }
                let [x0, y0, x1, y1] = boxes[k as usize];
                for y in y0.max(first)..y1.min(first + band) {
                    for x in x0..x1 {
                        let p = [x as f64 + 0.5, y as f64 + 0.5, 0.0];
                        let (wa, wb) = (edge(b, c, p) / area, edge(c, a, p) / area);
                        let wc = 1.0 - wa - wb;
                        // Inclusive edges: shared edges never leave cracks (overdraw is
                        // harmless).
                        if wa < -1e-9 || wb < -1e-9 || wc < -1e-9 {
                            continue;
                        }
                        let z = wa * a[2] + wb * b[2] + wc * c[2];
                        let i = (y - first) * w + x;
                        if z <= depth[i] {
                            continue;
                        }
                        depth[i] = z;
                        hit[i] = Hit {
                            triangle: k,
                            wa: wa as f32,
                            wb: wb as f32,
                        };
                    }
                }
            }
        });
    drop(depth);
    let shade = |i: usize| -> [f32; 3] {
        let Hit { triangle, wa, wb } = hit[i];
        if triangle == Hit::NONE.triangle {
            return BACKGROUND.map(|v| f32::from(v) / 255.0);
        }
        let (wa, wb) = (f64::from(wa), f64::from(wb));
        let t = mesh.triangles[triangle as usize];
        let wc = 1.0 - wa - wb;
        let mix = |f: &dyn Fn(usize) -> [f32; 3]| {
            let [fa, fb, fc] = t.map(|v| f(v as usize));
            [0, 1, 2].map(|k| {
                (wa * f64::from(fa[k]) + wb * f64::from(fb[k]) + wc * f64::from(fc[k])) as f32
            })
        };
        let n = unit(mix(&|v| mesh.normals[v]).map(f64::from));
        let lit = AMBIENT + (1.0 - AMBIENT) * dot(n, light).max(0.0) as f32;
        mix(&|v| albedo[v]).map(|a| a * lit)
    };

    // Shade and box-filter the supersamples down to the output size, rows in parallel.
    let mut out = vec![0u8; width as usize * height as usize * 3];
    out.par_chunks_mut(width as usize * 3)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(3).enumerate() {
                let mut sum = [0.0f32; 3];
                for dy in 0..ss as usize {
                    for dx in 0..ss as usize {
                        let c = shade((y * ss as usize + dy) * w + x * ss as usize + dx);
                        (0..3).for_each(|k| sum[k] += c[k]);
                    }
                }
                px.copy_from_slice(&sum.map(|v| to_u8(v / (ss * ss) as f32)));
            }
        });
    RgbImage::from_raw(width, height, out).expect("3 bytes per pixel")
}

/// The nearest triangle at a supersample and the sample's barycentric weights in it
/// (f32: 12 bytes a sample, as little as the colour buffer it replaces; the weights only
/// blend colours that end up as 8 bits).
#[derive(Clone, Copy)]
struct Hit {
    triangle: u32,
    wa: f32,
    wb: f32,
}

impl Hit {
    const NONE: Hit = Hit {
        triangle: u32::MAX,
        wa: 0.0,
        wb: 0.0,
    };
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Twice the signed area of (a, b, p) in screen coordinates.
fn edge(a: [f64; 3], b: [f64; 3], p: [f64; 3]) -> f64 {
    (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let len = dot(v, v).sqrt();
    if len > 0.0 {
        v.map(|x| x / len)
    } else {
        [0.0, 0.0, 1.0]
    }
}
