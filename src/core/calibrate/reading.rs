//! Reading the sphere images within a fixed memory budget, whatever their number.
//!
//! A pass reads every image of a [`Source`] once, at most [`READERS`] at a time, and
//! keeps only what is asked of it: a downscaled copy (box averages, the whole set's copies
//! within [`COARSE_BYTES`], each at most [`FIT_PIXELS`]), the full-resolution pixels of
//! some windows (the balls' boxes: all images' windows in memory within [`CROP_BYTES`],
//! else in an unlinked scratch file read back by bands), each image's brightest value,
//! and the per-pixel maximum as the overlay shows it (1 byte a pixel).
//!
//! The calibration's memory is then these budgets, a few full-resolution maps of one
//! window (the environment, the recurrence, the smoothed outline), and per reading thread
//! one image being decoded or searched: [`peak_bytes`].

use std::borrow::Cow;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use ndarray::{Array2, ArrayView2, s};

use super::circle::Circle;
use super::environment;
use super::error::CalibrationError;
use super::source::Source;
use crate::core::error::InputError;

/// The downscaled copies of a whole set, bytes.
pub const COARSE_BYTES: usize = 64 << 20;
/// Most pixels of one downscaled copy (what the outline fit searches; the fit holds about
/// 60 bytes a pixel).
pub const FIT_PIXELS: usize = 2 << 20;
/// The balls' windows of a whole set held in memory, bytes; past it they are spilled.
pub const CROP_BYTES: usize = 128 << 20;
/// One band of spilled windows over all images, bytes.
const SPILL_BAND_BYTES: usize = 32 << 20;
/// Images read (decoded, or searched for their highlight) at once.
pub const READERS: usize = 2;
/// What one reading thread may hold per pixel of an image: a whole decode (formats other
/// than PNG; up to 8 bytes for 16-bit RGBA, with the decoder's own scratch), or one
/// window's search at its worst, a highlight as large as the ball (its plane read back
/// from a spill 2, the blobs' labels 4, the core's labels 4 and pixels 8).
const READER_BYTES_PER_PIXEL: u64 = 18;
/// Full-resolution maps held beside them: the environment (2 bytes), the recurrence (2),
/// the smoothed image the outline is refined on (4), the ambient image's window (2), the
/// overlay (1), a given sphere mask (1).
const MAPS_BYTES_PER_PIXEL: u64 = 12;
/// Allocator slack, the decoder's buffers, the pictures' encoding.
const SLACK_BYTES: u64 = 64 << 20;

/// The most one calibration (or one matte fit) holds, bytes, for images of at most
/// `max_pixels` pixels, whatever their number: the budgets above, the full-resolution maps
/// of one window, and [`READERS`] images being read.
pub fn peak_bytes(max_pixels: u64) -> u64 {
    (COARSE_BYTES + CROP_BYTES + SPILL_BAND_BYTES) as u64
        + SLACK_BYTES
        + max_pixels * (MAPS_BYTES_PER_PIXEL + READERS as u64 * READER_BYTES_PER_PIXEL)
}

/// A rectangle of the image: `h` rows from `r0`, `w` columns from `c0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    pub r0: usize,
    pub c0: usize,
    pub h: usize,
    pub w: usize,
}

impl Window {
    /// The circle's box widened by `margin` on every side, within a `w` × `h` image.
    pub fn around(c: &Circle, margin: f64, (w, h): (usize, usize)) -> Self {
        let lo = |v: f64| (v - margin).floor().max(0.0) as usize;
        let hi = |v: f64, n: usize| ((v + margin).ceil().max(0.0) as usize).min(n - 1);
        let (r0, c0) = (lo(c.cy - c.r).min(h - 1), lo(c.cx - c.r).min(w - 1));
        let (r1, c1) = (hi(c.cy + c.r, h).max(r0), hi(c.cx + c.r, w).max(c0));
        Self {
            r0,
            c0,
            h: r1 - r0 + 1,
            w: c1 - c0 + 1,
        }
    }

    pub fn pixels(&self) -> usize {
        self.h * self.w
    }

    /// `c` in the window's coordinates.
    pub fn local(&self, c: &Circle) -> Circle {
        Circle {
            cx: c.cx - self.c0 as f64,
            cy: c.cy - self.r0 as f64,
            r: c.r,
        }
    }

    /// Whether the circle's box (within the image) lies inside the window.
    pub fn holds(&self, c: &Circle, (w, h): (usize, usize)) -> bool {
        let b = Self::around(c, 0.0, (w, h));
        b.r0 >= self.r0
            && b.c0 >= self.c0
            && b.r0 + b.h <= self.r0 + self.h
            && b.c0 + b.w <= self.c0 + self.w
    }
}

