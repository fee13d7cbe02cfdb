//! The mesh's base-colour texture: the albedo as a PNG, scaled to fit the largest texture
//! side, its background texels filled with nearby object colours so that filtering and
//! mipmaps do not bleed black into the object's edge.

use fast_image_resize as fir;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};
use ndarray::{Array2, ArrayView2, Axis};
use rayon::prelude::*;

use super::error::MeshError;
use crate::core::reconstruction::Reconstruction;

/// Largest texture side; larger albedo maps are downscaled (many GPUs stop at 4096).
const MAX_TEXTURE_SIDE: usize = 4096;
/// Rings of background texels filled with nearby object colours, so texture filtering and
/// mipmaps do not bleed black into the object's edge.
const FILL_RINGS: usize = 4;

/// The albedo as an 8-bit PNG: gray, or RGB when colour albedo exists, no side over
/// [`MAX_TEXTURE_SIDE`]. Values are written as stored, like `albedo.png` (intake does not
/// linearise its inputs).
pub(super) fn albedo_png(rec: &Reconstruction) -> Result<Vec<u8>, MeshError> {
    let planes: Vec<ArrayView2<f32>> = match &rec.albedo_rgb {
        Some(rgb) => rgb.axis_iter(Axis(2)).collect(),
        None => vec![rec.albedo.view()],
    };
    let (pixel, color) = if planes.len() == 1 {
        (fir::PixelType::U8, ExtendedColorType::L8)
    } else {
        (fir::PixelType::U8x3, ExtendedColorType::Rgb8)
    };
    let (h, w) = rec.mask.dim();
    let texels = texels(&planes, &rec.mask);
    let (texels, w, h) = fit_texture(texels, w as u32, h as u32, pixel, MAX_TEXTURE_SIDE)?;
    let mut out = Vec::new();
    // Fast settings, as for every PNG the service writes (see `outputs::png_to`).
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Up)
        .write_image(&texels, w, h, color)
        .map_err(|e| MeshError::Texture(e.to_string()))?;
    Ok(out)
}

/// `texels` (`w`×`h` pixels of type `pixel`) scaled down, when a side exceeds `max_side`,
/// to fit it: a tent filter whose support widens with the factor, in SIMD
/// (`fast_image_resize`). `image`'s generic resize took 2.4 s of a 5120² job's 7.7 s.
fn fit_texture(
    texels: Vec<u8>,
    w: u32,
    h: u32,
    pixel: fir::PixelType,
    max_side: usize,
) -> Result<(Vec<u8>, u32, u32), MeshError> {
    let side = w.max(h) as usize;
    if side <= max_side {
        return Ok((texels, w, h));
    }
    let f = max_side as f64 / side as f64;
    let scaled = |n: u32| ((f64::from(n) * f).round() as u32).clamp(1, max_side as u32);
    let failed = |e: &dyn std::fmt::Display| MeshError::Texture(format!("scaling: {e}"));
    let src = fir::images::Image::from_vec_u8(w, h, texels, pixel).map_err(|e| failed(&e))?;
    let mut dst = fir::images::Image::new(scaled(w), scaled(h), pixel);
    let tent = fir::ResizeOptions::new()
        .resize_alg(fir::ResizeAlg::Convolution(fir::FilterType::Bilinear));
    fir::Resizer::new()
        .resize(&src, &mut dst, &tent)
        .map_err(|e| failed(&e))?;
    let (w, h) = (dst.width(), dst.height());
    Ok((dst.into_vec(), w, h))
}

/// Interleaved 8-bit texels of `planes` (one channel each), the background filled by
/// [`fill_background`]. Rows are converted in parallel; the texture is made on every job
/// with a mesh, and at 2048² a per-pixel sequential pass was most of the mesh's time.
fn texels(planes: &[ArrayView2<f32>], mask: &Array2<bool>) -> Vec<u8> {
    let (h, w) = mask.dim();
    let n = planes.len();
    let mut out = vec![0u8; h * w * n];
    if out.is_empty() {
        return out;
    }
    // Rounds to nearest; NaN saturates to 0.
    let texel = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    out.par_chunks_mut(w * n).enumerate().for_each(|(r, row)| {
        for (k, plane) in planes.iter().enumerate() {
            let src = plane.row(r);
            match src.as_slice() {
                // Gray albedo: contiguous in and out, a loop that vectorises.
                Some(src) if n == 1 => row.iter_mut().zip(src).for_each(|(t, &v)| *t = texel(v)),
                _ => (row.iter_mut().skip(k).step_by(n).zip(src)).for_each(|(t, &v)| *t = texel(v)),
            }
        }
    });
    let mask = crate::core::arrays::contiguous(mask.view());
    fill_background(&mut out, n, &mask, w);
    out
}

