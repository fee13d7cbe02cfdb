//! The operators the multigrid works on: a weighted 4-neighbour graph Laplacian as a
//! [`Stencil`] (row kernels for the sweeps), with unit weights on a mask
//! ([`MaskStencil`], the plain Poisson integrator) or given edge weights
//! ([`WeightStencil`], every coarse level and the weighted integrators), and the edge
//! weights made from per-pixel confidences.

use rayon::prelude::*;

/// Edge bits of a mask pixel: its east / west / south / north neighbour is on the mask.
const EAST: u8 = 1;
const WEST: u8 = 2;
const SOUTH: u8 = 4;
const NORTH: u8 = 8;

/// Lower bound of an edge weight in [`crate::core::integrate::integrate_weighted`]:
/// zero-confidence pixels stay connected (so the answer is well defined) but barely
/// constrain the surface.
pub const MIN_EDGE_WEIGHT: f32 = 1e-3;

/// A weighted 4-neighbour graph Laplacian on an `h × w` grid.
pub(crate) trait Stencil: Sync {
    fn dims(&self) -> (usize, usize);
    /// Edge weights `[east, west, south, north]` of cell `(r, c)`; 0 where there is no edge
    /// (in particular at the frame border). For set-up code, not for sweeps.
    fn weights(&self, r: usize, c: usize) -> [f32; 4];
    /// Weights of the east and south edges of every cell of row `r`.
    fn edge_row(&self, r: usize, east: &mut [f32], south: &mut [f32]);
    /// `out[c] = Σ_j w_ij x_j` on row `r`, given rows `r − 1`, `r`, `r + 1` of `x` (`up` /
    /// `down` are zero rows outside the grid). `x` must be 0 on inactive cells.
    fn neighbour_sum(&self, r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]);
    /// The diagonal `d_c = Σ_j w_ij` of row `r` (0 exactly on inactive cells) and its
    /// inverse on active cells (0 on inactive ones).
    fn diag_row(&self, r: usize, d: &mut [f32], inv: &mut [f32]);
    /// `out = A x` on row `r`, in the difference form `Σ_j w_ij (x_i − x_j)`: neighbouring
    /// heights are close, so their differences are exact in f32 and the small Laplacian of
    /// large smooth heights loses nothing to cancellation (`d x − Σ w x_j` would).
    fn apply_row(&self, r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]);
}

/// Unit weights between adjacent mask pixels: the plain Poisson integrator. One byte per
/// pixel (which neighbours are on the mask).
pub(crate) struct MaskStencil {
    h: usize,
    w: usize,
    flags: Vec<u8>,
}

#[inline(always)]
fn degree(f: u8) -> u8 {
    (f & 1) + ((f >> 1) & 1) + ((f >> 2) & 1) + (f >> 3)
}

impl MaskStencil {
    pub(crate) fn new(mask: &[bool], h: usize, w: usize) -> Self {
        assert_eq!(mask.len(), h * w);
        let mut flags = vec![0u8; h * w];
        if w > 0 {
            let none = vec![false; w];
            flags.par_chunks_mut(w).enumerate().for_each(|(r, f)| {
                let m = &mask[r * w..(r + 1) * w];
                let up = if r > 0 {
                    &mask[(r - 1) * w..r * w]
                } else {
                    &none
                };
                let dn = if r + 1 < h {
                    &mask[(r + 1) * w..(r + 2) * w]
                } else {
                    &none
                };
                let b = |v: bool| u8::from(v);
                for c in 0..w {
                    f[c] = b(m[c]) * ((b(dn[c]) * SOUTH) | (b(up[c]) * NORTH));
                }
                for c in 0..w - 1 {
                    f[c] |= b(m[c]) * b(m[c + 1]) * EAST;
                    f[c + 1] |= b(m[c]) * b(m[c + 1]) * WEST;
                }
            });
        }
        Self { h, w, flags }
    }
}

impl Stencil for MaskStencil {
    fn dims(&self) -> (usize, usize) {
        (self.h, self.w)
    }

    #[inline(always)]
    fn weights(&self, r: usize, c: usize) -> [f32; 4] {
        let f = self.flags[r * self.w + c];
        [EAST, WEST, SOUTH, NORTH].map(|b| f32::from(u8::from(f & b != 0)))
    }

    #[inline(always)]
    fn edge_row(&self, r: usize, east: &mut [f32], south: &mut [f32]) {
        let w = self.w;
        let (f, east, south) = (
            &self.flags[r * w..(r + 1) * w],
            &mut east[..w],
            &mut south[..w],
        );
        for c in 0..w {
            east[c] = f32::from(f[c] & EAST);
            south[c] = f32::from((f[c] & SOUTH) >> 2);
        }
    }

