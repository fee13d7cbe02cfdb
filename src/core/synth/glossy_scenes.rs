//! Glossy scenes with ground truth across materials (issue #45): GGX microfacet lobes
//! from sharp to broad on dielectrics and metals, Blinn–Phong, Ward, a rough diffuse
//! Oren–Nayar surface, coloured metallic highlights and plain Lambertian controls, under
//! 24 to 96 lights, with noise, 16- and 8-bit, exposed so that some highlights clip.
//! Tests reconstruct them in memory; none is written to `res/`.

use super::brdf::{Diffuse, Specular};
use super::capture::Capture;
use super::lights::{light_grid, light_rings};
use super::scene::Scene;
use super::sensor::Exposure;

/// How much of a scene's appearance its specular lobe takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Gloss {
    /// No specular lobe (Lambertian or rough diffuse).
    Matte,
    /// A sharp lobe: each pixel's highlight covers a few lights at most.
    Narrow,
    /// A lobe spread over a wide range of angles (GGX roughness ≥ ~0.3 or the equivalent):
    /// many of a pixel's observations carry some of it.
    Broad,
}

/// One glossy scene: surface, lights, capture and what kind of gloss it shows.
#[derive(Debug, Clone)]
pub struct GlossyScene {
    pub name: &'static str,
    pub scene: Scene,
    pub lights: Vec<[f64; 3]>,
    pub capture: Capture,
    pub kind: Gloss,
    /// The true GGX roughness (sqrt of its alpha) for GGX scenes; None otherwise.
    pub roughness: Option<f64>,
}

/// A GGX Cook–Torrance lobe of `roughness` (alpha = roughness²) and Fresnel `f0`.
fn ggx(roughness: f64, f0: f64) -> Option<Specular> {
    Some(Specular::CookTorrance {
        alpha: roughness * roughness,
        f0,
    })
}