/// What a pass keeps of each image.
pub struct Plan<'a> {
    /// Downscaling factor of the copies (None: no copies).
    pub factor: Option<usize>,
    pub windows: &'a [Window],
    /// Whether to keep the overlay's maximum.
    pub overlay: bool,
    pub scratch: &'a Path,
    /// The windows of all images held in memory up to this many bytes; past it, spilled.
    pub crop_bytes: usize,
}

/// What a pass kept.
pub struct Pass {
    /// Per image, its downscaled copy.
    pub coarse: Vec<Array2<u16>>,
    /// Per window, every image's pixels in it.
    pub windows: Vec<Windows>,
    /// Per image, its brightest value.
    pub maxima: Vec<u16>,
    /// Per pixel, the brightest value of the set as the overlay shows it.
    pub overlay: Option<Array2<u8>>,
}

/// The downscaling factor for `count` images of `w` × `h`: the smallest that keeps the
/// set's copies within `coarse_bytes` (e.g. [`COARSE_BYTES`]) and one copy within
/// [`FIT_PIXELS`].
pub fn coarse_factor(count: usize, (w, h): (usize, usize), coarse_bytes: usize) -> usize {
    (1..)
        .find(|&f| {
            let px = h.div_ceil(f) * w.div_ceil(f);
            (px <= FIT_PIXELS && count.max(1) * px * 2 <= coarse_bytes) || f >= w.max(h)
        })
        .expect("a factor as large as the image fits")
}

/// Read every image of `src` once (all of size `dim`), keeping what `plan` asks.
pub fn read_all(
    src: &dyn Source,
    dim: (usize, usize),
    plan: &Plan,
) -> Result<Pass, CalibrationError> {
    let n = src.count();
    let (w, h) = dim;
    let in_memory = (plan.windows.iter().map(|w| w.pixels()).sum::<usize>()).saturating_mul(n * 2)
        <= plan.crop_bytes;
    // In memory: each image's windows, filled as it is read.
    let slots: Vec<Vec<Mutex<Array2<u16>>>> = plan
        .windows
        .iter()
        .map(|_| match in_memory {
            true => (0..n).map(|_| Mutex::new(Array2::zeros((0, 0)))).collect(),
            false => Vec::new(),
        })
        .collect();
    let windows: Vec<Windows> = plan
        .windows
        .iter()
        .map(|&win| {
            if in_memory {
                Ok(Windows::Memory(win, Vec::new()))
            } else {
                let file = tempfile::tempfile_in(plan.scratch).map_err(|e| {
                    InputError::io(plan.scratch, format!("a scratch file for the images: {e}"))
                })?;
                Ok(Windows::Spilled(win, n, file))
            }
        })
        .collect::<Result<_, CalibrationError>>()?;
    let overlay = plan
        .overlay
        .then(|| Mutex::new(Array2::<u8>::zeros((h, w))));
    let gamma: Vec<u8> = if plan.overlay {
        (0..=65535u32)
            .map(|v| ((v as f64 / 65535.0).sqrt() * 255.0) as u8)
            .collect()
    } else {
        Vec::new()
    };
    let read = |k: usize| -> Result<(Array2<u16>, u16), CalibrationError> {
        let mut max = 0u16;
        let f = plan.factor.unwrap_or(0);
        let mut coarse = match plan.factor {
            Some(f) => Array2::zeros((h.div_ceil(f), w.div_ceil(f))),
            None => Array2::zeros((0, 0)),
        };
        let mut shrink = Shrink::new(f, w);
        let mut mine: Vec<Array2<u16>> = windows
            .iter()
            .map(|ws| match ws {
                Windows::Memory(win, _) => Array2::zeros((win.h, win.w)),
                Windows::Spilled(..) => Array2::zeros((0, 0)),
            })
            .collect();
        let mut spill_error = None;
        let mut rows = 0;
        src.read(k, &mut |r0, band: ArrayView2<u16>| {
            if band.ncols() != w || r0 + band.nrows() > h {
                return;
            }
            rows = rows.max(r0 + band.nrows());
            max = max.max(band.iter().copied().max().unwrap_or(0));
            if let Some(o) = &overlay {
                let mut o = o.lock().expect("no reader panics holding it");
                for (i, row) in band.rows().into_iter().enumerate() {
                    for (m, &v) in o.row_mut(r0 + i).iter_mut().zip(row) {
                        *m = (*m).max(gamma[v as usize]);
                    }
                }
            }
            if f > 0 {
                for (i, row) in band.rows().into_iter().enumerate() {
                    shrink.row(r0 + i, row, &mut coarse);
                }
            }
            for (ws, dst) in windows.iter().zip(&mut mine) {
                let win = ws.window();
                let (a, b) = (r0.max(win.r0), (r0 + band.nrows()).min(win.r0 + win.h));
                if a >= b {
                    continue;
                }
                let part = band.slice(s![a - r0..b - r0, win.c0..win.c0 + win.w]);
                match ws {
                    Windows::Memory(..) => {
                        dst.slice_mut(s![a - win.r0..b - win.r0, ..]).assign(&part)
                    }
                    Windows::Spilled(_, _, file) => {
                        let bytes: Vec<u16> = part.iter().copied().collect();
                        let at = ((k * win.pixels() + (a - win.r0) * win.w) * 2) as u64;
                        if let Err(e) = file.write_all_at(bytemuck::cast_slice(&bytes), at) {
                            spill_error.get_or_insert(e);
                        }
                    }
                }
            }
        })?;
        if rows != h {
            return Err(CalibrationError::Image {
                name: src.name(k).to_string(),
                reason: format!("it decoded to other dimensions than its header's {w}×{h}"),
            });
        }
        if let Some(e) = spill_error {
            return Err(InputError::io(
                plan.scratch,
                format!("writing {:?}'s pixels to a scratch file: {e}", src.name(k)),
            )
            .into());
        }
        if f > 0 {
            shrink.flush(&mut coarse);
        }
        for (slot, plane) in slots.iter().zip(mine) {
            if in_memory {
                *slot[k].lock().expect("no reader panics holding it") = plane;
            }
        }
        Ok((coarse, max))
    };
    let done = bounded(n, read)?;
    let (coarse, maxima) = done.into_iter().unzip();
    let windows = windows
        .into_iter()
        .zip(slots)
        .map(|(ws, slot)| match ws {
            Windows::Memory(win, _) => Windows::Memory(
                win,
                slot.into_iter()
                    .map(|m| m.into_inner().expect("no reader panicked"))
                    .collect(),
            ),
            spilled => spilled,
        })
        .collect();
    Ok(Pass {
        coarse,
        windows,
        maxima,
        overlay: overlay.map(|o| o.into_inner().expect("no reader panicked")),
    })
}

