//! The scenes the project renders for `res/` and its tests: analytic surfaces with exact
//! normals, depth and albedo (gray or RGB), lit by distant point or area lights of given
//! colours, with cast shadows, one bounce of interreflection, Lambertian or Oren–Nayar
//! diffuse, specular lobes (Blinn–Phong, GGX Cook–Torrance, Ward; tinted for metals) and
//! a camera with exposure, black level, shot and read noise, clipping and quantisation;
//! the glossy catalogue ([`glossy_catalogue`]); and perspective scenes with depth steps
//! ([`depth_scenes`]).

mod brdf;
mod chrome;
mod depth_scenes;
mod glossy_scenes;
mod near_rigs;
mod render;
mod scene;
mod sensor;
mod transport;
mod write;

pub use brdf::{Diffuse, Specular};
pub use chrome::{ChromeSet, RoomLight, matte_intensities};
pub use depth_scenes::{DepthScene, depth_scenes, ortho_step_plate, sphere_in_front, step_plate};
pub use glossy_scenes::{Gloss, GlossyScene, glossy_catalogue};
pub use near_rigs::{
    NOISE_SIGMA, NearRig, close_ring, dome_sphere, far_ring, ring_relief, ring_relief_of,
};
pub use render::{Rendered, render, render_rgb};
pub use scene::Scene;
pub use sensor::Exposure;
pub use transport::AreaLight;
pub use write::{Truth, read_truth, write_set};

/// How the lights, the camera and the material depart from the ideal capture (unit point
/// lights, Lambertian, no shadows cast, exact values).
#[derive(Debug, Clone)]
pub struct Capture {
    pub bit_depth: u8,
    /// Added to every pixel (ambient light + sensor offset), as a fraction of full scale.
    pub black_level: f64,
    /// Standard deviation of additive Gaussian (read) noise, fraction of full scale.
    pub noise_sigma: f64,
    /// Electrons at full scale, for photon shot noise (σ = sqrt(signal / full well));
    /// None for no shot noise.
    pub full_well: Option<f64>,
    pub exposure: Exposure,
    pub specular: Option<Specular>,
    /// The specular lobe's colour per channel (a metal's tinted highlights; a dielectric's
    /// are white, [1, 1, 1]). A gray scene uses the first.
    pub specular_tint: [f64; 3],
    /// The diffuse base: Lambertian, or rough (Oren–Nayar).
    pub diffuse: Diffuse,
    pub cast_shadows: bool,
    /// Lights of finite size (soft shadows); None for point lights.
    pub area_light: Option<AreaLight>,
    /// One bounce of interreflection traced with this many rays per pixel; None for none.
    pub bounce_rays: Option<usize>,
    /// Per-light RGB intensities (one per light, written as `name, x, y, z, r, g, b`
    /// rows); None for unit white lights.
    pub light_colours: Option<Vec<[f64; 3]>>,
    pub seed: u64,
}

impl Default for Capture {
    fn default() -> Self {
        Self {
            bit_depth: 16,
            black_level: 0.0,
            noise_sigma: 0.0,
            full_well: None,
            exposure: Exposure::Gain(1.0),
            specular: None,
            specular_tint: [1.0; 3],
            diffuse: Diffuse::Lambert,
            cast_shadows: false,
            area_light: None,
            bounce_rays: None,
            light_colours: None,
            seed: 1,
        }
    }
}

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

/// The chrome-sphere calibration sets `photostereo render` writes into `res/`: a small
/// 8-bit one (12 lights, 10°–80° off the view axis, distractors, some highlights clipped).
pub fn chrome_catalogue() -> Vec<(&'static str, ChromeSet)> {
    let mut chrome = ChromeSet::standard(8, 41);
    chrome.lights = light_rings(12, 10.0, 80.0);
    chrome.highlight.truncate(12);
    vec![("chrome", chrome)]
}

