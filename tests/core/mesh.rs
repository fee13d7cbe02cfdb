//! glTF meshes and the preview, through the public API: geometry follows the mask, the
//! frame and the numbers match the reconstruction, files are well-formed, deterministic,
//! small enough, and pass the Khronos glTF-Validator.

use std::path::{Path, PathBuf};
use std::process::Command;

use ndarray::{Array2, Array3};
use photostereo::core::mesh::{self, MeshError};
use photostereo::core::options::{MeshNormals, MeshOptions};
use photostereo::core::preview::preview;
use photostereo::core::reconstruction::{Reconstruction, Report};
use serde_json::Value;

/// A reconstruction from a per-pixel surface: `Some((height, normal))` on the mask, the
/// normal in the arrays' frame (x right, y down, z towards the camera).
fn reconstruction(
    width: usize,
    height: usize,
    surface: impl Fn(usize, usize) -> Option<(f32, [f32; 3])>,
) -> Reconstruction {
    let mut mask = Array2::from_elem((height, width), false);
    let mut heights = Array2::zeros((height, width));
    let mut normals = Array3::zeros((height, width, 3));
    let mut albedo = Array2::zeros((height, width));
    for r in 0..height {
        for c in 0..width {
            if let Some((z, n)) = surface(r, c) {
                mask[[r, c]] = true;
                heights[[r, c]] = z;
                albedo[[r, c]] = 0.8;
                for k in 0..3 {
                    normals[[r, c, k]] = n[k];
                }
            }
        }
    }
    let lowest = (heights.iter().zip(&mask))
        .filter(|(_, m)| **m)
        .map(|(z, _)| *z)
        .fold(f32::INFINITY, f32::min);
    heights.zip_mut_with(&mask, |z, &m| {
        if !m {
            *z = lowest;
        }
    });
    let confidence = mask.mapv(f32::from);
    Reconstruction {
        width,
        height,
        lights: Vec::new(),
        albedo,
        albedo_rgb: None,
        gloss: None,
        normals,
        mask,
        heights,
        curl: Array2::zeros((height, width)),
        confidence,
        unreliable: Array2::from_elem((height, width), false),
        report: Report::default(),
    }
}

/// A hemisphere of radius `radius` centred in a `size`×`size` picture, its disc shrunk by
/// a pixel so the rim normals are not horizontal.
fn hemisphere(size: usize, radius: f32) -> Reconstruction {
    let centre = (size as f32 - 1.0) / 2.0;
    reconstruction(size, size, |r, c| {
        let (x, y) = (c as f32 - centre, r as f32 - centre);
        let rr = x * x + y * y;
        (rr < (radius - 1.0).powi(2)).then(|| {
            let z = (radius * radius - rr).sqrt();
            (z, [x / radius, y / radius, z / radius])
        })
    })
}

/// The hemisphere with a square hole, a one-pixel line and a lone pixel added.
fn awkward_mask() -> Reconstruction {
    let mut rec = hemisphere(61, 25.0);
    for r in 25..36 {
        for c in 27..33 {
            rec.mask[[r, c]] = false;
        }
    }
    let lines = (2..58).map(|c| (58, c));
    for (r, c) in lines.chain([(2, 2), (0, 60), (60, 0)]) {
        rec.mask[[r, c]] = true;
        rec.normals[[r, c, 2]] = 1.0;
    }
    rec
}

fn opts() -> MeshOptions {
    MeshOptions::default()
}

fn with_step(step: usize) -> MeshOptions {
    MeshOptions {
        step: Some(step),
        ..opts()
    }
}

/// A parsed GLB: the JSON document and the BIN chunk, with the container checked.
struct Glb {
    doc: Value,
    bin: Vec<u8>,
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap())
}