/// Box averages of `f` × `f` pixels, fed a row at a time.
struct Shrink {
    f: usize,
    w: usize,
    sums: Vec<u32>,
    rows: usize,
    at: usize,
}

impl Shrink {
    fn new(f: usize, w: usize) -> Self {
        Self {
            f,
            w,
            sums: vec![0; if f > 0 { w.div_ceil(f) } else { 0 }],
            rows: 0,
            at: 0,
        }
    }

    fn row(&mut self, r: usize, row: ndarray::ArrayView1<u16>, out: &mut Array2<u16>) {
        if r / self.f != self.at {
            self.flush(out);
            self.at = r / self.f;
        }
        match row.as_slice() {
            Some(row) => {
                for (s, cols) in self.sums.iter_mut().zip(row.chunks(self.f)) {
                    *s += cols.iter().map(|&v| v as u32).sum::<u32>();
                }
            }
            None => {
                for (c, &v) in row.iter().enumerate() {
                    self.sums[c / self.f] += v as u32;
                }
            }
        }
        self.rows += 1;
    }

    fn flush(&mut self, out: &mut Array2<u16>) {
        if self.rows == 0 {
            return;
        }
        for (cc, s) in self.sums.iter_mut().enumerate() {
            let cols = self.f.min(self.w - cc * self.f);
            let n = (cols * self.rows) as u32;
            out[[self.at, cc]] = ((*s + n / 2) / n) as u16;
            *s = 0;
        }
        self.rows = 0;
    }
}

/// Every image's pixels in one window.
pub enum Windows {
    Memory(Window, Vec<Array2<u16>>),
    /// In an unlinked scratch file: image k's window at k × its size, row after row.
    Spilled(Window, usize, File),
}

impl Windows {
    pub fn window(&self) -> Window {
        match self {
            Self::Memory(w, _) | Self::Spilled(w, ..) => *w,
        }
    }

    pub fn count(&self) -> usize {
        match self {
            Self::Memory(_, v) => v.len(),
            Self::Spilled(_, n, _) => *n,
        }
    }