/// The catalogue at `size` × `size` pixels (tests use ~96–128 so each renders fast).
///
/// Diffuse albedos are those of the project's scenes (0.2–0.85; the metals' are dark, as
/// a metal's diffuse is). Exposures either protect the highlights (`Highlights`, the
/// diffuse then dim, as a photographer of shiny objects does) or the diffuse (`Gain`,
/// the highlights then clip).
pub fn glossy_catalogue(size: usize) -> Vec<GlossyScene> {
    // Read noise and shot noise of a good 16-bit camera, and of a worse 8-bit one.
    let clean16 = Capture {
        noise_sigma: 0.001,
        full_well: Some(30_000.0),
        black_level: 0.002,
        ..Capture::default()
    };
    let noisy8 = Capture {
        bit_depth: 8,
        noise_sigma: 0.003,
        full_well: Some(10_000.0),
        ..Capture::default()
    };
    let rings = |count| light_rings(count, 10.0, 60.0);
    let gold = |x: f64, y: f64| {
        let s = size as f64;
        let t = 1.0 + 0.15 * ((x / s * 9.0).sin() * (y / s * 7.0).sin());
        [0.5 * t, 0.36 * t, 0.12 * t]
    };
    vec![
        GlossyScene {
            name: "ggx-0.1-dielectric",
            scene: Scene::sphere(size),
            lights: rings(48),
            capture: Capture {
                specular: ggx(0.1, 0.04),
                exposure: Exposure::Gain(0.8),
                noise_sigma: 0.002,
                seed: 101,
                ..clean16.clone()
            },
            kind: Gloss::Narrow,
            roughness: Some(0.1),
        },
        GlossyScene {
            name: "ggx-0.3-dielectric-bump",
            scene: Scene::bump(size),
            lights: rings(24),
            capture: Capture {
                specular: ggx(0.3, 0.04),
                exposure: Exposure::Highlights(1.5),
                seed: 102,
                ..clean16.clone()
            },
            kind: Gloss::Broad,
            roughness: Some(0.3),
        },
        GlossyScene {
            name: "ggx-0.5-dielectric-8bit",
            scene: Scene::sphere(size),
            lights: light_grid(12, 8, 55.0),
            capture: Capture {
                specular: ggx(0.5, 0.04),
                exposure: Exposure::Highlights(1.1),
                seed: 103,
                ..noisy8.clone()
            },
            kind: Gloss::Broad,
            roughness: Some(0.5),
        },
        GlossyScene {
            name: "ggx-0.3-metal",
            scene: Scene::dark_sphere(size),
            lights: rings(96),
            capture: Capture {
                specular: ggx(0.3, 0.9),
                exposure: Exposure::Highlights(4.0),
                seed: 104,
                ..clean16.clone()
            },
            kind: Gloss::Broad,
            roughness: Some(0.3),
        },
        GlossyScene {
            name: "ggx-0.5-metal-shadows",
            scene: Scene::shadows(size),
            lights: rings(48),
            capture: Capture {
                specular: ggx(0.5, 0.7),
                exposure: Exposure::Highlights(1.3),
                cast_shadows: true,
                seed: 105,
                ..clean16.clone()
            },
            kind: Gloss::Broad,
            roughness: Some(0.5),
        },
        GlossyScene {
            name: "gold-ggx-0.4-rgb",
            scene: Scene::sphere(size).with_colour(gold),
            lights: rings(48),
            capture: Capture {
                specular: ggx(0.4, 0.8),
                // Gold's reflectance: strong in red, weak in blue.
                specular_tint: [1.0, 0.78, 0.35],
                exposure: Exposure::Highlights(2.0),
                seed: 106,
                ..clean16.clone()
            },
            kind: Gloss::Broad,
            roughness: Some(0.4),
        },
        GlossyScene {
            name: "blinn-phong-broad-8bit",
            scene: Scene::sphere(size),
            lights: rings(24),
            capture: Capture {
                specular: Some(Specular::BlinnPhong {
                    strength: 0.5,
                    shininess: 10.0,
                }),
                exposure: Exposure::Highlights(1.15),
                seed: 107,
                ..noisy8.clone()
            },
            kind: Gloss::Broad,
            roughness: None,
        },
        GlossyScene {
            name: "blinn-phong-narrow-bump",
            scene: Scene::bump(size),
            lights: rings(48),
            capture: Capture {
                specular: Some(Specular::BlinnPhong {
                    strength: 0.8,
                    shininess: 200.0,
                }),
                exposure: Exposure::Gain(0.9),
                seed: 108,
                ..clean16.clone()
            },
            kind: Gloss::Narrow,
            roughness: None,
        },
        GlossyScene {
            name: "ward-broad",
            scene: Scene::sphere(size),
            lights: rings(48),
            capture: Capture {
                specular: Some(Specular::Ward {
                    alpha: 0.2,
                    strength: 0.2,
                }),
                exposure: Exposure::Highlights(1.3),
                noise_sigma: 0.003,
                seed: 109,
                ..clean16.clone()
            },
            kind: Gloss::Broad,
            roughness: None,
        },
        GlossyScene {
            name: "oren-nayar",
            scene: Scene::sphere(size),
            lights: rings(48),
            capture: Capture {
                diffuse: Diffuse::OrenNayar { sigma: 0.4 },
                seed: 110,
                ..clean16.clone()
            },
            kind: Gloss::Matte,
            roughness: None,
        },
        GlossyScene {
            name: "oren-nayar-basin-8bit",
            scene: Scene::basin(size),
            lights: rings(24),
            capture: Capture {
                diffuse: Diffuse::OrenNayar { sigma: 0.3 },
                seed: 111,
                ..noisy8.clone()
            },
            kind: Gloss::Matte,
            roughness: None,
        },
        GlossyScene {
            name: "lambert",
            scene: Scene::sphere(size),
            lights: rings(24),
            capture: Capture {
                seed: 112,
                ..clean16.clone()
            },
            kind: Gloss::Matte,
            roughness: None,
        },
        GlossyScene {
            name: "lambert-bump-8bit",
            scene: Scene::bump(size),
            lights: rings(96),
            capture: Capture {
                seed: 113,
                ..noisy8
            },
            kind: Gloss::Matte,
            roughness: None,
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_catalogue_covers_what_issue_45_asks_for() {
        let all = glossy_catalogue(16);
        let has = |f: &dyn Fn(&GlossyScene) -> bool| all.iter().any(f);
        let lobe = |g: &GlossyScene| g.capture.specular;
        assert!(has(&|g| matches!(lobe(g), Some(Specular::Ward { .. }))));
        assert!(has(&|g| matches!(
            lobe(g),
            Some(Specular::BlinnPhong { .. })
        )));
        assert!(has(&|g| matches!(
            g.capture.diffuse,
            Diffuse::OrenNayar { .. }
        )));
        assert!(has(
            &|g| g.scene.channels() == 3 && g.capture.specular_tint != [1.0; 3]
        ));
        for r in [0.1, 0.3, 0.5] {
            assert!(has(&|g| g.roughness == Some(r)), "roughness {r}");
        }
        for n in [24, 48, 96] {
            assert!(has(&|g| g.lights.len() == n), "{n} lights");
        }
        assert!(has(&|g| g.capture.bit_depth == 8) && has(&|g| g.capture.bit_depth == 16));
        assert!(has(&|g| g.kind == Gloss::Matte) && has(&|g| g.kind == Gloss::Narrow));
        for g in &all {
            // The kind and the roughness agree with the capture.
            assert_eq!(g.kind == Gloss::Matte, lobe(g).is_none(), "{}", g.name);
            let truth = match lobe(g) {
                Some(Specular::CookTorrance { alpha, .. }) => Some(alpha.sqrt()),
                _ => None,
            };
            let same = match (g.roughness, truth) {
                (Some(a), Some(b)) => (a - b).abs() < 1e-12,
                (a, b) => a == b,
            };
            assert!(same, "{}: {:?} vs {truth:?}", g.name, g.roughness);
            assert!(g.capture.noise_sigma > 0.0 && g.capture.full_well.is_some());
        }
        let names: std::collections::HashSet<_> = all.iter().map(|g| g.name).collect();
        assert_eq!(names.len(), all.len(), "names are unique");
    }
}