fn parse_glb(bytes: &[u8]) -> Glb {
    assert_eq!(&bytes[0..4], b"glTF", "magic");
    assert_eq!(u32_at(bytes, 4), 2, "version");
    assert_eq!(u32_at(bytes, 8) as usize, bytes.len(), "total length");
    let json_len = u32_at(bytes, 12) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_len % 4, 0, "JSON chunk alignment");
    let json = &bytes[20..20 + json_len];
    let text_end = json.iter().rposition(|&b| b != b' ').unwrap() + 1;
    assert!(
        json.len() - text_end < 4,
        "JSON padded with at most 3 spaces"
    );
    let doc: Value = serde_json::from_slice(json).expect("JSON chunk parses");
    let at = 20 + json_len;
    let bin_len = u32_at(bytes, at) as usize;
    assert_eq!(&bytes[at + 4..at + 8], b"BIN\0");
    assert_eq!(bin_len % 4, 0, "BIN chunk alignment");
    assert_eq!(at + 8 + bin_len, bytes.len(), "BIN is the last chunk");
    let bin = bytes[at + 8..].to_vec();
    assert_eq!(
        doc["buffers"][0]["byteLength"], bin_len,
        "buffer fills the BIN chunk"
    );
    assert!(
        doc["buffers"][0].get("uri").is_none(),
        "GLB buffer has no uri"
    );
    Glb { doc, bin }
}

impl Glb {
    fn primitive(&self) -> &Value {
        &self.doc["meshes"][0]["primitives"][0]
    }

    fn accessor(&self, index: &Value) -> &Value {
        &self.doc["accessors"][index.as_u64().unwrap() as usize]
    }

    /// An accessor's bytes (tightly packed, as the meshes are written).
    fn bytes(&self, accessor: &Value) -> &[u8] {
        let view = &self.doc["bufferViews"][accessor["bufferView"].as_u64().unwrap() as usize];
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize;
        assert_eq!(start % 4, 0, "views are 4-byte aligned");
        &self.bin[start..start + view["byteLength"].as_u64().unwrap() as usize]
    }

    fn vec3(&self, semantic: &str) -> Vec<[f32; 3]> {
        let a = self.accessor(&self.primitive()["attributes"][semantic]);
        assert_eq!(
            (a["type"].as_str(), a["componentType"].as_u64()),
            (Some("VEC3"), Some(5126))
        );
        let floats: Vec<f32> = (self.bytes(a).chunks_exact(4))
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(floats.len(), 3 * a["count"].as_u64().unwrap() as usize);
        floats.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect()
    }

    fn positions(&self) -> Vec<[f32; 3]> {
        self.vec3("POSITION")
    }

    fn normals(&self) -> Vec<[f32; 3]> {
        self.vec3("NORMAL")
    }

    fn triangles(&self) -> Vec<[u32; 3]> {
        let a = self.accessor(&self.primitive()["indices"]);
        let bytes = self.bytes(a);
        let indices: Vec<u32> = match a["componentType"].as_u64().unwrap() {
            5123 => (bytes.chunks_exact(2))
                .map(|b| u32::from(u16::from_le_bytes([b[0], b[1]])))
                .collect(),
            5125 => bytes
                .chunks_exact(4)
                .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
                .collect(),
            other => panic!("index component type {other}"),
        };
        assert_eq!(indices.len(), a["count"].as_u64().unwrap() as usize);
        indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect()
    }
}

/// The pixel `(row, col)` a vertex came from, for meshes in pixel units.
fn pixel_of(p: [f32; 3]) -> (usize, usize) {
    assert!(p[0] >= 0.0 && p[1] <= 0.0 && p[0].fract() == 0.0 && p[1].fract() == 0.0);
    ((-p[1]) as usize, p[0] as usize)
}

fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
    let dot: f64 = (0..3).map(|k| f64::from(a[k]) * f64::from(b[k])).sum();
    dot.clamp(-1.0, 1.0).acos().to_degrees()
}

/// The arrays' normal at a pixel in glTF's frame (y flipped).
fn photometric_normal(rec: &Reconstruction, (r, c): (usize, usize)) -> [f32; 3] {
    [
        rec.normals[[r, c, 0]],
        -rec.normals[[r, c, 1]],
        rec.normals[[r, c, 2]],
    ]
}

