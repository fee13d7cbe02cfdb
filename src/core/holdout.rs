//! A quality measure that needs no ground truth: reconstruct from part of the lights and
//! see how well the result predicts the images it was not given. The lights are split
//! into folds (every k-th light); each fold is left out in turn, the rest solved, and the
//! left-out images predicted from the normals and albedo (the Lambertian model, or the
//! lobe model where the `glossy` solver kept it). A user can see which solver explains
//! their capture best, on their own capture.
//!
//! A left-out light's intensity is a property of the light, not of the surface, and no
//! reconstruction from the other images can know it: where the table gives none (1 is
//! assumed) a real light's deviation from it would be the same error for every solver,
//! and on a real capture it dominates the score. So each left-out image's intensity is
//! fitted (one scale, the median ratio of observed to predicted) before it is scored;
//! the score as the table says is reported beside it.
//!
//! It reads the set band by band, as a job does, and holds one fold's maps at a time: an
//! error `|s·p − o| / o` is `|s / r − 1|` with `r = o / p`, so a histogram of each image's
//! ratios is all the scoring keeps.

use ndarray::{Array2, Array3};

use super::bands::{Band, Samples, SetInfo, Stack, each_band};
use super::error::InputError;
use super::error::RunError;
use super::lights::Light;
use super::mask;
use super::options::Options;
use super::progress::Halt;
use super::reconstruction::{Gloss, HoldoutScore};
use super::reflectance::{Facets, Fitted};
use super::solve;

/// Folds the lights are split into (each left out once).
pub const FOLDS: usize = 4;
/// Fewest images a holdout score is computed from: every fold leaves out at least two,
/// and each reconstruction keeps at least six.
pub const MIN_IMAGES: usize = 2 * FOLDS;
/// Observations at or above this are clipped, and below this (black level removed) in
/// shadow or too dark for a relative error to mean anything: both are left out.
const CLIPPED: f64 = 0.995;
const DARK: f64 = 0.02;

/// Refuses a holdout score of a set of `count` images, too few to leave some out (a job
/// is refused at its submission, before its 202).
pub fn check_count(count: usize) -> Result<(), InputError> {
    if count < MIN_IMAGES {
        return Err(InputError::Options(format!(
            "holdout_lights needs at least {MIN_IMAGES} images (each quarter of the lights \
             is left out in turn); this set has {count}"
        )));
    }
    Ok(())
}

/// Score `opts`' solver on `stack` by leaving out each of [`FOLDS`] folds of its lights
/// in turn (every 4th light from the fold's index), the lights' intensities the table's.
/// Needs [`MIN_IMAGES`] images. Once `halt` says stop, returns what was scored so far.
pub fn holdout(
    stack: &mut dyn Stack,
    opts: &Options,
    halt: Halt,
) -> Result<HoldoutScore, RunError> {
    let count = stack.info().lights.len();
    check_count(count)?;
    let mut ratios: Vec<Ratios> = (0..count).map(|_| Ratios::new()).collect();
    for fold in 0..FOLDS {
        let (kept, left): (Vec<usize>, Vec<usize>) = (0..count).partition(|k| k % FOLDS != fold);
        let model = Model::solve(stack, &kept, opts, halt)?;
        let lights = stack.info().lights.clone();
        each_band(stack, halt, |rows, band| {
            for &k in &left {
                model.add_band(&band, k, &lights[k], rows.start, &mut ratios[k]);
            }
        })?;
    }
    Ok(score(&ratios))
}

/// One fold's reconstruction: what the prediction needs of it.
struct Model {
    normals: Array3<f32>,
    albedo: Array2<f32>,
    gloss: Option<Gloss>,
    mask: Array2<bool>,
    black: f64,
}

impl Model {
    /// Solve `stack` from its images `kept` alone, masked as a job masks.
    fn solve(
        stack: &mut dyn Stack,
        kept: &[usize],
        opts: &Options,
        halt: Halt,
    ) -> Result<Self, RunError> {
        let mut part = Subset::of(stack, kept);
        let lights = part.info.lights.clone();
        let surface = solve::solve(&mut part, &lights, opts.solver, halt)?;
        let mask = mask::build(opts.mask, &surface.albedo, part.info.mask.as_ref())?;
        Ok(Self {
            black: surface.estimate.map_or(0.0, |e| e.black_level as f64),
            normals: surface.normals,
            albedo: surface.albedo,
            gloss: surface.gloss,
            mask,
        })
    }

