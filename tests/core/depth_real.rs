//! Depth from real objects' normal maps (../shared/real/normals: DiLiGenT's ground-truth
//! normals, perspective camera `K.txt`, true depth in mm; never in the repository), scored
//! as the field does: the mean absolute depth error after scaling the estimate by
//! median(true / estimated) over the mask (MADE). Skipped with a message on a fresh clone;
//! required under `CI=true`.

use crate::seed;

use std::path::Path;
use std::time::Instant;

use ndarray::Array2;
use photostereo::core::camera::Pinhole;
use photostereo::core::intake::Limits;
use photostereo::core::integrate::{self, perspective};
use photostereo::core::metrics::{self, Align};
use photostereo::core::normalmap::{self, Convention, Lens};
use photostereo::core::options::Integration;
use photostereo::core::progress::NEVER;

/// A little-endian float32 `.npy` array of two dimensions, in C or Fortran order.
fn read_npy_f32(path: &Path) -> Array2<f32> {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..6], b"\x93NUMPY", "{} is not .npy", path.display());
    let (len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
    };
    let header = std::str::from_utf8(&bytes[start..start + len]).unwrap();
    assert!(
        header.contains("'<f4'"),
        "{} is not float32",
        path.display()
    );
    let fortran = header.contains("'fortran_order': True");
    let shape = header.split("'shape': (").nth(1).unwrap();
    let shape: Vec<usize> = shape
        .split(')')
        .next()
        .unwrap()
        .split(',')
        .filter_map(|t| t.trim().parse().ok())
        .collect();
    let data: Vec<f32> = bytes[start + len..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if fortran {
        Array2::from_shape_vec((shape[1], shape[0]), data)
            .unwrap()
            .reversed_axes()
    } else {
        Array2::from_shape_vec((shape[0], shape[1]), data).unwrap()
    }
}

fn score(name: &str, method: Integration) -> Option<(f64, f64)> {
    let dir = seed::real_or_skip(&format!("normals/diligent-{name}"))?;
    let camera = Pinhole::read(&dir.join("K.txt")).unwrap();
    // Read as `photostereo integrate <map> --mask … --camera K.txt` reads it: 16-bit, the
    // benchmark convention (x right, y up, z towards the camera), renormalised.
    let map = normalmap::read(
        &dir.join("normal_map.png"),
        Some(&dir.join("mask.png")),
        Convention::Opengl,
        Some(Lens::Pinhole(camera)),
        &Limits::default(),
    )
    .unwrap();
    let (normals, mask) = (map.normals, map.mask);
    let truth = read_npy_f32(&dir.join("depth_gt.npy"));
    let t = Instant::now();
    let given = Default::default();
    let surface =
        integrate::integrate_log_depth(&normals, &mask, &camera, method, None, given, NEVER);
    let zeta = surface.zeta;
    let depth = perspective::depth_from_log(&zeta, &mask, &camera, None);
    let secs = t.elapsed().as_secs_f64();
    let made = metrics::depth_error(&depth, &truth, &mask, Align::Scale).mean_abs;
    Some((made, secs))
}

/// BiNI's MADE on each object with its published code (k = 2, perspective), mm: the
/// field's reference, and issue 42's target for the default integration.
const BINI: [(&str, f64); 3] = [("cat", 0.074), ("pot2", 0.220), ("harvest", 1.839)];
/// Perspective depth from the three objects' true normals: `bilateral` at or below BiNI on
/// each; the table (with Poisson and robust Poisson) is printed.
#[test]
fn bilateral_depth_is_as_good_as_bini_on_real_objects() {
    for (name, bini) in BINI {
        let mut row = format!("{name:8} BiNI {bini:.3}");
        for method in [
            Integration::Poisson,
            Integration::RobustPoisson,
            Integration::Bilateral,
        ] {
            let Some((e, s)) = score(name, method) else {
                return;
            };
            row += &format!(" | {method:?}: {e:.4} mm, {s:.2} s");
            if method == Integration::Bilateral {
                assert!(
                    e <= bini,
                    "{name}: bilateral MADE {e:.4} mm, BiNI {bini} mm"
                );
            }
        }
        println!("{row}");
    }
}