/// Background pixels with a 4-neighbour on the mask, in index order: row by row in
/// parallel, from whole rows (a per-pixel neighbour search cost 4 % of a 2048² job).
fn outline(mask: &[bool], w: usize) -> Vec<usize> {
    let h = mask.len() / w;
    let row = |r: usize| &mask[r * w..(r + 1) * w];
    let none = vec![false; w];
    (0..h)
        .into_par_iter()
        .flat_map_iter(|r| {
            let (up, cur) = (if r > 0 { row(r - 1) } else { &none }, row(r));
            let down = if r + 1 < h { row(r + 1) } else { &none };
            (0..w).filter_map(move |c| {
                let side = (c > 0 && cur[c - 1]) || (c + 1 < w && cur[c + 1]);
                (!cur[c] && (up[c] || down[c] || side)).then_some(r * w + c)
            })
        })
        .collect()
}

/// Give background texels near the mask the mean of their already-filled 4-neighbours,
/// ring by ring, and the rest the mask's mean colour: filtering and mipmaps then blend
/// the object's edge with its own colours, not black. Each ring is found from the last
/// one's neighbours, so the cost follows the mask's outline, not the frame. `texels` holds
/// `n` interleaved channels per pixel of a `mask.len() / w`-row grid.
fn fill_background(texels: &mut [u8], n: usize, mask: &[bool], w: usize) {
    let h = mask.len() / w;
    let neighbours = |i: usize| {
        let (r, c) = (i / w, i % w);
        [
            (r > 0).then(|| i - w),
            (r + 1 < h).then(|| i + w),
            (c > 0).then(|| i - 1),
            (c + 1 < w).then(|| i + 1),
        ]
        .into_iter()
        .flatten()
    };
    // The mask's mean colour, from exact integer sums (the last entry counts pixels).
    let sums = (texels.par_chunks(w * n).zip(mask.par_chunks(w)))
        .map(|(texels, mask)| {
            let mut sums = vec![0u64; n + 1];
            if n == 1 {
                // Branch-free, so it vectorises (gray textures are the common case).
                for (&v, &m) in texels.iter().zip(mask) {
                    sums[0] += u64::from(v) * u64::from(m);
                    sums[1] += u64::from(m);
                }
                return sums;
            }
            for (px, _) in texels.chunks_exact(n).zip(mask).filter(|(_, m)| **m) {
                sums.iter_mut()
                    .zip(px)
                    .for_each(|(s, &v)| *s += u64::from(v));
                sums[n] += 1;
            }
            sums
        })
        .reduce(
            || vec![0u64; n + 1],
            |a, b| a.iter().zip(&b).map(|(a, b)| a + b).collect(),
        );
    let count = sums[n].max(1);
    let mean: Vec<u8> = (sums[..n].iter())
        .map(|&s| ((s + count / 2) / count) as u8)
        .collect();

    let mut known = mask.to_vec();
    let mut ring = outline(mask, w);
    let mut fills: Vec<u8> = Vec::new();
    for depth in 0..FILL_RINGS {
        if ring.is_empty() {
            break;
        }
        // Values first (from pixels known before this ring), then mark the ring known.
        fills.clear();
        for &i in &ring {
            for k in 0..n {
                let (mut sum, mut m) = (0u32, 0u32);
                for j in neighbours(i).filter(|&j| known[j]) {
                    sum += u32::from(texels[j * n + k]);
                    m += 1;
                }
                fills.push(((sum + m / 2) / m) as u8);
            }
        }
        for (f, &i) in fills.chunks(n).zip(&ring) {
            texels[i * n..(i + 1) * n].copy_from_slice(f);
            known[i] = true;
        }
        if depth + 1 < FILL_RINGS {
            let mut next: Vec<usize> = (ring.iter())
                .flat_map(|&i| neighbours(i))
                .filter(|&j| !known[j])
                .collect();
            next.sort_unstable();
            next.dedup();
            ring = next;
        }
    }
    (texels.par_chunks_mut(w * n).zip(known.par_chunks(w))).for_each(|(texels, known)| {
        if n == 1 {
            for (t, &k) in texels.iter_mut().zip(known) {
                *t = if k { *t } else { mean[0] };
            }
            return;
        }
        for (px, _) in texels.chunks_exact_mut(n).zip(known).filter(|(_, k)| !**k) {
            px.copy_from_slice(&mean);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outline_is_every_background_pixel_next_to_the_mask() {
        let (h, w) = (23, 31);
        let mask: Vec<bool> = (0..h * w).map(|i| (i * 7919 % 13) < 4).collect();
        let on = |r: isize, c: isize| {
            (0..h as isize).contains(&r)
                && (0..w as isize).contains(&c)
                && mask[r as usize * w + c as usize]
        };
        let naive: Vec<usize> = (0..h * w)
            .filter(|&i| {
                let (r, c) = ((i / w) as isize, (i % w) as isize);
                !mask[i] && (on(r - 1, c) || on(r + 1, c) || on(r, c - 1) || on(r, c + 1))
            })
            .collect();
        assert!(!naive.is_empty());
        assert_eq!(outline(&mask, w), naive);
    }

    #[test]
    fn texture_keeps_the_object_and_pads_its_outline_with_its_own_colours() {
        // A 3×3 object in a 16×16 frame: left column 0.2, the rest 1.0 (RGB: the green
        // channel is inverted).
        let (h, w) = (16, 16);
        let mask =
            Array2::from_shape_fn((h, w), |(r, c)| (5..8).contains(&r) && (5..8).contains(&c));
        let value = |c: usize| if c == 5 { 0.2 } else { 1.0 };
        let gray =
            Array2::from_shape_fn((h, w), |(r, c)| if mask[[r, c]] { value(c) } else { 0.0 });
        let inverted = gray.mapv(|v| 1.0 - v);
        let q = |v: f32| (v * 255.0).round() as u8;
        for planes in [
            vec![gray.view()],
            vec![gray.view(), inverted.view(), gray.view()],
        ] {
            let n = planes.len();
            let t = texels(&planes, &mask);
            let at = |r: usize, c: usize, k: usize| t[(r * w + c) * n + k];
            let want = |v: f32, k: usize| if k == 1 { q(1.0 - v) } else { q(v) };
            for k in 0..n {
                for ((r, c), &m) in mask.indexed_iter() {
                    if m {
                        assert_eq!(at(r, c, k), want(value(c), k), "object ({r}, {c})");
                    }
                }
                // Ring 1, left of the object: its one known neighbour.
                assert_eq!(at(6, 4, k), want(0.2, k));
                // Ring 2, diagonal to the corner: the mean of its two ring-1 neighbours.
                let corner = (u32::from(at(4, 5, k)) + u32::from(at(5, 4, k))).div_ceil(2) as u8;
                assert_eq!(at(4, 4, k), corner);
                // Beyond the rings: the object's mean colour.
                let mean = (0.2 + 2.0 * 1.0) / 3.0;
                let mean_q =
                    ((3 * u32::from(want(0.2, k)) + 6 * u32::from(want(1.0, k)) + 4) / 9) as u8;
                assert!(want(mean, k).abs_diff(mean_q) <= 1);
                assert_eq!(at(0, 15, k), mean_q, "far corner");
            }
        }
    }

    #[test]
    fn oversized_textures_are_scaled_to_fit_keeping_their_colours() {
        // 30×12 RGB, left half dark red, right half light blue, one bright column at 15.
        let (w, h) = (30u32, 12u32);
        let colour = |c: u32| match c {
            15 => [255, 255, 255],
            c if c < 15 => [120, 10, 10],
            _ => [20, 40, 200],
        };
        let texels: Vec<u8> = (0..w * h).flat_map(|i| colour(i % w)).collect();
        let fits = fit_texture(texels.clone(), w, h, fir::PixelType::U8x3, 30).unwrap();
        assert_eq!(
            fits,
            (texels.clone(), w, h),
            "a texture that fits is kept as is"
        );

        let (t, sw, sh) = fit_texture(texels, w, h, fir::PixelType::U8x3, 10).unwrap();
        assert_eq!((sw, sh), (10, 4), "longest side at the limit, aspect kept");
        let at = |r: u32, c: u32| &t[((r * sw + c) * 3) as usize..][..3];
        for r in 0..sh {
            // Far from the edges each side keeps its colour exactly (a filter's weights
            // sum to 1); next to the bright column it is brighter than its side.
            assert_eq!(at(r, 0), &[120, 10, 10]);
            assert_eq!(at(r, 9), &[20, 40, 200]);
            assert!(
                at(r, 4)[1] > 10 && at(r, 5)[0] > 20,
                "the bright column leaves a trace"
            );
        }

        let gray = vec![77u8; 5000 * 3];
        let (t, sw, sh) = fit_texture(gray, 5000, 3, fir::PixelType::U8, 4096).unwrap();
        assert_eq!((sw, sh), (4096, 2));
        assert!(t.iter().all(|&v| v == 77));
    }
}
