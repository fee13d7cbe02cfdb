//! Normal maps from the fits: `g = ρ n` split into normals and albedo, and how far one
//! map's normals moved from another's.

use ndarray::{Array2, Array3, Axis, Zip};

/// Unit normals and albedo from `g`, zero off the mask and where `g` is zero.
pub fn split(g: &Array3<f32>, mask: &Array2<bool>) -> (Array3<f32>, Array2<f32>) {
    let mut normals = Array3::<f32>::zeros(g.dim());
    let mut albedo = Array2::<f32>::zeros(mask.dim());
    Zip::from(normals.lanes_mut(Axis(2)))
        .and(&mut albedo)
        .and(g.lanes(Axis(2)))
        .and(mask)
        .for_each(|mut n, a, g, &m| {
            let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
            if m && len > 0.0 {
                *a = len;
                for k in 0..3 {
                    n[k] = g[k] / len;
                }
            }
        });
    (normals, albedo)
}

/// Mean and 95th-percentile angle (degrees) between two normal maps over the mask.
pub fn changes(a: &Array3<f32>, b: &Array3<f32>, mask: &Array2<bool>) -> (f64, f64) {
    let mut angles: Vec<f64> = Vec::new();
    Zip::from(a.lanes(Axis(2)))
        .and(b.lanes(Axis(2)))
        .and(mask)
        .for_each(|a, b, &m| {
            if m {
                let d = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0);
                angles.push(f64::from(d).acos().to_degrees());
            }
        });
    if angles.is_empty() {
        return (0.0, 0.0);
    }
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    let k = (angles.len() * 95 / 100).min(angles.len() - 1);
    let p95 = *angles.select_nth_unstable_by(k, f64::total_cmp).1;
    (mean, p95)
}