#[test]
fn glb_header_and_chunks_are_well_formed() {
    let bytes = mesh::glb(&hemisphere(40, 15.0), &opts()).unwrap();
    let glb = parse_glb(&bytes);
    assert_eq!(glb.doc["asset"]["version"], "2.0");
    // Padding: spaces after the JSON (checked in parse_glb), zeros after the last view.
    let last_end = (glb.doc["bufferViews"].as_array().unwrap().iter())
        .map(|v| (v["byteOffset"].as_u64().unwrap() + v["byteLength"].as_u64().unwrap()) as usize)
        .max()
        .unwrap();
    assert!(glb.bin[last_end..].iter().all(|&b| b == 0));
    assert!(glb.bin.len() - last_end < 4);
}

#[test]
fn triangles_cover_exactly_the_mask() {
    let rec = awkward_mask();
    for step in [1, 2, 3] {
        let glb = parse_glb(&mesh::glb(&rec, &with_step(step)).unwrap());
        let positions = glb.positions();
        let triangles = glb.triangles();

        // Expected from the mask alone: one vertex per sampled mask pixel; per grid cell
        // two triangles with four corners in the mask, one with three.
        let on = |gi: usize, gj: usize| {
            let (r, c) = (gi * step, gj * step);
            r < rec.height && c < rec.width && rec.mask[[r, c]]
        };
        let (gh, gw) = (rec.height.div_ceil(step), rec.width.div_ceil(step));
        let vertices = (0..gh).flat_map(|i| (0..gw).map(move |j| (i, j)));
        let vertices = vertices.filter(|&(i, j)| on(i, j)).count();
        let mut expected = 0;
        for i in 1..gh {
            for j in 1..gw {
                let corners = [on(i - 1, j - 1), on(i - 1, j), on(i, j - 1), on(i, j)];
                expected += match corners.iter().filter(|&&b| b).count() {
                    4 => 2,
                    3 => 1,
                    _ => 0,
                };
            }
        }
        assert_eq!(positions.len(), vertices, "step {step}: vertices");
        assert_eq!(triangles.len(), expected, "step {step}: triangles");

        for t in &triangles {
            let px = t.map(|i| pixel_of(positions[i as usize]));
            for (r, c) in px {
                assert!(
                    rec.mask[[r, c]],
                    "step {step}: {t:?} uses background ({r}, {c})"
                );
                assert_eq!((r % step, c % step), (0, 0), "step {step}: off-grid vertex");
            }
            // Corners within one grid cell: no triangle spans a hole or the background.
            let rows = px.map(|p| p.0);
            let cols = px.map(|p| p.1);
            assert_eq!(
                rows.iter().max().unwrap() - rows.iter().min().unwrap(),
                step
            );
            assert_eq!(
                cols.iter().max().unwrap() - cols.iter().min().unwrap(),
                step
            );
            // Front faces towards the viewer: counter-clockwise seen from +z.
            let [a, b, c] = t.map(|i| positions[i as usize]);
            let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            assert!(cross > 0.0, "step {step}: {t:?} is clockwise");
        }
    }
}

#[test]
fn photometric_normals_match_the_reconstruction() {
    let rec = awkward_mask();
    for step in [1, 3] {
        let glb = parse_glb(&mesh::glb(&rec, &with_step(step)).unwrap());
        for (p, n) in glb.positions().into_iter().zip(glb.normals()) {
            let len = n.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((len - 1.0).abs() < 1e-5, "unit normals");
            let expected = photometric_normal(&rec, pixel_of(p));
            let angle = angle_deg(n, expected);
            assert!(
                angle < 1.0,
                "normal at {:?} off by {angle:.3}°",
                pixel_of(p)
            );
        }
    }
}

