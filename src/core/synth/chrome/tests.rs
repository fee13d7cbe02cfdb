use std::path::{Path, PathBuf};

use ndarray::Array2;

use super::set::{ChromeSet, matte_intensities};
use super::write::TRUTH;
use crate::core::vec3::{dot, normalise};

fn fnv(h: u64, bytes: impl IntoIterator<Item = u8>) -> u64 {
    bytes
        .into_iter()
        .fold(h, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3))
}

const FNV: u64 = 0xcbf2_9ce4_8422_2325;

fn checksum(images: &[Array2<u16>]) -> u64 {
    images
        .iter()
        .flat_map(|img| img.iter())
        .fold(FNV, |h, v| fnv(h, v.to_le_bytes()))
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(files(&p));
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn existing_sets_are_unchanged() {
    // Checksums taken before room lights, near lights and extra balls were added.
    assert_eq!(
        checksum(&ChromeSet::standard(8, 41).render()),
        0x0666_7a22_c592_2e93
    );
    assert_eq!(
        checksum(&ChromeSet::filling(16, 47).render()),
        0x2824_2c9e_5853_5acb
    );
    // Every file written then, bytes and names (`circles.txt` is new).
    let set = ChromeSet::standard(8, 41);
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), Some(&matte_intensities(set.lights.len(), 5)))
        .unwrap();
    let written = files(dir.path())
        .into_iter()
        .filter(|f| !f.ends_with("circles.txt"))
        .fold(FNV, |h, f| fnv(h, std::fs::read(f).unwrap()));
    assert_eq!(written, 0x21de_2d66_de69_46c3);
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    dot(normalise(a), normalise(b))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The surface point of ball (c, r) at image point (x, y) and the direction it mirrors.
fn mirror(c: [f64; 2], r: f64, x: f64, y: f64) -> ([f64; 3], [f64; 3]) {
    let (u, v) = ((x - c[0]) / r, (y - c[1]) / r);
    let w = (1.0 - u * u - v * v).sqrt();
    ([x, y, r * w], [2.0 * w * u, 2.0 * w * v, 2.0 * w * w - 1.0])
}

/// Each image of `set` less the same image with the light turned off: the light's
/// highlight alone, the room and the noise cancelling (the same noise draws).
fn highlights(set: &ChromeSet) -> Vec<Array2<f64>> {
    let dark = ChromeSet {
        highlight: vec![0.0; set.highlight.len()],
        ..set.clone()
    };
    set.render()
        .iter()
        .zip(dark.render())
        .map(|(lit, dark)| (lit.mapv(f64::from) - dark.mapv(f64::from)).mapv(|v| v.max(0.0)))
        .collect()
}

/// The weighted centre of the brightest spot of `img` on ball (c, r), within 5 px.
fn spot(img: &Array2<f64>, c: [f64; 2], r: f64) -> [f64; 2] {
    let on = |(row, col): (usize, usize)| (col as f64 - c[0]).hypot(row as f64 - c[1]) < r - 1.5;
    let (peak, _) = img
        .indexed_iter()
        .filter(|&(i, _)| on(i))
        .max_by(|a, b| a.1.total_cmp(b.1))
        .unwrap();
    let (mut sum, mut x, mut y) = (0.0, 0.0, 0.0);
    for ((row, col), &v) in img.indexed_iter() {
        if row.abs_diff(peak.0) <= 5 && col.abs_diff(peak.1) <= 5 && on((row, col)) {
            (sum, x, y) = (sum + v, x + v * col as f64, y + v * row as f64);
        }
    }
    [x / sum, y / sum]
}