    /// Image `k`'s window (read back, when spilled).
    pub fn image(&self, k: usize) -> Result<Cow<'_, Array2<u16>>, CalibrationError> {
        match self {
            Self::Memory(_, v) => Ok(Cow::Borrowed(&v[k])),
            Self::Spilled(win, _, file) => Ok(Cow::Owned(read_rows(file, win, k, 0..win.h)?)),
        }
    }

    /// The environment over the window: the per-pixel median of the images, raised to
    /// `ambient` (its window) where that is brighter; spilled windows a band at a time.
    pub fn median(&self, ambient: Option<&Array2<u16>>) -> Result<Array2<u16>, CalibrationError> {
        match self {
            Self::Memory(_, v) => {
                let refs: Vec<&Array2<u16>> = v.iter().collect();
                Ok(environment::estimate(&refs, ambient))
            }
            Self::Spilled(win, n, file) => {
                let mut env = Array2::zeros((win.h, win.w));
                let band = (SPILL_BAND_BYTES / (n * win.w * 2).max(1)).clamp(1, win.h);
                let mut r = 0;
                while r < win.h {
                    let end = (r + band).min(win.h);
                    use rayon::prelude::*;
                    let planes: Vec<Array2<u16>> = (0..*n)
                        .into_par_iter()
                        .map(|k| read_rows(file, win, k, r..end))
                        .collect::<Result<_, _>>()?;
                    let refs: Vec<&Array2<u16>> = planes.iter().collect();
                    let amb = ambient.map(|a| a.slice(s![r..end, ..]).to_owned());
                    env.slice_mut(s![r..end, ..])
                        .assign(&environment::estimate(&refs, amb.as_ref()));
                    r = end;
                }
                Ok(env)
            }
        }
    }
}

/// Rows `rows` of image `k`'s spilled window.
fn read_rows(
    file: &File,
    win: &Window,
    k: usize,
    rows: std::ops::Range<usize>,
) -> Result<Array2<u16>, CalibrationError> {
    let mut v = vec![0u16; rows.len() * win.w];
    let at = ((k * win.pixels() + rows.start * win.w) * 2) as u64;
    file.read_exact_at(bytemuck::cast_slice_mut(&mut v), at)
        .map_err(|e| InputError::Decode {
            name: "the sphere images".into(),
            reason: format!("reading their pixels back from the scratch file: {e}"),
        })?;
    Ok(Array2::from_shape_vec((rows.len(), win.w), v).expect("rows of the window's width"))
}

/// `f(k)` for every k in 0..n, at most [`READERS`] at once on rayon's pool, in order; the
/// first error in index order among those run (none is started after one).
pub fn bounded<T: Send>(
    n: usize,
    f: impl Fn(usize) -> Result<T, CalibrationError> + Sync,
) -> Result<Vec<T>, CalibrationError> {
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let out: Vec<Mutex<Option<Result<T, CalibrationError>>>> =
        (0..n).map(|_| Mutex::new(None)).collect();
    let work = || {
        loop {
            if failed.load(Ordering::Relaxed) {
                break;
            }
            let k = next.fetch_add(1, Ordering::Relaxed);
            if k >= n {
                break;
            }
            let r = f(k);
            if r.is_err() {
                failed.store(true, Ordering::Relaxed);
            }
            *out[k].lock().expect("slots are set once") = Some(r);
        }
    };
    rayon::scope(|s| {
        for _ in 1..READERS.min(rayon::current_num_threads()).max(1) {
            s.spawn(|_| work());
        }
        work();
    });
    let mut done = Vec::with_capacity(n);
    for slot in out {
        match slot.into_inner().expect("slots are set once") {
            Some(Ok(v)) => done.push(v),
            Some(Err(e)) => return Err(e),
            None => {}
        }
    }
    if done.len() < n {
        return Err(CalibrationError::Names("reading stopped early".into()));
    }
    Ok(done)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Box averages of a 7 × 11 image by 3 (ragged last row and column), fed contiguous
    /// rows and strided ones, against the means computed directly.
    #[test]
    fn shrink_is_the_rounded_mean_of_each_box() {
        let img = Array2::from_shape_fn((7, 11), |(r, c)| (r * 997 + c * 131) as u16 * 7);
        let f = 3;
        let expected = Array2::from_shape_fn((3, 4), |(i, j)| {
            let cells: Vec<u32> = (i * f..(i * f + f).min(7))
                .flat_map(|r| (j * f..(j * f + f).min(11)).map(move |c| (r, c)))
                .map(|(r, c)| img[[r, c]] as u32)
                .collect();
            let n = cells.len() as u32;
            ((cells.iter().sum::<u32>() + n / 2) / n) as u16
        });
        let transposed = Array2::from_shape_fn((11, 7), |(c, r)| img[[r, c]]);
        for strided in [false, true] {
            let mut out = Array2::zeros((3, 4));
            let mut shrink = Shrink::new(f, 11);
            for r in 0..7 {
                let row = match strided {
                    false => img.row(r),
                    true => transposed.column(r),
                };
                assert_eq!(row.as_slice().is_none(), strided);
                shrink.row(r, row, &mut out);
            }
            shrink.flush(&mut out);
            assert_eq!(out, expected, "strided rows: {strided}");
        }
    }
}