#[test]
fn geometric_normals_match_a_smooth_hemisphere_inside() {
    let (size, radius) = (241, 100.0);
    let rec = hemisphere(size, radius);
    let centre = (size as f32 - 1.0) / 2.0;
    let opts = MeshOptions {
        normals: MeshNormals::Geometric,
        ..opts()
    };
    let glb = parse_glb(&mesh::glb(&rec, &opts).unwrap());
    let mut worst = 0.0f64;
    for (p, n) in glb.positions().into_iter().zip(glb.normals()) {
        let (r, c) = pixel_of(p);
        let d = ((r as f32 - centre).powi(2) + (c as f32 - centre).powi(2)).sqrt();
        if d < 0.7 * radius {
            worst = worst.max(angle_deg(n, photometric_normal(&rec, (r, c))));
        }
    }
    assert!(worst < 3.0, "geometric normals off by up to {worst:.2}°");
}

#[test]
fn height_scale_tilts_photometric_normals_like_the_surface() {
    // With z stretched, photometric normals must still agree with the geometry.
    let rec = hemisphere(121, 50.0);
    let centre = 60.0;
    let scaled = |normals| MeshOptions {
        height_scale: 2.0,
        normals,
        ..opts()
    };
    let photo = parse_glb(&mesh::glb(&rec, &scaled(MeshNormals::Photometric)).unwrap());
    let geo = parse_glb(&mesh::glb(&rec, &scaled(MeshNormals::Geometric)).unwrap());
    let positions = photo.positions();
    assert_eq!(positions, geo.positions());
    for ((p, a), b) in positions.iter().zip(photo.normals()).zip(geo.normals()) {
        let (r, c) = pixel_of(*p);
        if ((r as f32 - centre).powi(2) + (c as f32 - centre).powi(2)).sqrt() < 0.6 * 50.0 {
            assert!(angle_deg(a, b) < 3.0, "at ({r}, {c}): {a:?} vs {b:?}");
        }
    }
}

#[test]
fn hemisphere_centre_is_nearest_the_viewer() {
    let rec = hemisphere(61, 25.0);
    let glb = parse_glb(&mesh::glb(&rec, &opts()).unwrap());
    let positions = glb.positions();
    let z_at = |rc| positions.iter().find(|p| pixel_of(**p) == rc).unwrap()[2];
    let centre = z_at((30, 30));
    assert!((centre - 25.0).abs() < 1e-4, "apex at the radius: {centre}");
    let rim = positions.iter().filter(|p| {
        let (r, c) = pixel_of(**p);
        ((r as f32 - 30.0).powi(2) + (c as f32 - 30.0).powi(2)).sqrt() > 22.0
    });
    for p in rim {
        assert!(
            p[2] < centre - 10.0,
            "rim vertex {p:?} not below the apex {centre}"
        );
    }
}

#[test]
fn bounds_match_the_data() {
    let rec = awkward_mask();
    for (pixel_size, height_scale) in [(None, 1.0), (Some(0.5e-3), 2.5)] {
        let opts = MeshOptions {
            pixel_size,
            height_scale,
            ..opts()
        };
        let glb = parse_glb(&mesh::glb(&rec, &opts).unwrap());
        let accessor = glb.accessor(&glb.primitive()["attributes"]["POSITION"]);
        let positions = glb.positions();
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let as_f32 = |v: &Value| -> Vec<f32> {
            v.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect()
        };
        assert_eq!(as_f32(&accessor["min"]), lo);
        assert_eq!(as_f32(&accessor["max"]), hi);

        // And the data is the reconstruction: columns, flipped rows, scaled heights.
        let unit = pixel_size.unwrap_or(1.0);
        let (rows, cols): (Vec<usize>, Vec<usize>) = (rec.mask.indexed_iter())
            .filter(|(_, m)| **m)
            .map(|(rc, _)| rc)
            .unzip();
        let zs = (rec.heights.iter().zip(&rec.mask))
            .filter(|(_, m)| **m)
            .map(|(z, _)| *z);
        let (zlo, zhi) = zs.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), z| {
            (a.min(z), b.max(z))
        });
        let close = |a: f32, b: f64| (f64::from(a) - b).abs() <= 1e-6 * b.abs().max(1e-3);
        assert!(close(lo[0], *cols.iter().min().unwrap() as f64 * unit));
        assert!(close(hi[0], *cols.iter().max().unwrap() as f64 * unit));
        assert!(close(lo[1], -(*rows.iter().max().unwrap() as f64) * unit));
        assert!(close(hi[1], -(*rows.iter().min().unwrap() as f64) * unit));
        let zunit = unit * f64::from(height_scale);
        assert!(close(lo[2], f64::from(zlo) * zunit), "{} vs {}", lo[2], zlo);
        assert!(close(hi[2], f64::from(zhi) * zunit), "{} vs {}", hi[2], zhi);
    }
}

