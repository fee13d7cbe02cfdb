//! The sets `photostereo render` writes into `res/` ([`catalogue`], [`chrome_catalogue`]):
//! each one's scene, lights and capture.

use super::brdf::Specular;
use super::capture::Capture;
use super::chrome::ChromeSet;
use super::depth_scenes::step_plate;
use super::lights::{light_colours, light_grid, light_rings};
use super::scene::Scene;
use super::sensor::Exposure;
use super::transport::AreaLight;

/// The chrome-sphere calibration sets `photostereo render` writes into `res/`: a small
/// 8-bit one (12 lights, 10°–80° off the view axis, distractors, some highlights clipped).
pub fn chrome_catalogue() -> Vec<(&'static str, ChromeSet)> {
    let mut chrome = ChromeSet::standard(8, 41);
    chrome.lights = light_rings(12, 10.0, 80.0);
    chrome.highlight.truncate(12);
    vec![("chrome", chrome)]
}

/// The capture of `res/glossy` (with [`Scene::dark_sphere`]), also the bench's glossy
/// scene: a dielectric GGX coat of roughness 0.2 over a dark diffuse body, exposed so
/// that the highlights clip a little, with a black level and shot noise.
pub fn glossy_coat() -> Capture {
    Capture {
        // alpha = roughness².
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
    }
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
            glossy_coat(),
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
    use super::super::render::render;
    use super::*;

    /// The catalogue's entry `name`.
    fn entry(name: &str) -> (Scene, Vec<[f64; 3]>, Capture) {
        let (_, scene, lights, capture) = catalogue()
            .into_iter()
            .find(|e| e.0 == name)
            .expect("in the catalogue");
        (scene, lights, capture)
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
}