    /// Add the ratios of observed to predicted of image `k` (under `light`) over `band`'s
    /// rows, the first of which is image row `first`.
    fn add_band(&self, band: &Band<'_>, k: usize, light: &Light, first: usize, out: &mut Ratios) {
        let cols = self.mask.ncols();
        let plane = band.planes[k];
        for (i, values) in plane.chunks_exact(cols).enumerate() {
            let r = first + i;
            for (c, &v) in values.iter().enumerate() {
                if !self.mask[[r, c]] {
                    continue;
                }
                let raw = v as f64 / 65535.0;
                let observed = raw - self.black;
                if raw >= CLIPPED || observed < DARK {
                    continue;
                }
                let mut model = Fitted {
                    normal: [0, 1, 2].map(|i| self.normals[[r, c, i]] as f64),
                    diffuse: self.albedo[[r, c]].min(1.0) as f64,
                    specular: 0.0,
                    roughness: 1.0,
                    facets: Facets::Ggx,
                };
                if let Some(g) = self.gloss.as_ref().filter(|g| g.used[[r, c]]) {
                    model.specular = g.specular[[r, c]] as f64;
                    model.roughness = g.roughness[[r, c]] as f64;
                    if g.beckmann[[r, c]] {
                        model.facets = Facets::Beckmann;
                    }
                }
                out.add(model.predict(light.direction, light.intensity), observed);
            }
        }
    }
}

/// A set seen through some of its images: the solve of one fold.
struct Subset<'a> {
    inner: &'a mut dyn Stack,
    kept: Vec<usize>,
    info: SetInfo,
    samples: Samples,
}

impl<'a> Subset<'a> {
    fn of(inner: &'a mut dyn Stack, kept: &[usize]) -> Self {
        let all = inner.info();
        let info = SetInfo {
            lights: kept.iter().map(|&k| all.lights[k].clone()).collect(),
            // Colour moments sum over every image; the score is on luminance.
            colour: false,
            notes: Vec::new(),
            ..all.clone()
        };
        let samples = Samples {
            stride: inner.samples().stride,
            planes: kept
                .iter()
                .map(|&k| inner.samples().planes[k].clone())
                .collect(),
        };
        Self {
            inner,
            kept: kept.to_vec(),
            info,
            samples,
        }
    }
}

impl Stack for Subset<'_> {
    fn info(&self) -> &SetInfo {
        &self.info
    }

    fn samples(&self) -> &Samples {
        &self.samples
    }

    fn band_rows(&self) -> usize {
        self.inner.band_rows()
    }

    fn band(&mut self, rows: std::ops::Range<usize>) -> Result<Band<'_>, InputError> {
        let band = self.inner.band(rows)?;
        Ok(Band {
            planes: self.kept.iter().map(|&k| band.planes[k]).collect(),
            moments: None,
        })
    }

    fn rewind(&mut self) {
        self.inner.rewind();
    }
}

/// Ratios kept to this precision (of ln r) over [`LOW`, `HIGH`]; beyond, the tails are
/// counted with the sums that make their mean exact.
const STEP: f64 = 5e-4;
const LOW: f64 = 0.05;
const HIGH: f64 = 20.0;

/// One left-out image's ratios of observed to predicted: all of them, and those of the
/// pixels predicted clearly lit (the intensity scale is fitted on these).
struct Ratios {
    all: Vec<u32>,
    lit: Vec<u32>,
    /// Below LOW and above HIGH: counts and sums of 1/r.
    tails: [(u64, f64); 2],
    lit_tails: [u64; 2],
}

fn bins() -> usize {
    ((HIGH / LOW).ln() / STEP).ceil() as usize
}

/// The ratio at the centre of bin `i`.
fn centre(i: usize) -> f64 {
    LOW * ((i as f64 + 0.5) * STEP).exp()
}

impl Ratios {
    fn new() -> Self {
        Self {
            all: vec![0; bins()],
            lit: vec![0; bins()],
            tails: [(0, 0.0); 2],
            lit_tails: [0; 2],
        }
    }

    fn add(&mut self, predicted: f64, observed: f64) {
        let lit = predicted > DARK;
        let r = observed / predicted.max(1e-12);
        let tail = if r < LOW {
            Some(0)
        } else if r >= HIGH {
            Some(1)
        } else {
            None
        };
        match tail {
            Some(t) => {
                self.tails[t].0 += 1;
                self.tails[t].1 += 1.0 / r;
                self.lit_tails[t] += u64::from(lit);
            }
            None => {
                let i = (((r / LOW).ln() / STEP) as usize).min(self.all.len() - 1);
                self.all[i] += 1;
                self.lit[i] += u32::from(lit);
            }
        }
    }