/// The data sets `photostereo render` writes into `res/`: name, scene, lights, capture.
/// `step-plate` is perspective ([`step_plate`]): it carries its camera (`K.txt`,
/// `camera.json`) and depth along the optical axis as truth; it is kept small (96², eight
/// images) because its EXR truth barely compresses.
pub fn catalogue() -> Vec<(&'static str, Scene, Vec<[f64; 3]>, Capture)> {
    let seed_lights = vec![
        [0.0, 0.0, 1.0],
        [-0.2, 0.0, 1.0],
        [0.2, 0.0, 1.0],
        [0.0, -0.2, 1.0],
    ];
    let sphere_lights = light_rings(24, 10.0, 60.0);
    let low_lights: Vec<[f64; 3]> = (0..24)
        .map(|i| {
            let elevation = (15.0 + 25.0 * (i % 6) as f64 / 5.0).to_radians();
            let azimuth = i as f64 * std::f64::consts::TAU / 24.0 + 0.3;
            [
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            ]
        })
        .collect();
    let noisy = Capture {
        black_level: 0.02,
        noise_sigma: 0.004,
        seed: 7,
        ..Capture::default()
    };
    vec![
        (
            "bump",
            Scene::bump(128),
            seed_lights.clone(),
            Capture::default(),
        ),
        (
            "bump-noisy",
            Scene::bump(128),
            seed_lights,
            Capture {
                bit_depth: 8,
                noise_sigma: 0.01,
                seed: 3,
                ..Capture::default()
            },
        ),
        (
            "sphere",
            Scene::sphere(256),
            sphere_lights.clone(),
            Capture::default(),
        ),
        (
            "sphere-noisy",
            Scene::sphere(256),
            sphere_lights.clone(),
            noisy.clone(),
        ),
        (
            "sphere-specular",
            Scene::sphere(256),
            sphere_lights,
            Capture {
                specular: Some(Specular::BlinnPhong {
                    strength: 0.6,
                    shininess: 40.0,
                }),
                ..Capture::default()
            },
        ),
        (
            "shadows",
            Scene::shadows(192),
            low_lights.clone(),
            Capture {
                cast_shadows: true,
                ..Capture::default()
            },
        ),
        (
            "shadows-noisy",
            Scene::shadows(192),
            low_lights,
            Capture {
                bit_depth: 8,
                black_level: 0.01,
                noise_sigma: 0.01,
                cast_shadows: true,
                seed: 11,
                ..Capture::default()
            },
        ),
        (
            "soft-shadows",
            Scene::basin(128),
            light_rings(64, 10.0, 70.0),
            Capture {
                cast_shadows: true,
                area_light: Some(AreaLight {
                    radius_deg: 4.0,
                    samples: 32,
                }),
                bounce_rays: Some(64),
                noise_sigma: 0.0005,
                full_well: Some(40_000.0),
                seed: 13,
                ..Capture::default()
            },
        ),
        (
            "glossy",
            Scene::dark_sphere(128),
            light_rings(64, 10.0, 60.0),
            Capture {
                // Roughness 0.2 (alpha = roughness²), a dielectric coat.
                specular: Some(Specular::CookTorrance {
                    alpha: 0.04,
                    f0: 0.04,
                }),
                exposure: Exposure::Highlights(1.3),
                black_level: 0.002,
                noise_sigma: 0.0003,
                full_well: Some(20_000.0),
                seed: 17,
                ..Capture::default()
            },
        ),
        (
            "rgb96",
            Scene::painted_sphere(96),
            light_grid(12, 8, 48.0),
            Capture {
                light_colours: Some(light_colours(96, 0.6, 1.4, 23)),
                noise_sigma: 0.0005,
                full_well: Some(30_000.0),
                seed: 19,
                ..Capture::default()
            },
        ),
        (
            "step-plate",
            step_plate(96).to_scene(),
            light_rings(8, 10.0, 50.0),
            Capture::default(),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;

    /// The catalogue's entry `name`.
    fn entry(name: &str) -> (Scene, Vec<[f64; 3]>, Capture) {
        let (_, scene, lights, capture) = catalogue()
            .into_iter()
            .find(|e| e.0 == name)
            .expect("in the catalogue");
        (scene, lights, capture)
    }

    /// Channel 0 of the single image rendered under `light`.
    fn image(scene: &Scene, light: [f64; 3], capture: &Capture) -> Array2<u16> {
        render(scene, &[light], capture).images[0]
            .index_axis(ndarray::Axis(2), 0)
            .to_owned()
    }

    fn low_light(elevation_deg: f64) -> [f64; 3] {
        let e = elevation_deg.to_radians();
        [e.cos(), 0.0, e.sin()]
    }

    #[test]
    fn cast_shadows_darken_the_far_side_of_a_bump() {
        let s = Scene::shadows(96);
        let lit = image(&s, low_light(10.0), &Capture::default());
        let shadowed = image(
            &s,
            low_light(10.0),
            &Capture {
                cast_shadows: true,
                ..Capture::default()
            },
        );
        let dark = lit.iter().zip(&shadowed).filter(|(a, b)| a > b).count();
        assert!(dark > 50, "{dark} pixels in cast shadow");
        assert!(lit.iter().zip(&shadowed).all(|(a, b)| a >= b));
    }

    /// Pixels a cast shadow dims to between 10 % and 90 % of their unshadowed value.
    fn penumbra_pixels(area_light: Option<AreaLight>) -> usize {
        let s = Scene::basin(96);
        let capture = Capture {
            area_light,
            ..Capture::default()
        };
        let open = image(&s, low_light(25.0), &capture);
        let shadowed = image(
            &s,
            low_light(25.0),
            &Capture {
                cast_shadows: true,
                ..capture.clone()
            },
        );
        open.iter()
            .zip(&shadowed)
            .filter(|&(&a, &b)| {
                a > 2000 && (b as f64) > 0.1 * a as f64 && (b as f64) < 0.9 * a as f64
            })
            .count()
    }

    #[test]
    fn area_lights_cast_soft_shadows() {
        let area = AreaLight {
            radius_deg: 5.0,
            samples: 32,
        };
        let (hard, soft) = (penumbra_pixels(None), penumbra_pixels(Some(area)));
        eprintln!("partially shadowed pixels: point light {hard}, area light {soft}");
        assert!(
            hard < 5,
            "a point light's shadows are hard: {hard} partial pixels"
        );
        assert!(soft > 40, "an area light's are soft: {soft} partial pixels");
    }

    #[test]
    fn interreflection_only_adds_light_and_most_in_concavities() {
        let s = Scene::basin(96);
        let capture = Capture {
            cast_shadows: true,
            ..Capture::default()
        };
        let light = light_rings(3, 20.0, 20.0)[1];
        let direct = image(&s, light, &capture);
        let both = image(
            &s,
            light,
            &Capture {
                bounce_rays: Some(64),
                ..capture
            },
        );
        assert!(direct.iter().zip(&both).all(|(d, b)| b >= d));
        // Mean relative gain over a region (rows, cols as fractions of the frame).
        let gain = |rows: (f64, f64), cols: (f64, f64)| {
            let mut sum = (0.0, 0.0);
            for ((r, c), &d) in direct.indexed_iter() {
                let (y, x) = (r as f64 / 96.0, c as f64 / 96.0);
                if (rows.0..rows.1).contains(&y) && (cols.0..cols.1).contains(&x) && d > 1000 {
                    sum = (sum.0 + both[[r, c]] as f64 - d as f64, sum.1 + d as f64);
                }
            }
            sum.0 / sum.1
        };
        let bowl = gain((0.25, 0.41), (0.22, 0.38));
        let open_plane = gain((0.05, 0.15), (0.05, 0.15));
        let trench = gain((0.78, 0.82), (0.1, 0.9));
        eprintln!(
            "interreflection adds: bowl {bowl:.3}, trench {trench:.3}, open plane {open_plane:.4}"
        );
        assert!(bowl > 0.03 && trench > 0.03, "bowl {bowl}, trench {trench}");
        assert!(
            open_plane < 0.2 * bowl,
            "open plane {open_plane} vs bowl {bowl}"
        );
    }

    #[test]
    fn glossy_exposure_is_set_by_the_highlights() {
        let (scene, lights, capture) = entry("glossy");
        let shot = render(&scene, &lights, &capture);
        let clipped = shot
            .images
            .iter()
            .filter(|img| img.iter().any(|&v| v == 65535))
            .count();
        assert!(
            clipped * 2 > lights.len(),
            "{clipped} of {} images clip",
            lights.len()
        );
        // The diffuse part alone, at the same gain and without noise or offset.
        let diffuse = render(
            &scene,
            &lights,
            &Capture {
                specular: None,
                exposure: Exposure::Gain(shot.gain),
                black_level: 0.0,
                noise_sigma: 0.0,
                full_well: None,
                ..capture
            },
        );
        let mut lit: Vec<u16> = diffuse
            .images
            .iter()
            .flat_map(|img| img.iter().cloned())
            .filter(|&v| v > 0)
            .collect();
        let k = lit.len() / 2;
        let median = *lit.select_nth_unstable(k).1;
        let top = lit.iter().cloned().max().unwrap();
        eprintln!(
            "glossy: gain {:.4}, diffuse median {median} max {top} counts, {clipped} of {} images clip",
            shot.gain,
            lights.len()
        );
        assert!((300..=800).contains(&median), "diffuse median {median}");
        assert!((top as f64) < 0.02 * 65535.0, "diffuse maximum {top}");
    }

    #[test]
    fn rgb_channels_divided_by_their_intensities_agree() {
        let (scene, lights, capture) = entry("rgb96");
        assert_eq!((lights.len(), scene.channels()), (96, 3));
        let colours = capture.light_colours.clone().unwrap();
        let exact = render(
            &scene,
            &lights,
            &Capture {
                noise_sigma: 0.0,
                full_well: None,
                ..capture
            },
        );
        let mut checked = 0;
        for (img, colour) in exact.images.iter().zip(&colours) {
            for ((r, c), _) in scene.mask.indexed_iter().filter(|(_, m)| **m) {
                // Each channel over intensity × albedo is the same unit-light shading.
                let shading = |k: usize| {
                    img[[r, c, k]] as f64 / 65535.0 / (colour[k] * scene.albedo[[r, c, k]])
                };
                if img[[r, c, 0]] > 2000 && img[[r, c, 1]] > 2000 && img[[r, c, 2]] > 2000 {
                    assert!((shading(0) - shading(1)).abs() < 2e-3, "{r},{c}");
                    assert!((shading(0) - shading(2)).abs() < 2e-3, "{r},{c}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 100_000, "{checked}");
        let spread = colours
            .iter()
            .flatten()
            .fold((f64::MAX, 0f64), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        assert!(spread.0 < 0.7 && spread.1 > 1.3 && spread.0 >= 0.6 && spread.1 <= 1.4);
    }

    #[test]
    fn rgb_sets_write_colour_rows_and_luminance_truth() {
        let dir = tempfile::tempdir().unwrap();
        let scene = Scene::painted_sphere(24);
        let lights = light_grid(3, 2, 40.0);
        let capture = Capture {
            light_colours: Some(light_colours(6, 0.6, 1.4, 2)),
            ..Capture::default()
        };
        write_set(dir.path(), &scene, &lights, &capture).unwrap();
        let csv = std::fs::read_to_string(dir.path().join("light_directions.csv")).unwrap();
        let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(", ").collect()).collect();
        assert_eq!(rows.len(), 6);
        assert!(rows.iter().all(|r| r.len() == 7), "{csv}");
        let img = image::open(dir.path().join("im1.png")).unwrap();
        assert_eq!(img.color(), image::ColorType::Rgb16);
        let truth = read_truth(dir.path()).unwrap();
        let a = |k: usize| scene.albedo[[12, 12, k]];
        let luma = 0.2126 * a(0) + 0.7152 * a(1) + 0.0722 * a(2);
        assert!((truth.albedo[[12, 12]] as f64 - luma).abs() < 1e-6);
        assert!((a(0) - a(1)).abs() > 0.01, "the channels differ");
    }

    #[test]
    fn perspective_sets_write_their_camera_and_depth() {
        let dir = tempfile::tempdir().unwrap();
        let scene = sphere_in_front(32);
        let lights = light_rings(4, 10.0, 40.0);
        write_set(dir.path(), &scene.to_scene(), &lights, &Capture::default()).unwrap();
        let camera = crate::core::camera::Pinhole::in_folder(dir.path()).unwrap();
        assert_eq!(camera, scene.camera);
        let k = crate::core::camera::Pinhole::read(&dir.path().join("K.txt")).unwrap();
        assert_eq!(Some(k), scene.camera);
        let truth = read_truth(dir.path()).unwrap();
        assert_eq!(truth.mask, scene.mask);
        for (t, d) in truth.depth.iter().zip(&scene.depth) {
            assert_eq!(t, d);
        }
        for (t, n) in truth.normals.iter().zip(&scene.normals) {
            assert_eq!(t, n);
        }
    }
}
