//! `bench --integrators`: the integrators alone, timed on normal maps. Two tables:
//!
//! - At each of `--sizes`: the rendered `sphere-in-front` scene (`synth::sphere_in_front`:
//!   a sphere standing in front of a steep plane, seen through a pinhole camera) integrated
//!   by each method into perspective depth (log-depth gradients, then `depth_from_log`),
//!   and by `robust-poisson` orthographically (its heights' gradients) as the reference
//!   every ratio is taken against: issue 42's "perspective default within 1.5 × today's
//!   orthographic `robust-poisson`".
//! - With `--normal-maps <dir>`: each sub-folder holding `normal_map.png`, `mask.png` and
//!   `K.txt` (the layout of DiLiGenT's objects in `../shared/real/normals`), read in the
//!   benchmark convention and integrated perspective by each method; the mean over them.
//!
//! Each figure is the median of `--runs` runs; the methods take turns within a run, so that
//! a change in the machine's load hits them alike.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use ndarray::{Array2, Array3};

use photostereo::core::camera::Pinhole;
use photostereo::core::intake::Limits;
use photostereo::core::integrate::{self, perspective};
use photostereo::core::normalmap::{self, Convention, Lens};
use photostereo::core::options::Integration;
use photostereo::core::progress::NEVER;
use photostereo::core::synth;

use super::stats::median;

/// The methods timed, the default first.
pub(super) const METHODS: [Integration; 3] = [
    Integration::RobustPoisson,
    Integration::Poisson,
    Integration::Bilateral,
];

/// Normals to integrate: perspective under `camera`, or orthographic without one.
struct Map {
    name: String,
    normals: Array3<f32>,
    mask: Array2<bool>,
    camera: Option<Pinhole>,
}

impl Map {
    /// Seconds `method` takes to turn the normals into heights, or into depth under the
    /// camera.
    fn time(&self, method: Integration) -> f64 {
        let start = Instant::now();
        let z = match &self.camera {
            Some(k) => {
                let zeta = integrate::integrate_log_depth(
                    &self.normals,
                    &self.mask,
                    k,
                    method,
                    None,
                    Default::default(),
                    NEVER,
                )
                .zeta;
                perspective::depth_from_log(&zeta, &self.mask, k, None)
            }
            None => {
                let (p, q) = integrate::gradients(&self.normals, &self.mask);
                integrate::integrate(&p, &q, &self.mask, method)
            }
        };
        let secs = start.elapsed().as_secs_f64();
        drop(z);
        secs
    }
}

/// One table row: what was integrated, its size, and per method of [`METHODS`] the
/// median seconds; `reference` the orthographic `robust-poisson` seconds, if timed.
pub(super) struct Row {
    pub name: String,
    pub size: (usize, usize),
    pub seconds: Vec<f64>,
    pub reference: Option<f64>,
}

/// The rendered scene at each size (with the orthographic reference) and the maps under
/// `maps`, if given.
pub(super) fn run(
    sizes: &[usize],
    runs: usize,
    maps: Option<&Path>,
) -> anyhow::Result<(Vec<Row>, Vec<Row>)> {
    let mut rendered = Vec::new();
    for &size in sizes {
        let scene = synth::sphere_in_front(size);
        let perspective = Map {
            name: scene.name.to_string(),
            normals: scene.normals,
            mask: scene.mask,
            camera: scene.camera,
        };
        let flat = Map {
            name: String::new(),
            normals: perspective.normals.clone(),
            mask: perspective.mask.clone(),
            camera: None,
        };
        let mut reference = Vec::new();
        let mut seconds = vec![Vec::new(); METHODS.len()];
        for _ in 0..runs {
            reference.push(flat.time(Integration::RobustPoisson));
            for (m, method) in METHODS.iter().enumerate() {
                seconds[m].push(perspective.time(*method));
            }
        }
        rendered.push(Row {
            name: perspective.name.clone(),
            size: (size, size),
            seconds: seconds.iter().map(|s| mid(s)).collect(),
            reference: Some(mid(&reference)),
        });
    }
    let real = match maps {
        Some(dir) => real_maps(dir)?
            .iter()
            .map(|map| {
                let mut seconds = vec![Vec::new(); METHODS.len()];
                for _ in 0..runs {
                    for (m, method) in METHODS.iter().enumerate() {
                        seconds[m].push(map.time(*method));
                    }
                }
                Row {
                    name: map.name.clone(),
                    size: (map.mask.ncols(), map.mask.nrows()),
                    seconds: seconds.iter().map(|s| mid(s)).collect(),
                    reference: None,
                }
            })
            .collect(),
        None => Vec::new(),
    };
    Ok((rendered, real))
}

/// The median of one method's runs (`--runs` is at least 1).
fn mid(runs: &[f64]) -> f64 {
    median(runs).unwrap_or(f64::NAN)
}

/// The sub-folders of `dir` with a `normal_map.png`, `mask.png` and `K.txt`, read.
fn real_maps(dir: &Path) -> anyhow::Result<Vec<Map>> {
    let mut folders: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("--normal-maps {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            ["normal_map.png", "mask.png", "K.txt"]
                .iter()
                .all(|f| p.join(f).is_file())
        })
        .collect();
    folders.sort();
    anyhow::ensure!(
        !folders.is_empty(),
        "--normal-maps {}: no sub-folder holds normal_map.png, mask.png and K.txt",
        dir.display()
    );
    folders
        .iter()
        .map(|folder| {
            let camera = Pinhole::read(&folder.join("K.txt"))?;
            let map = normalmap::read(
                &folder.join("normal_map.png"),
                Some(&folder.join("mask.png")),
                Convention::Opengl,
                Some(Lens::Pinhole(camera)),
                &Limits::default(),
            )?;
            Ok(Map {
                name: folder
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into(),
                normals: map.normals,
                mask: map.mask,
                camera: map.camera,
            })
        })
        .collect()
}