    /// With `x = 0` off the mask, the weighted neighbour sum is just the sum of the four
    /// neighbours: no weights are loaded at all.
    #[inline(always)]
    fn neighbour_sum(&self, _r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]) {
        let w = self.w;
        let (up, cur, down, out) = (&up[..w], &cur[..w], &down[..w], &mut out[..w]);
        if w == 1 {
            out[0] = up[0] + down[0];
            return;
        }
        out[0] = up[0] + down[0] + cur[1];
        for c in 1..w - 1 {
            out[c] = (up[c] + down[c]) + (cur[c - 1] + cur[c + 1]);
        }
        out[w - 1] = up[w - 1] + down[w - 1] + cur[w - 2];
    }

    #[inline(always)]
    fn diag_row(&self, r: usize, d: &mut [f32], inv: &mut [f32]) {
        let w = self.w;
        let (f, d, inv) = (&self.flags[r * w..(r + 1) * w], &mut d[..w], &mut inv[..w]);
        for c in 0..w {
            let v = f32::from(degree(f[c]));
            d[c] = v;
            inv[c] = if v > 0.0 { 1.0 / v.max(1.0) } else { 0.0 };
        }
    }

    #[inline(always)]
    fn apply_row(&self, r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]) {
        let w = self.w;
        let f = &self.flags[r * w..(r + 1) * w];
        let (up, cur, down, out) = (&up[..w], &cur[..w], &down[..w], &mut out[..w]);
        let bit = |c: usize, b: u8| f32::from(u8::from(f[c] & b != 0));
        let vertical =
            |c: usize| bit(c, SOUTH) * (cur[c] - down[c]) + bit(c, NORTH) * (cur[c] - up[c]);
        if w == 1 {
            out[0] = vertical(0);
            return;
        }
        out[0] = vertical(0) + bit(0, EAST) * (cur[0] - cur[1]);
        for c in 1..w - 1 {
            out[c] = vertical(c)
                + (bit(c, EAST) * (cur[c] - cur[c + 1]) + bit(c, WEST) * (cur[c] - cur[c - 1]));
        }
        out[w - 1] = vertical(w - 1) + bit(w - 1, WEST) * (cur[w - 1] - cur[w - 2]);
    }
}

/// General edge weights: `wx[r][c]` joins `(r, c)`–`(r, c+1)` (0 in the last column),
/// `wy[r][c]` joins `(r, c)`–`(r+1, c)` (0 in the last row). The diagonal is summed from
/// them row by row when a sweep needs it: storing it (and its inverse) doubled the bytes
/// every sweep streams, and the sweeps are memory-bound.
pub(crate) struct WeightStencil {
    h: usize,
    w: usize,
    wx: Vec<f32>,
    wy: Vec<f32>,
    zero_row: Vec<f32>,
}

impl WeightStencil {
    pub(crate) fn new(h: usize, w: usize, wx: Vec<f32>, wy: Vec<f32>) -> Self {
        Self {
            h,
            w,
            wx,
            wy,
            zero_row: vec![0.0; w],
        }
    }

    /// The edge weights east and south, to be refilled for another operator.
    pub(crate) fn into_weights(self) -> (Vec<f32>, Vec<f32>) {
        (self.wx, self.wy)
    }

    /// Weighted least squares on a mask: edge weights from [`edge_weights`].
    pub(crate) fn from_pixel_weights(
        mask: &[bool],
        weight: &[f32],
        h: usize,
        w: usize,
        floor: f32,
    ) -> Self {
        let (wx, wy) = edge_weights(mask, Some(weight), h, w, floor);
        Self::new(h, w, wx, wy)
    }

    fn row<'a>(&self, v: &'a [f32], r: usize) -> &'a [f32] {
        &v[r * self.w..(r + 1) * self.w]
    }
}

/// Weights of the edges to the right (`wx`) and below (`wy`) of each mask pixel: the mean
/// of the two pixels' weights (clamped to [0, 1], non-finite → 0; all 1 without weights),
/// floored at `floor > 0` so that the mask's connectivity (and hence the null space) does
/// not depend on the weights. Edges leaving the mask get 0.
pub(crate) fn edge_weights(
    mask: &[bool],
    weight: Option<&[f32]>,
    h: usize,
    w: usize,
    floor: f32,
) -> (Vec<f32>, Vec<f32>) {
    let mut wx = vec![0f32; h * w];
    let mut wy = vec![0f32; h * w];
    if w == 0 {
        return (wx, wy);
    }
    wx.par_chunks_mut(w)
        .zip(wy.par_chunks_mut(w))
        .enumerate()
        .for_each(|(r, (wx, wy))| edge_weight_row(mask, weight, h, floor, r, wx, wy));
    (wx, wy)
}

