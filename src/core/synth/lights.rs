//! Light layouts for the rendered sets: rings around the view axis, a benchmark-style
//! grid, and per-light RGB intensities.

use super::sensor;

/// Lights in rings around the view axis: `count` directions with polar angles spread
/// evenly up to `max_polar_deg` and azimuths on a golden-angle spiral.
pub fn light_rings(count: usize, min_polar_deg: f64, max_polar_deg: f64) -> Vec<[f64; 3]> {
    (0..count)
        .map(|i| {
            let t = if count > 1 {
                i as f64 / (count - 1) as f64
            } else {
                0.0
            };
            let polar = (min_polar_deg + t * (max_polar_deg - min_polar_deg)).to_radians();
            let azimuth = i as f64 * 2.399963229728653;
            [
                polar.sin() * azimuth.cos(),
                polar.sin() * azimuth.sin(),
                polar.cos(),
            ]
        })
        .collect()
}

/// A benchmark-style dome: `cols` × `rows` lights on a regular grid in a plane facing
/// the object, the corner lights `max_polar_deg` from the view axis.
pub fn light_grid(cols: usize, rows: usize, max_polar_deg: f64) -> Vec<[f64; 3]> {
    let (hc, hr) = (0.5 * (cols - 1) as f64, 0.5 * (rows - 1) as f64);
    let spacing = max_polar_deg.to_radians().tan() / (hc * hc + hr * hr).sqrt();
    (0..rows)
        .flat_map(|j| (0..cols).map(move |i| (i, j)))
        .map(|(i, j)| {
            let (x, y) = ((i as f64 - hc) * spacing, (j as f64 - hr) * spacing);
            let len = (x * x + y * y + 1.0).sqrt();
            [x / len, y / len, 1.0 / len]
        })
        .collect()
}

/// Per-light RGB intensities like a rig of measured LEDs: each channel of each light
/// drawn uniformly from `low..high`, reproducibly from `seed`.
pub fn light_colours(count: usize, low: f64, high: f64, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = sensor::Rng::new(seed);
    (0..count)
        .map(|_| [0; 3].map(|_| low + (high - low) * rng.uniform()))
        .collect()
}