#[test]
fn decimation_respects_max_vertices() {
    let rec = reconstruction(300, 200, |_, _| Some((0.0, [0.0, 0.0, 1.0])));
    let sampled = |step: usize| 300usize.div_ceil(step) * 200usize.div_ceil(step);
    for max_vertices in [60_000, 59_999, 5_000, 100] {
        let opts = MeshOptions {
            max_vertices,
            ..opts()
        };
        let tri = mesh::triangulate(&rec, &opts).unwrap();
        let glb = parse_glb(&mesh::glb(&rec, &opts).unwrap());
        let n = glb.positions().len();
        assert_eq!(n, tri.positions.len());
        assert_eq!(n, sampled(tri.step));
        assert!(n <= max_vertices, "{n} vertices > {max_vertices}");
        assert!(
            tri.step == 1 || sampled(tri.step - 1) > max_vertices,
            "step not minimal"
        );
    }
    // A requested step larger than needed wins.
    let tri = mesh::triangulate(&rec, &with_step(7)).unwrap();
    assert_eq!((tri.step, tri.positions.len()), (7, sampled(7)));
}

#[test]
fn output_is_deterministic() {
    let mut rec = awkward_mask();
    rec.albedo_rgb = Some(Array3::from_shape_fn((61, 61, 3), |(r, c, k)| {
        ((r * 7 + c * 3 + k * 11) % 17) as f32 / 16.0
    }));
    for opts in [opts(), with_step(2)] {
        assert_eq!(
            mesh::glb(&rec, &opts).unwrap(),
            mesh::glb(&rec, &opts).unwrap()
        );
        assert_eq!(
            mesh::gltf(&rec, &opts).unwrap(),
            mesh::gltf(&rec, &opts).unwrap()
        );
    }
}

#[test]
fn gltf_embeds_the_glb_buffer() {
    let rec = awkward_mask();
    let glb = parse_glb(&mesh::glb(&rec, &opts()).unwrap());
    let text = mesh::gltf(&rec, &opts()).unwrap();
    let mut doc: Value = serde_json::from_str(&text).unwrap();
    let uri = doc["buffers"][0]["uri"].as_str().unwrap().to_owned();
    let data = uri
        .strip_prefix("data:application/octet-stream;base64,")
        .unwrap();
    assert_eq!(base64_decode(data), glb.bin);
    // Apart from the data URI the documents are the same.
    doc["buffers"][0].as_object_mut().unwrap().remove("uri");
    assert_eq!(doc, glb.doc);
}

fn base64_decode(text: &str) -> Vec<u8> {
    const ABC: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    assert_eq!(text.len() % 4, 0);
    let mut out = Vec::new();
    for quad in text.as_bytes().chunks(4) {
        let pad = quad.iter().filter(|&&b| b == b'=').count();
        let n = (quad.iter()).fold(0u32, |n, &b| {
            n << 6 | ABC.iter().position(|&a| a == b).unwrap_or(0) as u32
        });
        out.extend_from_slice(&n.to_be_bytes()[1..4 - pad]);
    }
    out
}

#[test]
fn empty_mask_is_an_error() {
    let rec = reconstruction(20, 10, |_, _| None);
    let err = mesh::glb(&rec, &opts()).unwrap_err();
    assert!(matches!(err, MeshError::EmptyMask), "{err:?}");
    assert_eq!(err.to_string(), "the mask is empty: no mesh");
    assert!(matches!(
        mesh::gltf(&rec, &opts()),
        Err(MeshError::EmptyMask)
    ));
    // Pixels but no three neighbours: no triangles either.
    let dots = reconstruction(20, 10, |r, c| {
        ((r + c) % 2 == 0).then_some((0.0, [0.0, 0.0, 1.0]))
    });
    let err = mesh::glb(&dots, &opts()).unwrap_err();
    assert!(matches!(err, MeshError::NoTriangles { step: 1 }), "{err:?}");
}

