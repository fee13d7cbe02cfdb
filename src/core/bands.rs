//! The solve's view of an image set: what it is (size, depth, lights, mask), the rows the
//! robust pre-pass samples, and bands of rows read top to bottom in lockstep over the
//! images. A set behind a [`Stack`] need not be in memory whole: `stream` reads its files
//! band by band; an [`ImageSet`] already in memory serves itself as one band. A band's
//! solve fills the same rows of the output maps ([`SurfaceRows`]).

use std::borrow::Borrow;
use std::ops::Range;

use ndarray::{Array2, ArrayViewMut2, ArrayViewMut3};

use super::error::InputError;
use super::intake::ImageSet;
use super::lights::Light;

/// What the stages after the solve need to know about a set.
#[derive(Debug, Clone)]
pub struct SetInfo {
    pub width: usize,
    pub height: usize,
    /// Bits per sample of the source images (8 or 16).
    pub bit_depth: u8,
    /// One light per image, same order.
    pub lights: Vec<Light>,
    /// True when every image carries colour: bands then bring colour moments.
    pub colour: bool,
    /// The caller's mask (true = object), if any.
    pub mask: Option<Array2<bool>>,
    pub mask_file: Option<String>,
    /// What intake ignored or chose on the caller's behalf (for `result.json`).
    pub notes: Vec<String>,
}

/// Rows `first..first + count` of every image, and their colour moments.
pub struct Band<'a> {
    /// Per image (table order): `count × width` luminance values, row-major.
    pub planes: Vec<&'a [u16]>,
    /// For colour sets: Σᵢ lᵢ·Iᵢ,c per pixel, `count × width × 9` (channel × 3 + axis).
    pub moments: Option<&'a [f32]>,
}

/// The rows the robust pre-pass fits, of every image: rows and columns
/// `stride/2, stride/2 + stride, …` with the stride [`sample_stride`] gives.
#[derive(Debug, Clone)]
pub struct Samples {
    pub stride: usize,
    /// Per image (table order): the sampled rows, each `width` long, top to bottom.
    pub planes: Vec<Vec<u16>>,
}

/// Pixels the pre-pass samples: enough for stable medians, a small cost next to the solve.
const SAMPLE_PIXELS: f64 = 12_000.0;

/// The sampling stride for a `width × height` set: about [`SAMPLE_PIXELS`] pixels.
pub fn sample_stride(width: usize, height: usize) -> usize {
    ((((width * height) as f64 / SAMPLE_PIXELS).sqrt().ceil()) as usize).max(1)
}

/// The rows [`Samples`] holds, in order.
pub fn sampled_rows(width: usize, height: usize) -> impl Iterator<Item = usize> {
    let stride = sample_stride(width, height);
    (stride / 2..height).step_by(stride)
}

/// An image set the solve reads in bands.
pub trait Stack: Send {
    fn info(&self) -> &SetInfo;
    fn samples(&self) -> &Samples;
    /// Rows per band this stack is best read in (bounding what one band holds).
    fn band_rows(&self) -> usize;
    /// The next band; bands must be asked for in order, each starting where the last ended.
    fn band(&mut self, rows: Range<usize>) -> Result<Band<'_>, InputError>;
    /// Start again at row 0, for a solve that passes over the set more than once.
    fn rewind(&mut self);
}

/// Every band of `stack` from its first row, in order, each handed to `each` with its
/// rows; once `halt` says stop, the rest are not read.
pub fn each_band(
    stack: &mut dyn Stack,
    halt: &(dyn Fn() -> bool + Sync),
    mut each: impl FnMut(Range<usize>, Band<'_>),
) -> Result<(), InputError> {
    let height = stack.info().height;
    let step = stack.band_rows().max(1);
    stack.rewind();
    for r0 in (0..height).step_by(step) {
        if halt() {
            break;
        }
        let rows = r0..(r0 + step).min(height);
        each(rows.clone(), stack.band(rows)?);
    }
    Ok(())
}

/// An [`ImageSet`] in memory (owned or borrowed) as a [`Stack`]: one band, the whole set.
pub struct InMemory<S> {
    set: S,
    info: SetInfo,
    samples: Samples,
    /// Planes not in standard layout, copied once.
    owned: Vec<Option<Array2<u16>>>,
}

impl<S: Borrow<ImageSet>> InMemory<S> {
    pub fn new(owner: S) -> Self {
        let set = owner.borrow();
        let info = SetInfo {
            width: set.width,
            height: set.height,
            bit_depth: set.bit_depth,
            lights: set.lights.clone(),
            colour: set.colour_moments.is_some(),
            mask: set.mask.clone(),
            mask_file: set.mask_file.clone(),
            notes: set.notes.clone(),
        };
        let samples = Samples {
            stride: sample_stride(set.width, set.height),
            planes: (set.planes.iter())
                .map(|p| {
                    sampled_rows(set.width, set.height)
                        .flat_map(|r| p.row(r).to_vec())
                        .collect()
                })
                .collect(),
        };
        let owned = (set.planes.iter())
            .map(|p| (!p.is_standard_layout()).then(|| p.as_standard_layout().into_owned()))
            .collect();
        Self {
            set: owner,
            info,
            samples,
            owned,
        }
    }
}

impl<S: Borrow<ImageSet> + Send> Stack for InMemory<S> {
    fn info(&self) -> &SetInfo {
        &self.info
    }

    fn samples(&self) -> &Samples {
        &self.samples
    }

    fn band_rows(&self) -> usize {
        self.info.height.max(1)
    }

    fn band(&mut self, rows: Range<usize>) -> Result<Band<'_>, InputError> {
        let set = self.set.borrow();
        let w = set.width;
        let span = rows.start * w..rows.end * w;
        let planes = (set.planes.iter().zip(&self.owned))
            .map(|(p, o)| {
                let all = o.as_ref().unwrap_or(p);
                &all.as_slice().expect("standard layout is contiguous")[span.clone()]
            })
            .collect();
        let moments = (set.colour_moments.as_ref())
            .and_then(|m| m.as_slice())
            .map(|m| &m[span.start * 9..span.end * 9]);
        Ok(Band { planes, moments })
    }

    fn rewind(&mut self) {}
}

/// Some rows of the solve's per-pixel maps (its `Surface`), for a
/// band's solve to fill.
pub struct SurfaceRows<'a> {
    pub albedo: ArrayViewMut2<'a, f32>,
    pub normals: ArrayViewMut3<'a, f32>,
    pub residual: ArrayViewMut2<'a, f32>,
    pub confidence: ArrayViewMut2<'a, f32>,
    pub inliers: ArrayViewMut2<'a, u16>,
    pub unreliable: ArrayViewMut2<'a, bool>,
}