#[test]
fn near_light_highlights_obey_the_reflection_law_on_each_ball() {
    let mut set = ChromeSet::near_dome(16, 5, 2.0);
    let picked = [0, 5, 10, 15];
    let positions = set.light_positions.clone().unwrap();
    set.light_positions = Some(picked.iter().map(|&i| positions[i]).collect());
    set.lights = picked.iter().map(|&i| set.lights[i]).collect();
    set.highlight = vec![0.9; picked.len()];
    (set.noise_sigma, set.distractors) = (0.0, false);
    let images = highlights(&set);
    let (balls, seen_from) = (set.balls(), [set.truth_from(0), set.truth_from(1)]);
    let mut worst: f64 = 0.0;
    for (i, (img, q)) in images
        .iter()
        .zip(set.light_positions.as_ref().unwrap())
        .enumerate()
    {
        for &(c, r) in &balls {
            let [x, y] = spot(img, c, r);
            let (p, d) = mirror(c, r, x, y);
            let to = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            worst = worst.max(angle_deg(d, to));
        }
        // Near lights: the two balls see each light from clearly different directions.
        let parallax = angle_deg(seen_from[0][i].0, seen_from[1][i].0);
        assert!(parallax > 10.0, "light {i}: {parallax}°");
    }
    eprintln!(
        "near lights: mirror direction at the highlight off the light by {worst:.3}° at most"
    );
    assert!(worst < 0.3, "{worst}°");
}

#[test]
fn near_dome_lights_are_hidden_from_neither_ball() {
    for distance in [1.0, 2.0, 5.0, 20.0] {
        let set = ChromeSet::near_dome(8, 1, distance);
        let balls = set.balls();
        for q in set.light_positions.as_ref().unwrap() {
            for (a, &(c, r)) in balls.iter().enumerate() {
                // The highlight: where the normal halves the way to the light and the view.
                let mut n = [0.0, 0.0, 1.0];
                for _ in 0..50 {
                    let p = [c[0] + r * n[0], c[1] + r * n[1], r * n[2]];
                    let l = normalise([q[0] - p[0], q[1] - p[1], q[2] - p[2]]);
                    n = normalise([l[0], l[1], l[2] + 1.0]);
                }
                let p = [c[0] + r * n[0], c[1] + r * n[1], r * n[2]];
                let (o, s) = balls[1 - a];
                let seg = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                let to = [o[0] - p[0], o[1] - p[1], -p[2]];
                let t = (dot(to, seg) / dot(seg, seg)).clamp(0.0, 1.0);
                let gap = [0, 1, 2].map(|k| to[k] - t * seg[k]);
                let clear = dot(gap, gap).sqrt() - s;
                assert!(
                    clear > 5.0,
                    "{distance} diameters: {q:?} from ball {a}: {clear}"
                );
            }
        }
    }
}

#[test]
fn room_lights_stay_put_in_every_image() {
    let mut set = ChromeSet::real_room(8, 7);
    set.lights.truncate(5);
    set.highlight.truncate(5);
    let images = set.render();
    let at = |direction: [f64; 3]| {
        let d = normalise(direction);
        let n = normalise([d[0], d[1], d[2] + 1.0]);
        let x = set.centre[0] + set.radius * n[0];
        let y = set.centre[1] + set.radius * n[1];
        (y.round() as usize, x.round() as usize)
    };
    let (lamp, window) = (&set.room_lights[0], &set.room_lights[1]);
    // The lamp clips, the same pixels in every image.
    let (row, col) = at(lamp.direction);
    let clipped = |img: &Array2<u16>| -> Vec<(usize, usize)> {
        img.indexed_iter()
            .filter(|&((r, c), &v)| r.abs_diff(row) <= 8 && c.abs_diff(col) <= 8 && v == 255)
            .map(|(i, _)| i)
            .collect()
    };
    let first = clipped(&images[0]);
    assert!(first.contains(&(row, col)) && first.len() >= 4, "{first:?}");
    assert!(images.iter().all(|img| clipped(img) == first));
    // The window: bright, unclipped, the same in every image.
    let (row, col) = at(window.direction);
    for img in &images {
        let v = img[[row, col]];
        assert!((195..=217).contains(&v), "window at {row},{col}: {v}");
    }
}