#[test]
fn one_megapixel_mesh_is_under_40_mb() {
    let size = 1000;
    let rec = reconstruction(size, size, |r, c| {
        let (x, y) = (c as f32 / 100.0, r as f32 / 100.0);
        Some((20.0 * x.sin() * y.cos(), [0.0, 0.0, 1.0]))
    });
    let glb = mesh::glb(&rec, &opts()).unwrap();
    let gltf = mesh::gltf(&rec, &opts()).unwrap();
    println!("1 MP: {} bytes GLB, {} bytes glTF", glb.len(), gltf.len());
    assert!(glb.len() < 40_000_000, "{} bytes", glb.len());
    assert!(gltf.len() < 40_000_000, "{} bytes", gltf.len());
}

/// Run `.ci/gltf-validate.mjs` over `files`; skip loudly when the validator is not
/// installed, except on CI where that is a failure.
fn khronos_validate(files: &[PathBuf]) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let on_ci = std::env::var("CI").is_ok_and(|v| !matches!(v.as_str(), "" | "0" | "false"));
    let installed = root.join(".ci/node_modules/gltf-validator").is_dir();
    let output = installed.then(|| {
        Command::new("node")
            .arg(root.join(".ci/gltf-validate.mjs"))
            .args(files)
            .output()
    });
    let output = match output {
        Some(Ok(output)) => output,
        missing => {
            let why = match missing {
                Some(Err(e)) => format!("cannot run node: {e}"),
                _ => "gltf-validator is not installed".to_owned(),
            };
            assert!(!on_ci, "{why}: run `cd .ci && npm ci`");
            eprintln!("\n!!!!!!!! skipped: {why}: run `cd .ci && npm ci` !!!!!!!!\n");
            return;
        }
    };
    let stdout = String::from_utf8_lossy(&output.stdout);
    println!("{stdout}{}", String::from_utf8_lossy(&output.stderr));
    assert!(
        output.status.success(),
        "glTF-Validator found errors:\n{stdout}"
    );
}

#[test]
fn meshes_pass_the_khronos_validator() {
    let dir = tempfile::tempdir().unwrap();
    let mut rgb = awkward_mask();
    rgb.albedo_rgb = Some(Array3::from_shape_fn((61, 61, 3), |(r, c, k)| {
        [r as f32 / 60.0, c as f32 / 60.0, 0.5][k]
    }));
    // 90 000 vertices: u32 indices.
    let big = reconstruction(300, 300, |r, _| {
        Some(((r as f32 * 0.05).sin() * 5.0, [0.0, 0.0, 1.0]))
    });
    // Wider than the largest texture: the albedo is downscaled.
    let wide = reconstruction(5000, 12, |r, c| {
        (r > 1 && c % 97 != 0).then_some((0.0, [0.0, 0.0, 1.0]))
    });
    let cases: [(&str, Reconstruction, MeshOptions); 7] = [
        ("hemisphere", hemisphere(61, 25.0), opts()),
        ("awkward", awkward_mask(), with_step(2)),
        ("rgb", rgb, opts()),
        (
            "geometric-metres",
            awkward_mask(),
            MeshOptions {
                normals: MeshNormals::Geometric,
                pixel_size: Some(1e-4),
                height_scale: 3.0,
                ..opts()
            },
        ),
        ("big", big, opts()),
        ("wide", wide, opts()),
        (
            "decimated",
            hemisphere(241, 100.0),
            MeshOptions {
                max_vertices: 2000,
                ..opts()
            },
        ),
    ];
    let mut files = Vec::new();
    for (name, rec, opts) in &cases {
        let glb = dir.path().join(format!("{name}.glb"));
        std::fs::write(&glb, mesh::glb(rec, opts).unwrap()).unwrap();
        let gltf = dir.path().join(format!("{name}.gltf"));
        std::fs::write(&gltf, mesh::gltf(rec, opts).unwrap()).unwrap();
        files.extend([glb, gltf]);
    }
    khronos_validate(&files);
}