    fn count(&self) -> u64 {
        self.all.iter().map(|&n| n as u64).sum::<u64>() + self.tails[0].0 + self.tails[1].0
    }

    /// The image's intensity relative to the table's: the median ratio over the pixels
    /// predicted clearly lit (1 when there are none).
    fn scale(&self) -> f64 {
        let lit =
            self.lit.iter().map(|&n| n as u64).sum::<u64>() + self.lit_tails[0] + self.lit_tails[1];
        if lit == 0 {
            return 1.0;
        }
        let mut rank = lit / 2;
        if rank < self.lit_tails[0] {
            return LOW;
        }
        rank -= self.lit_tails[0];
        for (i, &n) in self.lit.iter().enumerate() {
            if rank < n as u64 {
                return centre(i);
            }
            rank -= n as u64;
        }
        HIGH
    }
}

/// Errors are gathered to this precision up to [`MAX_ERROR`] for the median.
const ERROR_STEP: f64 = 1e-4;
const MAX_ERROR: f64 = 2.0;

/// The score over every image's ratios, each under its fitted scale and under 1.
fn score(images: &[Ratios]) -> HoldoutScore {
    let observations: u64 = images.iter().map(Ratios::count).sum();
    let scales: Vec<f64> = images.iter().map(Ratios::scale).collect();
    let fitted = errors(images, &scales);
    let table = errors(images, &vec![1.0; images.len()]);
    HoldoutScore {
        median_relative: fitted.median(observations),
        mean_relative: fitted.sum / observations.max(1) as f64,
        median_relative_table: table.median(observations),
        observations,
    }
}

/// A histogram of relative errors and their exact sum.
struct Errors {
    counts: Vec<u64>,
    sum: f64,
}

impl Errors {
    fn median(&self, total: u64) -> f64 {
        if total == 0 {
            return f64::NAN;
        }
        let mut rank = total / 2;
        for (i, &n) in self.counts.iter().enumerate() {
            if rank < n {
                return (i as f64 + 0.5) * ERROR_STEP;
            }
            rank -= n;
        }
        MAX_ERROR
    }
}

/// The errors `|s / r − 1|` of every image's ratios, each image under its scale `s`.
fn errors(images: &[Ratios], scales: &[f64]) -> Errors {
    let slots = (MAX_ERROR / ERROR_STEP) as usize;
    let mut out = Errors {
        counts: vec![0; slots + 1],
        sum: 0.0,
    };
    for (image, &s) in images.iter().zip(scales) {
        for (i, &n) in image.all.iter().enumerate().filter(|(_, n)| **n > 0) {
            let e = (s / centre(i) - 1.0).abs();
            out.counts[((e / ERROR_STEP) as usize).min(slots)] += n as u64;
            out.sum += n as f64 * e;
        }
        // Below LOW, s/r > 1 (s ≥ LOW): the error is s/r − 1; above HIGH, 1 − s/r.
        let [(low, low_inv), (high, high_inv)] = image.tails;
        out.counts[slots] += low;
        out.sum += s * low_inv - low as f64;
        let high_error = high as f64 - s * high_inv;
        out.sum += high_error;
        if high > 0 {
            let e = (high_error / high as f64).max(0.0);
            out.counts[((e / ERROR_STEP) as usize).min(slots)] += high;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The histogram's median and mean match the exact ones, the fitted scale the
    /// image's true intensity.
    #[test]
    fn binned_scores_match_exact_ones() {
        let mut image = Ratios::new();
        let mut exact = Vec::new();
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        // An image 7 % brighter than the table says, with 2 % noise and a few outliers.
        for i in 0..20_000 {
            let predicted = 0.05 + 0.9 * next();
            let noise = 1.0 + 0.04 * (next() - 0.5);
            let observed = match i % 100 {
                0 => predicted * 30.0,
                1 => predicted * 0.01,
                _ => 1.07 * predicted * noise,
            };
            image.add(predicted, observed);
            exact.push((predicted, observed));
        }
        let s = image.scale();
        assert!((s - 1.07).abs() < 0.002, "scale {s}");
        let score = score(&[image]);
        let mut e: Vec<f64> = exact.iter().map(|(p, o)| (s * p - o).abs() / o).collect();
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        e.sort_by(f64::total_cmp);
        let median = e[e.len() / 2];
        assert!(
            (score.median_relative - median).abs() < 3e-4,
            "{score:?} vs {median}"
        );
        assert!(
            (score.mean_relative - mean).abs() < 1e-3 * mean.max(1.0),
            "{score:?} vs {mean}"
        );
        assert!(score.median_relative_table > 0.05, "{score:?}");
        assert_eq!(score.observations, 20_000);
    }
}
