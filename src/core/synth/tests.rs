//! The renderer's effects checked on small scenes: cast shadows, soft shadows under area
//! lights, interreflection, and what `write_set` writes for RGB and perspective sets.

use ndarray::Array2;

use super::*;

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
        .filter(|&(&a, &b)| a > 2000 && (b as f64) > 0.1 * a as f64 && (b as f64) < 0.9 * a as f64)
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
