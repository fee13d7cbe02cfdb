//! Pictures drawn from a reconstruction: shading under a light, the needle (quiver) map
//! and a diverging colour map. Pure functions over arrays; encoding lives in `outputs`.

use image::{Rgb, RgbImage};
use ndarray::{Array2, Array3, ArrayView1, ArrayViewMut3, Axis, Zip};

/// A distant light (any length, not zero), normalised once for [`Shading::at`].
pub struct Shading([f32; 3]);

impl Shading {
    pub fn new(light: [f64; 3]) -> Self {
        let len = light.iter().map(|v| v * v).sum::<f64>().sqrt();
        Self(light.map(|v| (v / len) as f32))
    }

    /// albedo · max(0, n·l̂): a pixel re-lit by this light.
    #[inline]
    pub fn at(&self, albedo: f32, n: ArrayView1<f32>) -> f32 {
        let l = &self.0;
        albedo * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0)
    }
}

/// The seed's quiver plot as a picture: the albedo in gray, with a needle every few
/// pixels from each sample along the normal's image-plane direction (x right, y down).
pub fn needle_map(albedo: &Array2<f32>, normals: &Array3<f32>, mask: &Array2<bool>) -> RgbImage {
    let (rows, cols) = albedo.dim();
    let mut img = rgb_from(albedo, mask, |a, _| [(a.clamp(0.0, 1.0) * 160.0) as u8; 3]);
    let spacing = (rows.max(cols) / 40).max(4);
    let length = spacing as f32 * 1.6;
    for r in (spacing / 2..rows).step_by(spacing) {
        for c in (spacing / 2..cols).step_by(spacing) {
            if !mask[[r, c]] {
                continue;
            }
            let (nx, ny) = (normals[[r, c, 0]], normals[[r, c, 1]]);
            let (x0, y0) = (c as f32, r as f32);
            let (x1, y1) = (x0 + nx * length, y0 + ny * length);
            draw_line(&mut img, (x0, y0), (x1, y1), Rgb([255, 200, 0]));
            put(&mut img, x0 as i64, y0 as i64, Rgb([0, 120, 255]));
        }
    }
    img
}

fn put(img: &mut RgbImage, x: i64, y: i64, colour: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, colour);
    }
}

/// A DDA line; the pictures are small and lines short, so no anti-aliasing.
fn draw_line(img: &mut RgbImage, (x0, y0): (f32, f32), (x1, y1): (f32, f32), colour: Rgb<u8>) {
    let steps = (x1 - x0).abs().max((y1 - y0).abs()).ceil().max(1.0) as usize;
    for i in 0..=steps {
        let t = i as f32 / steps as f32;
        put(
            img,
            (x0 + t * (x1 - x0)).round() as i64,
            (y0 + t * (y1 - y0)).round() as i64,
            colour,
        );
    }
}

/// A blue–white–red map of a signed field, symmetric about 0, saturating at the 99th
/// percentile of |value| over the mask; background black.
pub fn diverging(values: &Array2<f32>, mask: &Array2<bool>) -> RgbImage {
    let mut mags: Vec<f32> = values
        .iter()
        .zip(mask.iter())
        .filter(|(_, m)| **m)
        .map(|(v, _)| v.abs())
        .collect();
    let scale = if mags.is_empty() {
        1.0
    } else {
        let k = ((mags.len() - 1) as f64 * 0.99) as usize;
        let (_, p, _) = mags.select_nth_unstable_by(k, f32::total_cmp);
        if *p > 0.0 { *p } else { 1.0 }
    };
    rgb_from(values, mask, |v, m| {
        let t = (v / scale).clamp(-1.0, 1.0);
        let fade = |k: f32| (255.0 * (1.0 - k)) as u8;
        match (m, t >= 0.0) {
            (false, _) => [0, 0, 0],
            (true, true) => [255, fade(t), fade(t)],
            (true, false) => [fade(-t), fade(-t), 255],
        }
    })
}

/// An 8-bit RGB picture of `colour(value, inside the mask)` per pixel, rows in parallel.
fn rgb_from(
    values: &Array2<f32>,
    mask: &Array2<bool>,
    colour: impl Fn(f32, bool) -> [u8; 3] + Sync,
) -> RgbImage {
    let (rows, cols) = values.dim();
    let mut raw = vec![0u8; rows * cols * 3];
    let mut pixels =
        ArrayViewMut3::from_shape((rows, cols, 3), &mut raw).expect("3 bytes per pixel");
    Zip::from(pixels.lanes_mut(Axis(2)))
        .and(values)
        .and(mask)
        .par_for_each(|mut p, &v, &m| {
            let [r, g, b] = colour(v, m);
            (p[0], p[1], p[2]) = (r, g, b);
        });
    RgbImage::from_raw(cols as u32, rows as u32, raw).expect("3 bytes per pixel")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shading_follows_lambert_and_clamps_shadows() {
        let shading = Shading::new([1.0, 0.0, 1.0]);
        let (up, away) = (
            ndarray::arr1(&[0.0, 0.0, 1.0]),
            ndarray::arr1(&[-1.0, 0.0, 0.0]),
        );
        assert!((shading.at(0.5, up.view()) - 0.5 / 2f32.sqrt()).abs() < 1e-6);
        assert_eq!(shading.at(0.5, away.view()), 0.0);
    }

    #[test]
    fn diverging_map_is_symmetric() {
        let v = Array2::from_shape_vec((1, 3), vec![-1.0, 0.0, 1.0]).unwrap();
        let m = Array2::from_elem((1, 3), true);
        let img = diverging(&v, &m);
        assert_eq!(img.get_pixel(0, 0).0, [0, 0, 255]);
        assert_eq!(img.get_pixel(1, 0).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(2, 0).0, [255, 0, 0]);
    }
}