/// Save a preview under `$MESH_PREVIEW_DIR` (for looking at it during development).
fn keep(name: &str, img: &image::RgbImage) {
    if let Some(dir) = std::env::var_os("MESH_PREVIEW_DIR") {
        img.save(Path::new(&dir).join(name)).unwrap();
    }
}

const BACKGROUND: image::Rgb<u8> = image::Rgb(photostereo::core::preview::BACKGROUND);

#[test]
fn preview_fills_the_frame_with_the_object() {
    let img = preview(&hemisphere(241, 100.0), 400, 300);
    keep("preview-hemisphere.png", &img);
    assert_eq!(img.dimensions(), (400, 300));
    let (mut lo, mut hi) = ((u32::MAX, u32::MAX), (0, 0));
    for (x, y, p) in img.enumerate_pixels() {
        if *p != BACKGROUND {
            lo = (lo.0.min(x), lo.1.min(y));
            hi = (hi.0.max(x), hi.1.max(y));
        }
    }
    let (w, h) = (hi.0 - lo.0 + 1, hi.1 - lo.1 + 1);
    assert!(w >= 360 || h >= 270, "object spans only {w}×{h}");
    assert!(w <= 400 && h <= 300);
    assert_ne!(*img.get_pixel(200, 150), BACKGROUND, "centre is drawn");
}

#[test]
fn preview_is_upright_and_not_mirrored() {
    // Red top half, blue left half, on a gentle dome.
    let size = 200;
    let mut rec = reconstruction(size, size, |r, c| {
        let (x, y) = (c as f32 - 99.5, r as f32 - 99.5);
        let z = 30.0 - (x * x + y * y) / 1000.0;
        let n = [x / 500.0, y / 500.0, 1.0];
        let len = (n[0] * n[0] + n[1] * n[1] + 1.0).sqrt();
        Some((z, n.map(|v| v / len)))
    });
    rec.albedo_rgb = Some(Array3::from_shape_fn(
        (size, size, 3),
        |(r, c, k)| match k {
            0 => {
                if r < size / 2 {
                    1.0
                } else {
                    0.1
                }
            }
            1 => 0.1,
            _ => {
                if c < size / 2 {
                    1.0
                } else {
                    0.1
                }
            }
        },
    ));
    let img = preview(&rec, 320, 240);
    keep("preview-orientation.png", &img);
    // Centroids of red-dominated vs the other object pixels, and of blue ones.
    let mut sums = [[0.0f64; 3]; 4]; // [red, not red, blue, not blue] → (x, y, count)
    for (x, y, p) in img.enumerate_pixels() {
        if *p == BACKGROUND {
            continue;
        }
        let red = p[0] > p[1] + 10 && p[0] >= p[2] / 2;
        let blue = p[2] > p[1] + 10 && p[2] >= p[0] / 2;
        for (k, on) in [(0, red), (1, !red), (2, blue), (3, !blue)] {
            if on {
                sums[k][0] += f64::from(x);
                sums[k][1] += f64::from(y);
                sums[k][2] += 1.0;
            }
        }
    }
    let centroid = |k: usize| (sums[k][0] / sums[k][2], sums[k][1] / sums[k][2]);
    assert!(
        centroid(0).1 < centroid(1).1 - 20.0,
        "top of the object is not at the top"
    );
    assert!(
        centroid(2).0 < centroid(3).0 - 20.0,
        "left of the object is not on the left"
    );
}

#[test]
fn preview_without_a_mask_is_background() {
    let img = preview(&reconstruction(30, 20, |_, _| None), 64, 48);
    assert_eq!(img.dimensions(), (64, 48));
    assert!(img.pixels().all(|p| *p == BACKGROUND));
}