#[test]
fn a_20_degree_light_fills_its_cone_and_each_light_has_its_radius() {
    let mut set = ChromeSet::standard(16, 9);
    let polar = 50f64.to_radians();
    set.lights = vec![
        [polar.sin(), 0.0, polar.cos()],
        [-polar.sin() * 0.6, polar.sin() * 0.8, polar.cos()],
    ];
    set.highlight = vec![0.9; 2];
    set.light_radius_deg_each = Some(vec![20.0, 5.0]);
    (set.noise_sigma, set.distractors) = (0.0, false);
    let images = set.render();
    let full = (0.9 + set.black_level) * 65535.0;
    let (c, r) = (set.centre, set.radius);
    for (img, (l, radius)) in images.iter().zip(set.lights.iter().zip([20.0, 5.0])) {
        let (mut bright, mut rho) = (0, (f64::MAX, 0f64));
        for ((row, col), &v) in img.indexed_iter() {
            let (x, y) = (col as f64, row as f64);
            let from_centre = (x - c[0]).hypot(y - c[1]);
            if from_centre > r - 2.0 {
                continue;
            }
            let (p, d) = mirror(c, r, x, y);
            // How far a pixel's footprint (half diagonal 0.71 px) turns the mirror direction.
            let margin = (2.0 * 0.71 / p[2]).to_degrees();
            let off = angle_deg(d, *l);
            if off < radius - margin {
                // Shot noise: σ ≈ 0.7 % here.
                assert!((v as f64 - full).abs() < 0.04 * full, "{row},{col}: {v}");
            } else if off > radius + margin {
                assert!((v as f64) < 0.5 * full, "{row},{col}: {v}");
            }
            if v as f64 > 0.5 * full {
                bright += 1;
                rho = (rho.0.min(from_centre), rho.1.max(from_centre));
            }
        }
        eprintln!(
            "{radius}° light: {bright} bright pixels, {:.1}–{:.1} px from the centre",
            rho.0, rho.1
        );
        if radius == 20.0 {
            // Mirror directions 30°–70° off the view axis: normals 15°–35°.
            let (inner, outer) = (r * 15f64.to_radians().sin(), r * 35f64.to_radians().sin());
            assert!(
                (rho.0 - inner).abs() < 1.5 && (rho.1 - outer).abs() < 1.5,
                "{rho:?}"
            );
        } else {
            assert!(bright > 20 && bright < 400, "{bright}");
        }
    }
}

#[test]
fn all_same_light_puts_every_highlight_in_one_place() {
    let set = ChromeSet::all_same_light(8, 4);
    assert_eq!(set.lights.len(), 8);
    assert!(set.lights.iter().all(|&l| l == set.lights[0]));
    let spots: Vec<[f64; 2]> = highlights(&set)
        .iter()
        .map(|img| spot(img, set.centre, set.radius))
        .collect();
    for s in &spots {
        assert!(
            (s[0] - spots[0][0]).hypot(s[1] - spots[0][1]) < 0.5,
            "{spots:?}"
        );
    }
}

#[test]
fn near_sets_write_positions_each_balls_directions_and_circles() {
    let mut set = ChromeSet::near_dome(8, 3, 3.0);
    set.lights.truncate(3);
    set.highlight.truncate(3);
    set.light_positions.as_mut().unwrap().truncate(3);
    let k = [1.0, 1.2, 0.8];
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), Some(&k)).unwrap();
    let truth = dir.path().join(TRUTH);
    let read = |name: &str| std::fs::read_to_string(truth.join(name)).unwrap();
    let rows = |name: &str| -> Vec<Vec<f64>> {
        read(name)
            .lines()
            .map(|l| l.split(", ").skip(1).map(|v| v.parse().unwrap()).collect())
            .collect()
    };
    let circles = read("circles.txt");
    assert_eq!(circles.lines().count(), 2);
    assert_eq!(
        read("circle.txt"),
        circles.lines().next().unwrap().to_owned() + "\n"
    );
    assert_eq!(
        read("light_directions.csv"),
        read("light_directions_ball1.csv")
    );
    let positions = rows("light_positions.csv");
    for (b, (c, _)) in set.balls().into_iter().enumerate() {
        let table = rows(&format!("light_directions_ball{}.csv", b + 1));
        assert_eq!(table.len(), 3);
        for ((row, p), &k) in table.iter().zip(&positions).zip(&k) {
            let to = [p[0] - c[0], p[1] - c[1], p[2]];
            assert!(angle_deg([row[0], row[1], row[2]], to) < 1e-6);
            // The intensity there, by the inverse square law from the first ball's centre.
            let first = [p[0] - set.centre[0], p[1] - set.centre[1], p[2]];
            let expected = k * dot(first, first) / dot(to, to);
            assert!((row[3] - expected).abs() < 1e-9 * expected, "{row:?}");
        }
    }
    assert!(
        dir.path().join("ball03.png").exists() && dir.path().join("matte/matte03.png").exists()
    );
}