/// Row `r` of [`edge_weights`] into `wx` and `wy` (each a row long, and zero: only the
/// edges that exist are written, so the pages of a fresh buffer's rows off the mask are
/// never touched), for a caller that also forms them a row at a time.
pub(crate) fn edge_weight_row(
    mask: &[bool],
    weight: Option<&[f32]>,
    h: usize,
    floor: f32,
    r: usize,
    wx: &mut [f32],
    wy: &mut [f32],
) {
    let w = wx.len();
    let wt = |i: usize| {
        weight.map_or(1.0, |v| {
            if v[i].is_finite() {
                v[i].clamp(0.0, 1.0)
            } else {
                0.0
            }
        })
    };
    for c in 0..w {
        let i = r * w + c;
        if !mask[i] {
            continue;
        }
        if c + 1 < w && mask[i + 1] {
            wx[c] = (0.5 * (wt(i) + wt(i + 1))).max(floor);
        }
        if r + 1 < h && mask[i + w] {
            wy[c] = (0.5 * (wt(i) + wt(i + w))).max(floor);
        }
    }
}

impl Stencil for WeightStencil {
    fn dims(&self) -> (usize, usize) {
        (self.h, self.w)
    }

    #[inline(always)]
    fn weights(&self, r: usize, c: usize) -> [f32; 4] {
        let i = r * self.w + c;
        [
            self.wx[i],
            if c > 0 { self.wx[i - 1] } else { 0.0 },
            self.wy[i],
            if r > 0 { self.wy[i - self.w] } else { 0.0 },
        ]
    }

    #[inline(always)]
    fn edge_row(&self, r: usize, east: &mut [f32], south: &mut [f32]) {
        east.copy_from_slice(self.row(&self.wx, r));
        south.copy_from_slice(self.row(&self.wy, r));
    }

    #[inline(always)]
    fn neighbour_sum(&self, r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]) {
        let w = self.w;
        let wx = self.row(&self.wx, r);
        let wy = self.row(&self.wy, r);
        // Row r − 1's south weights; on row 0 any finite row will do, `up` is zero there.
        let wyu = self.row(&self.wy, r.saturating_sub(1));
        let (up, cur, down, out) = (&up[..w], &cur[..w], &down[..w], &mut out[..w]);
        for c in 0..w {
            out[c] = wyu[c] * up[c] + wy[c] * down[c];
        }
        if w > 1 {
            out[0] += wx[0] * cur[1];
            for c in 1..w - 1 {
                out[c] += wx[c - 1] * cur[c - 1] + wx[c] * cur[c + 1];
            }
            out[w - 1] += wx[w - 2] * cur[w - 2];
        }
    }

    #[inline(always)]
    fn diag_row(&self, r: usize, d: &mut [f32], inv: &mut [f32]) {
        let w = self.w;
        let wx = self.row(&self.wx, r);
        let wy = self.row(&self.wy, r);
        let wyu = if r > 0 {
            self.row(&self.wy, r - 1)
        } else {
            &self.zero_row
        };
        let (d, inv) = (&mut d[..w], &mut inv[..w]);
        // East + south + west + north, in that order (0 for a missing west or north edge).
        for c in 0..w {
            let west = if c > 0 { wx[c - 1] } else { 0.0 };
            let s = wx[c] + wy[c] + west + wyu[c];
            d[c] = s;
            inv[c] = if s > 0.0 { 1.0 / s } else { 0.0 };
        }
    }

    #[inline(always)]
    fn apply_row(&self, r: usize, up: &[f32], cur: &[f32], down: &[f32], out: &mut [f32]) {
        let w = self.w;
        let wx = self.row(&self.wx, r);
        let wy = self.row(&self.wy, r);
        let wyu = if r > 0 {
            self.row(&self.wy, r - 1)
        } else {
            &self.zero_row
        };
        let (up, cur, down, out) = (&up[..w], &cur[..w], &down[..w], &mut out[..w]);
        for c in 0..w {
            out[c] = wy[c] * (cur[c] - down[c]) + wyu[c] * (cur[c] - up[c]);
        }
        if w > 1 {
            out[0] += wx[0] * (cur[0] - cur[1]);
            for c in 1..w - 1 {
                out[c] += wx[c] * (cur[c] - cur[c + 1]) + wx[c - 1] * (cur[c] - cur[c - 1]);
            }
            out[w - 1] += wx[w - 2] * (cur[w - 1] - cur[w - 2]);
        }
    }
}
