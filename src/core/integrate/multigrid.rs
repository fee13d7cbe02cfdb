//! Geometric multigrid V-cycle for weighted graph Laplacians on masked 4-neighbour grids,
//! used as the (symmetric) preconditioner of the masked Poisson solver.
//!
//! Operator at every level: `(A x)_i = Σ_j w_ij (x_i − x_j)` over the 4-neighbours `j` of
//! `i` that share an edge of weight `w_ij > 0`. Cells without edges are inactive (not
//! unknowns; their value is kept at 0).
//!
//! * Coarsening: 2×2 cells → 1 (a single row/column stays single). A coarse cell is active
//!   iff one of its children has an edge leaving the 2×2 block. A coarse edge carries
//!   [`COARSE_SCALE`] × the sum of the fine edges it crosses: the rediscretised Laplacian
//!   (weight 1 at every level of a full grid), and no coarse edge bridges a gap of the mask.
//! * Transfers: piecewise-constant prolongation `P` (each active fine cell takes its
//!   parent's value) and restriction `R = Pᵀ` (sum over the children). They are cheap, keep
//!   constants per component, never reach across a gap of the mask, and — with the ½-scaled
//!   coarse operator, which compensates the too-stiff Galerkin product `PᵀAP` — give a
//!   preconditioner whose CG iteration count to a relative residual of 1e-6 stays ~8 from
//!   128² to 4096² on solid masks (cell-centred bilinear transfers needed as many
//!   iterations at ~2× the cost). Ragged masks converge more slowly (27 iterations with 25%
//!   random holes), since a coarse cell may then merge pieces that are not connected on the
//!   fine grid.
//! * Smoother: red–black Gauss–Seidel, red then black before the coarse correction and
//!   black then red after it, so the V-cycle is a symmetric operator (required by CG).
//! * Coarsest level (≤ [`COARSEST_CELLS`] cells): dense Cholesky of `A + Q`, where `Q`
//!   projects onto the per-component constants. That is the pseudo-inverse on the range
//!   of `A` and the identity on its null space: symmetric, and never divides by ~0.
//!
//! All sweeps are row-parallel (rayon) with vectorisable row kernels; storage is f32.

use rayon::prelude::*;

/// Edge bits of a mask pixel: its east / west / south / north neighbour is on the mask.
const EAST: u8 = 1;
const WEST: u8 = 2;
const SOUTH: u8 = 4;
const NORTH: u8 = 8;

/// Lower bound of an edge weight in [`super::integrate_weighted`]: zero-confidence pixels stay
/// connected (so the answer is well defined) but barely constrain the surface.
pub const MIN_EDGE_WEIGHT: f32 = 1e-3;

/// Stop coarsening once a level has at most this many cells.
const COARSEST_CELLS: usize = 256;
/// Coarse edge weight = this × (sum of the fine edge weights it crosses).
const COARSE_SCALE: f32 = 0.5;

/// A weighted 4-neighbour graph Laplacian on an `h × w` grid.
pub(super) trait Stencil: Sync {
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
pub(super) struct MaskStencil {
    h: usize,
    w: usize,
    flags: Vec<u8>,
}

#[inline(always)]
fn degree(f: u8) -> u8 {
    (f & 1) + ((f >> 1) & 1) + ((f >> 2) & 1) + (f >> 3)
}

impl MaskStencil {
    pub(super) fn new(mask: &[bool], h: usize, w: usize) -> Self {
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
pub(super) struct WeightStencil {
    h: usize,
    w: usize,
    wx: Vec<f32>,
    wy: Vec<f32>,
    zero_row: Vec<f32>,
}

impl WeightStencil {
    pub(super) fn new(h: usize, w: usize, wx: Vec<f32>, wy: Vec<f32>) -> Self {
        Self {
            h,
            w,
            wx,
            wy,
            zero_row: vec![0.0; w],
        }
    }

    /// Weighted least squares on a mask: edge weights from [`edge_weights`].
    pub(super) fn from_pixel_weights(
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
pub(super) fn edge_weights(
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
pub(super) fn edge_weight_row(
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

// ---------------------------------------------------------------------------------------
// Row-band kernels.
//
// Every pass over a level is parallel over bands of rows (an even number of rows each, so
// that coarse rows belong to exactly one band) and sequential inside a band, streaming the
// rows through small ring buffers. Each pass fuses several sweeps, so one pass reads and
// writes each large array once. Kernels that update an array in place first copy the
// rows just outside every band ("ghosts"), so bands never read rows another band writes.
// ---------------------------------------------------------------------------------------

/// Band partition of `h` rows.
#[derive(Clone, Copy)]
struct Bands {
    rows: usize,
    count: usize,
}

impl Bands {
    fn new(h: usize, w: usize) -> Self {
        // Small grids run as one band: splitting them costs more than it saves.
        let rows = if h * w < 1 << 15 {
            h
        } else {
            h.div_ceil(4 * rayon::current_num_threads()).max(8)
        };
        let rows = rows + (rows & 1);
        Self {
            rows,
            count: h.div_ceil(rows),
        }
    }
}

/// For every band, the `halo` rows above it then the `halo` rows below it (zero rows
/// outside the grid), copied from `x` into `g` before an in-place pass. Every element of
/// `g` is written.
fn ghosts(x: &[f32], h: usize, w: usize, bands: Bands, halo: usize, g: &mut [f32]) {
    for (k, gb) in g.chunks_mut(2 * halo * w).enumerate() {
        let (r0, r1) = (k * bands.rows, ((k + 1) * bands.rows).min(h));
        // Above: rows r0 − halo .. r0; below: rows r1 .. r1 + halo.
        let rows =
            (r0 as isize - halo as isize..r0 as isize).chain(r1 as isize..(r1 + halo) as isize);
        for (j, r) in rows.enumerate() {
            let out = &mut gb[j * w..(j + 1) * w];
            if in_grid(r, h) {
                let r = r as usize;
                out.copy_from_slice(&x[r * w..(r + 1) * w]);
            } else {
                out.fill(0.0);
            }
        }
    }
}

/// Per-level buffers of the band passes, allocated once per solve and reused by every
/// pass: one [`Scratch`] per band and two ghost-row arrays. Fresh allocations per pass
/// page-faulted in the kernel on every call (and read-before-write of untouched zeroed
/// pages costs a copy-on-write fault with a TLB shootdown each).
struct Work {
    bands: Bands,
    scratch: Vec<Scratch>,
    ghost: [Vec<f32>; 2],
}

impl Work {
    fn new(h: usize, w: usize) -> Self {
        let bands = Bands::new(h, w);
        let len = bands.count * 2 * PRE_HALO.max(POST_HALO) * w;
        Self {
            bands,
            scratch: (0..bands.count).map(|_| Scratch::new(w)).collect(),
            ghost: [vec![0.0; len], vec![0.0; len]],
        }
    }

    /// The band partition, the band scratches, and the ghost rows (`halo` deep) of `x` and
    /// (if given) of `y`.
    fn split(
        &mut self,
        dims: (usize, usize),
        halo: usize,
        x: &[f32],
        y: Option<&[f32]>,
    ) -> (Bands, &mut [Scratch], &[f32], &[f32]) {
        let (h, w) = dims;
        let len = self.bands.count * 2 * halo * w;
        let [gx, gy] = &mut self.ghost;
        ghosts(x, h, w, self.bands, halo, &mut gx[..len]);
        if let Some(y) = y {
            ghosts(y, h, w, self.bands, halo, &mut gy[..len]);
        }
        (self.bands, &mut self.scratch, &gx[..len], &gy[..len])
    }
}

/// Row `k` of an array being rewritten in place by the band `[r0, r1)`: from the band while
/// not yet overwritten, else from the ghosts; a zero row outside the grid.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn fetch<'a>(
    k: isize,
    r0: usize,
    r1: usize,
    h: usize,
    band: &'a [f32],
    ghost: &'a [f32],
    halo: usize,
    zeros: &'a [f32],
) -> &'a [f32] {
    let w = zeros.len();
    if k < 0 || k as usize >= h {
        return zeros;
    }
    let k = k as usize;
    let j = if k < r0 {
        halo - (r0 - k)
    } else if k >= r1 {
        halo + (k - r1)
    } else {
        return &band[(k - r0) * w..(k - r0 + 1) * w];
    };
    &ghost[j * w..(j + 1) * w]
}

/// Three rows indexed by `k mod 3`: the window a 5-point stencil needs.
struct Ring {
    data: Vec<f32>,
    w: usize,
}

impl Ring {
    fn new(w: usize) -> Self {
        Self {
            data: vec![0f32; 3 * w],
            w,
        }
    }
    #[inline(always)]
    fn slot(k: isize) -> usize {
        k.rem_euclid(3) as usize
    }
    #[inline(always)]
    fn row(&self, k: isize) -> &[f32] {
        let s = Self::slot(k) * self.w;
        &self.data[s..s + self.w]
    }
    #[inline(always)]
    fn row_mut(&mut self, k: isize) -> &mut [f32] {
        let s = Self::slot(k) * self.w;
        &mut self.data[s..s + self.w]
    }
    /// Rows `k − 1`, `k`, `k + 1`.
    #[inline(always)]
    fn window(&self, k: isize) -> [&[f32]; 3] {
        [self.row(k - 1), self.row(k), self.row(k + 1)]
    }
}

/// Per-task scratch: two ring buffers of values, rings of the diagonal and its inverse, a
/// row buffer and a zero row.
struct Scratch {
    a: Ring,
    b: Ring,
    /// Right-hand-side rows.
    f: Ring,
    d: Ring,
    inv: Ring,
    nb: Vec<f32>,
    zeros: Vec<f32>,
    /// `!0` on the cells with `c` even, then on the cells with `c` odd; 0 elsewhere.
    parity: [Vec<u32>; 2],
}

impl Scratch {
    fn new(w: usize) -> Self {
        Self {
            a: Ring::new(w),
            b: Ring::new(w),
            f: Ring::new(w),
            d: Ring::new(w),
            inv: Ring::new(w),
            nb: vec![0f32; w],
            zeros: vec![0f32; w],
            parity: [0, 1].map(|p| (0..w).map(|c| if c & 1 == p { !0 } else { 0 }).collect()),
        }
    }

    /// Diagonal and inverse of row `k` into the rings (zeros outside the grid).
    #[inline(always)]
    fn load_diag<S: Stencil>(&mut self, st: &S, k: isize, h: usize) {
        let (d, inv) = (self.d.row_mut(k), self.inv.row_mut(k));
        if in_grid(k, h) {
            st.diag_row(k as usize, &mut d[..], &mut inv[..]);
        } else {
            d.fill(0.0);
            inv.fill(0.0);
        }
    }
}

/// The sum of `parts` added in index order. Rayon's `sum` adds in an order that depends
/// on how the work was split and stolen, and f64 addition is not associative: heights
/// (and so artifacts) could then differ in their last bits from run to run.
pub(super) fn ordered_sum(parts: impl IndexedParallelIterator<Item = f64>) -> f64 {
    let parts: Vec<f64> = parts.collect();
    parts.iter().sum()
}

/// `Σ a_i b_i` in f64 with independent partial sums (so it pipelines / vectorises).
#[inline(always)]
pub(super) fn dot_f64(a: &[f32], b: &[f32]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(&x, &y)| f64::from(x) * f64::from(y))
        .sum();
    for (x, y) in ca.zip(cb) {
        for j in 0..8 {
            acc[j] += f64::from(x[j]) * f64::from(y[j]);
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// Bit mask selecting the cells of `colour` (red = 0: `r + c` even) in row `r`.
#[inline(always)]
fn colour(parity: &[Vec<u32>; 2], r: usize, colour: usize) -> &[u32] {
    &parity[(r + colour) & 1]
}

#[inline(always)]
fn in_grid(k: isize, h: usize) -> bool {
    k >= 0 && (k as usize) < h
}

/// Gauss–Seidel update of the cells of one colour in row `r`: `out = (b + Σ w x_j) / d`
/// there (0 on inactive cells), `out = keep` elsewhere. `nb` holds the neighbour sum.
#[inline(always)]
fn gs_row(sel: &[u32], b: &[f32], nb: &[f32], inv: &[f32], keep: &[f32], out: &mut [f32]) {
    let n = out.len();
    let (sel, b, nb, inv, keep) = (&sel[..n], &b[..n], &nb[..n], &inv[..n], &keep[..n]);
    // Every cell is computed and the colour picked bitwise, so the loop vectorises.
    for c in 0..n {
        let v = (b[c] + nb[c]) * inv[c];
        out[c] = f32::from_bits((v.to_bits() & sel[c]) | (keep[c].to_bits() & !sel[c]));
    }
}

/// Where the pre-smoother's right-hand side comes from.
enum Rhs<'a> {
    /// A fixed array (all rows).
    Fixed(&'a [f32]),
    /// The CG residual of this band, updated in place to `r − α A p` (`A p` is read from
    /// the band of `x` before it is overwritten), with the ghost rows of both.
    Step {
        r: &'a mut [f32],
        ghost_r: &'a [f32],
        ghost_ap: &'a [f32],
        alpha: f32,
    },
}

/// Band body of [`presmooth_restrict`]: rows `[r0, r1)` of `x`, the matching coarse rows.
/// Returns the squared norm of the band's right-hand side (meaningful for [`Rhs::Step`]).
#[inline(always)]
fn presmooth_band_body<S: Stencil>(
    st: &S,
    mut rhs: Rhs<'_>,
    xband: &mut [f32],
    cband: &mut [f32],
    s: &mut Scratch,
    r0: usize,
    r1: usize,
) -> f64 {
    let (h, w) = st.dims();
    let cw = w.div_ceil(2);
    let mut rr = 0.0f64;
    cband.fill(0.0);
    for kk in r0 as isize - 2..=r1 as isize + 1 {
        s.load_diag(st, kk, h);
        // F(kk): the right-hand side row.
        let fr = s.f.row_mut(kk);
        if in_grid(kk, h) {
            let r = kk as usize;
            match &mut rhs {
                Rhs::Fixed(b) => fr.copy_from_slice(&b[r * w..(r + 1) * w]),
                Rhs::Step {
                    r: rband,
                    ghost_r,
                    ghost_ap,
                    alpha,
                } => {
                    let old = fetch(kk, r0, r1, h, rband, ghost_r, PRE_HALO, &s.zeros);
                    let ap = fetch(kk, r0, r1, h, xband, ghost_ap, PRE_HALO, &s.zeros);
                    for c in 0..w {
                        fr[c] = old[c] - *alpha * ap[c];
                    }
                    if (r0..r1).contains(&r) {
                        rband[(r - r0) * w..(r - r0 + 1) * w].copy_from_slice(fr);
                        rr += dot_f64(fr, fr);
                    }
                }
            }
        } else {
            fr.fill(0.0);
        }
        // Z(kk): red cells b/d, black cells 0.
        let zr = s.a.row_mut(kk);
        let (br, inv) = (s.f.row(kk), s.inv.row(kk));
        let sel = colour(&s.parity, kk.rem_euclid(2) as usize, 0);
        for c in 0..w {
            zr[c] = f32::from_bits((br[c] * inv[c]).to_bits() & sel[c]);
        }
        // X(j): black half-sweep on Z.
        let j = kk - 1;
        if j >= r0 as isize - 1 {
            let xj = s.b.row_mut(j);
            if in_grid(j, h) {
                let r = j as usize;
                let [up, cur, down] = s.a.window(j);
                st.neighbour_sum(r, up, cur, down, &mut s.nb);
                let br = s.f.row(j);
                gs_row(colour(&s.parity, r, 1), br, &s.nb, s.inv.row(j), cur, xj);
            } else {
                xj.fill(0.0);
            }
        }
        // Residual of row i, restricted; X(i) stored.
        let i = kk - 2;
        if i >= r0 as isize && (i as usize) < r1 {
            let r = i as usize;
            let [up, cur, down] = s.b.window(i);
            let nb = &mut s.nb[..w];
            st.neighbour_sum(r, up, cur, down, nb);
            let (br, cur, d) = (s.f.row(i), &cur[..w], s.d.row(i));
            for c in 0..w {
                let t = br[c] - (d[c] * cur[c] - nb[c]);
                nb[c] = if d[c] > 0.0 { t } else { 0.0 };
            }
            let out = &mut cband[(r - r0) / 2 * cw..((r - r0) / 2 + 1) * cw];
            // Each pair of columns into its coarse cell (in pairs, which vectorises).
            let (pairs, tail) = nb.as_chunks::<2>();
            for (o, [a, b]) in out.iter_mut().zip(pairs) {
                *o += a + b;
            }
            if let [t] = tail {
                out[cw - 1] += t + 0.0;
            }
            xband[(r - r0) * w..(r - r0 + 1) * w].copy_from_slice(cur);
        }
    }
    rr
}

multiversion! {
    fn presmooth_band<S: Stencil>(
        st: &S, rhs: Rhs<'_>, xband: &mut [f32], cband: &mut [f32], s: &mut Scratch, r0: usize,
        r1: usize,
    ) -> f64 => presmooth_band_body
}

/// Ghost rows needed by the pre-smoother (two sweeps deep).
const PRE_HALO: usize = 2;

/// Pre-smoothing from a zero guess (red half-sweep, then black) into `x`, fused with the
/// restriction of the resulting residual: `cb = Pᵀ (b − A x)`.
fn presmooth_restrict<S: Stencil>(
    st: &S,
    b: &[f32],
    x: &mut [f32],
    cb: &mut [f32],
    work: &mut Work,
) {
    let (h, w) = st.dims();
    let cw = w.div_ceil(2);
    let bands = work.bands;
    x.par_chunks_mut(bands.rows * w)
        .zip(cb.par_chunks_mut(bands.rows / 2 * cw))
        .zip(work.scratch.par_iter_mut())
        .enumerate()
        .for_each(|(k, ((xband, cband), s))| {
            let (r0, r1) = (k * bands.rows, ((k + 1) * bands.rows).min(h));
            presmooth_band(st, Rhs::Fixed(b), xband, cband, s, r0, r1);
        });
}

/// The CG residual update `r ← r − α A p` (`zq` holds `A p`) fused with
/// [`presmooth_restrict`] on the updated `r`, whose output replaces `A p` in `zq`. Returns
/// `‖r‖²` after the update.
fn step_presmooth_restrict<S: Stencil>(
    st: &S,
    r: &mut [f32],
    zq: &mut [f32],
    alpha: f32,
    cb: &mut [f32],
    work: &mut Work,
) -> f64 {
    let (h, w) = st.dims();
    let cw = w.div_ceil(2);
    let (bands, scratch, g_r, g_ap) = work.split((h, w), PRE_HALO, r, Some(zq));
    let rows = bands.rows;
    ordered_sum(
        zq.par_chunks_mut(rows * w)
            .zip(cb.par_chunks_mut(rows / 2 * cw))
            .zip(r.par_chunks_mut(rows * w))
            .zip(
                g_r.par_chunks(2 * PRE_HALO * w)
                    .zip(g_ap.par_chunks(2 * PRE_HALO * w)),
            )
            .zip(scratch.par_iter_mut())
            .enumerate()
            .map(|(k, ((((xband, cband), rband), (ghost_r, ghost_ap)), s))| {
                let (r0, r1) = (k * rows, ((k + 1) * rows).min(h));
                let rhs = Rhs::Step {
                    r: rband,
                    ghost_r,
                    ghost_ap,
                    alpha,
                };
                presmooth_band(st, rhs, xband, cband, s, r0, r1)
            }),
    )
}

/// Band body of [`prolong_postsmooth`]: rows `[r0, r1)` of `x`, with ghost rows `gb`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn postsmooth_band_body<S: Stencil>(
    st: &S,
    b: &[f32],
    xc: &[f32],
    xband: &mut [f32],
    gb: &[f32],
    s: &mut Scratch,
    r0: usize,
    r1: usize,
) -> f64 {
    let (h, w) = st.dims();
    let cw = w.div_ceil(2);
    let mut acc = 0.0f64;
    for kk in r0 as isize - 2..=r1 as isize + 1 {
        s.load_diag(st, kk, h);
        // Y(kk) = x + P xc on active cells.
        let yr = s.a.row_mut(kk);
        if in_grid(kk, h) {
            let r = kk as usize;
            yr.copy_from_slice(fetch(kk, r0, r1, h, xband, gb, POST_HALO, &s.zeros));
            let crow = &xc[r / 2 * cw..(r / 2 + 1) * cw];
            let nb = &mut s.nb[..w];
            // Each coarse value twice (written as one 64-bit pattern, which vectorises).
            let (pairs, tail) = nb.as_chunks_mut::<2>();
            for (pair, &v) in pairs.iter_mut().zip(crow) {
                *pair = [v, v];
            }
            if let [t] = tail {
                *t = crow[cw - 1];
            }
            let d = s.d.row(kk);
            for c in 0..w {
                let v = nb[c];
                yr[c] += if d[c] > 0.0 { v } else { 0.0 };
            }
        } else {
            yr.fill(0.0);
        }
        // B(j): black half-sweep on Y.
        let j = kk - 1;
        if j >= r0 as isize - 1 {
            let bj = s.b.row_mut(j);
            if in_grid(j, h) {
                let r = j as usize;
                let [up, cur, down] = s.a.window(j);
                st.neighbour_sum(r, up, cur, down, &mut s.nb);
                let br = &b[r * w..(r + 1) * w];
                gs_row(colour(&s.parity, r, 1), br, &s.nb, s.inv.row(j), cur, bj);
            } else {
                bj.fill(0.0);
            }
        }
        // F(i): red half-sweep on B, stored.
        let i = kk - 2;
        if i >= r0 as isize && (i as usize) < r1 {
            let r = i as usize;
            let [up, cur, down] = s.b.window(i);
            st.neighbour_sum(r, up, cur, down, &mut s.nb);
            let br = &b[r * w..(r + 1) * w];
            let out = &mut xband[(r - r0) * w..(r - r0 + 1) * w];
            gs_row(colour(&s.parity, r, 0), br, &s.nb, s.inv.row(i), cur, out);
            acc += dot_f64(out, br);
        }
    }
    acc
}

multiversion! {
    fn postsmooth_band<S: Stencil>(
        st: &S, b: &[f32], xc: &[f32], xband: &mut [f32], gb: &[f32], s: &mut Scratch,
        r0: usize, r1: usize,
    ) -> f64 => postsmooth_band_body
}

/// Ghost rows needed by the post-smoother (two sweeps deep).
const POST_HALO: usize = 2;

/// Coarse correction and post-smoothing, fused: `x += P xc`, then a black half-sweep, then
/// a red one. Returns `bᵀ x` of the result.
fn prolong_postsmooth<S: Stencil>(
    st: &S,
    b: &[f32],
    x: &mut [f32],
    xc: &[f32],
    work: &mut Work,
) -> f64 {
    let (h, w) = st.dims();
    let (bands, scratch, g, _) = work.split((h, w), POST_HALO, x, None);
    ordered_sum(
        x.par_chunks_mut(bands.rows * w)
            .zip(g.par_chunks(2 * POST_HALO * w))
            .zip(scratch.par_iter_mut())
            .enumerate()
            .map(|(k, ((xband, gb), s))| {
                let (r0, r1) = (k * bands.rows, ((k + 1) * bands.rows).min(h));
                postsmooth_band(st, b, xc, xband, gb, s, r0, r1)
            }),
    )
}

/// Band body of [`direction_apply`].
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn direction_band_body<S: Stencil>(
    st: &S,
    zband: &mut [f32],
    pband: &mut [f32],
    xband: &mut [f32],
    gzb: &[f32],
    gpb: &[f32],
    s: &mut Scratch,
    r0: usize,
    r1: usize,
    coef: [f32; 2],
) -> f64 {
    let (h, w) = st.dims();
    let [alpha, beta] = coef;
    let Scratch { a: pn, zeros, .. } = s;
    let mut acc = 0.0f64;
    for kk in r0 as isize - 1..=r1 as isize {
        let zr = fetch(kk, r0, r1, h, zband, gzb, 1, zeros);
        let pr = fetch(kk, r0, r1, h, pband, gpb, 1, zeros);
        if alpha != 0.0 && kk >= r0 as isize && (kk as usize) < r1 {
            let xr = &mut xband[(kk as usize - r0) * w..(kk as usize - r0 + 1) * w];
            for c in 0..w {
                xr[c] += alpha * pr[c];
            }
        }
        let o = pn.row_mut(kk);
        for c in 0..w {
            o[c] = zr[c] + beta * pr[c];
        }
        let i = kk - 1;
        if i >= r0 as isize && (i as usize) < r1 {
            let r = i as usize;
            let [up, cur, down] = pn.window(i);
            let o = (r - r0) * w..(r - r0 + 1) * w;
            st.apply_row(r, up, cur, down, &mut zband[o.clone()]);
            acc += dot_f64(cur, &zband[o.clone()]);
            pband[o].copy_from_slice(cur);
        }
    }
    acc
}

multiversion! {
    fn direction_band<S: Stencil>(
        st: &S, zband: &mut [f32], pband: &mut [f32], xband: &mut [f32], gzb: &[f32],
        gpb: &[f32], s: &mut Scratch, r0: usize, r1: usize, coef: [f32; 2],
    ) -> f64 => direction_band_body
}

/// The CG direction update fused with the operator and the deferred solution update:
/// `x ← x + α p`, `p ← z + β p`, then `z ← A p` (in place: the buffer holding `z` receives
/// `A p`). Returns `pᵀ A p` (f64 sums).
fn direction_apply<S: Stencil>(
    st: &S,
    zq: &mut [f32],
    p: &mut [f32],
    x: &mut [f32],
    alpha: f32,
    beta: f32,
    work: &mut Work,
) -> f64 {
    let (h, w) = st.dims();
    if h * w == 0 {
        return 0.0;
    }
    let (bands, scratch, gz, gp) = work.split((h, w), 1, zq, Some(p));
    let rows = bands.rows * w;
    ordered_sum(
        zq.par_chunks_mut(rows)
            .zip(p.par_chunks_mut(rows).zip(x.par_chunks_mut(rows)))
            .zip(gz.par_chunks(2 * w).zip(gp.par_chunks(2 * w)))
            .zip(scratch.par_iter_mut())
            .enumerate()
            .map(|(k, (((zband, (pband, xband)), (gzb, gpb)), s))| {
                let (r0, r1) = (k * bands.rows, ((k + 1) * bands.rows).min(h));
                direction_band(st, zband, pband, xband, gzb, gpb, s, r0, r1, [alpha, beta])
            }),
    )
}

/// `out = A x` (f64 arithmetic, f32 storage); returns `xᵀ A x`.
#[cfg(test)]
pub(super) fn apply<S: Stencil>(st: &S, x: &[f32], out: &mut [f32]) -> f64 {
    let mut p = vec![0f32; x.len()];
    let mut dummy = vec![0f32; x.len()];
    out.copy_from_slice(x);
    let (h, w) = st.dims();
    direction_apply(st, out, &mut p, &mut dummy, 0.0, 0.0, &mut Work::new(h, w))
}

/// One coarse level: its operator and work vectors.
struct Level {
    st: WeightStencil,
    x: Vec<f32>,
    b: Vec<f32>,
    work: Work,
}

fn coarsen<S: Stencil>(fine: &S) -> Level {
    let (h, w) = fine.dims();
    let (ch, cw) = (h.div_ceil(2), w.div_ceil(2));
    let mut wx = vec![0f32; ch * cw];
    let mut wy = vec![0f32; ch * cw];
    wx.par_chunks_mut(cw)
        .zip(wy.par_chunks_mut(cw))
        .enumerate()
        .for_each_init(
            || [(); 4].map(|_| vec![0f32; w]),
            |[e0, s0, e1, s1], (rr, (wxr, wyr))| {
                fine.edge_row(2 * rr, e0, s0);
                if 2 * rr + 1 < h {
                    fine.edge_row(2 * rr + 1, e1, s1);
                } else {
                    e1.fill(0.0);
                    s1.fill(0.0);
                }
                // East edges leaving the children's right column; south edges leaving the
                // bottom row (zero in the last column / row by construction).
                for cc in 0..cw {
                    let c = (2 * cc + 1).min(w - 1);
                    wxr[cc] = COARSE_SCALE * (e0[c] + e1[c]);
                    wyr[cc] = COARSE_SCALE
                        * (s1[2 * cc] + if 2 * cc + 1 < w { s1[2 * cc + 1] } else { 0.0 });
                }
                if 2 * rr + 1 >= h {
                    wyr.fill(0.0);
                }
            },
        );
    Level {
        st: WeightStencil::new(ch, cw, wx, wy),
        x: vec![0.0; ch * cw],
        b: vec![0.0; ch * cw],
        work: Work::new(ch, cw),
    }
}

/// Dense solve on the coarsest level: Cholesky of `A + Q` over the active cells.
struct Dense {
    cells: Vec<usize>,
    chol: Vec<f64>,
}

impl Dense {
    fn new<S: Stencil>(st: &S) -> Self {
        let (h, w) = st.dims();
        let active = |r: usize, c: usize| st.weights(r, c).iter().any(|&v| v > 0.0);
        let mut index = vec![usize::MAX; h * w];
        let mut cells = Vec::new();
        for r in 0..h {
            for c in 0..w {
                if active(r, c) {
                    index[r * w + c] = cells.len();
                    cells.push(r * w + c);
                }
            }
        }
        let n = cells.len();
        let mut a = vec![0f64; n * n];
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(p: &mut [usize], mut i: usize) -> usize {
            while p[i] != i {
                p[i] = p[p[i]];
                i = p[i];
            }
            i
        }
        for (k, &i) in cells.iter().enumerate() {
            let (r, c) = (i / w, i % w);
            let [we, _, ws, _] = st.weights(r, c);
            for (wt, j) in [(we, i + 1), (ws, i + w)] {
                if wt > 0.0 {
                    let l = index[j];
                    let wt = f64::from(wt);
                    a[k * n + k] += wt;
                    a[l * n + l] += wt;
                    a[k * n + l] -= wt;
                    a[l * n + k] -= wt;
                    let (x, y) = (find(&mut parent, k), find(&mut parent, l));
                    parent[x] = y;
                }
            }
        }
        // + Q: 1/n_k on every pair of cells of component k.
        let roots: Vec<usize> = (0..n).map(|k| find(&mut parent, k)).collect();
        let mut size = vec![0usize; n];
        for &r in &roots {
            size[r] += 1;
        }
        for k in 0..n {
            for l in 0..n {
                if roots[k] == roots[l] {
                    a[k * n + l] += 1.0 / size[roots[k]] as f64;
                }
            }
        }
        // In-place lower Cholesky; A + Q is SPD, the floor only guards round-off.
        for j in 0..n {
            let mut d = a[j * n + j];
            for k in 0..j {
                d -= a[j * n + k] * a[j * n + k];
            }
            let d = d.max(1e-12).sqrt();
            a[j * n + j] = d;
            for i in j + 1..n {
                let mut s = a[i * n + j];
                for k in 0..j {
                    s -= a[i * n + k] * a[j * n + k];
                }
                a[i * n + j] = s / d;
            }
        }
        Self { cells, chol: a }
    }

    fn solve(&self, b: &[f32], x: &mut [f32]) {
        let n = self.cells.len();
        let l = &self.chol;
        let mut y: Vec<f64> = self.cells.iter().map(|&i| f64::from(b[i])).collect();
        for i in 0..n {
            let mut s = y[i];
            for k in 0..i {
                s -= l[i * n + k] * y[k];
            }
            y[i] = s / l[i * n + i];
        }
        for i in (0..n).rev() {
            let mut s = y[i];
            for k in i + 1..n {
                s -= l[k * n + i] * y[k];
            }
            y[i] = s / l[i * n + i];
        }
        x.fill(0.0);
        for (&i, &v) in self.cells.iter().zip(&y) {
            x[i] = v as f32;
        }
    }
}

/// The multigrid hierarchy below a fine operator; applying it is one V(1,1)-cycle.
pub(super) struct Hierarchy {
    levels: Vec<Level>,
    dense: Dense,
    /// Band buffers of the fine level.
    work: Work,
}

impl Hierarchy {
    pub(super) fn new<S: Stencil>(fine: &S) -> Self {
        let mut levels: Vec<Level> = Vec::new();
        let too_big = |(h, w): (usize, usize)| h * w > COARSEST_CELLS;
        if too_big(fine.dims()) {
            levels.push(coarsen(fine));
            while let Some(last) = levels.last()
                && too_big(last.st.dims())
            {
                let next = coarsen(&last.st);
                levels.push(next);
            }
        }
        let dense = match levels.last() {
            Some(l) => Dense::new(&l.st),
            None => Dense::new(fine),
        };
        let (h, w) = fine.dims();
        Self {
            levels,
            dense,
            work: Work::new(h, w),
        }
    }

    /// Number of levels including the fine one.
    pub(super) fn depth(&self) -> usize {
        self.levels.len() + 1
    }

    /// `x = M b` with `M ≈ A⁺` symmetric positive definite; returns `bᵀ x`. `b` must be 0
    /// on inactive cells; so is `x`.
    pub(super) fn apply<S: Stencil>(&mut self, fine: &S, b: &[f32], x: &mut [f32]) -> f64 {
        vcycle(fine, b, x, &mut self.work, &mut self.levels, &self.dense)
    }

    /// [`direction_apply`] on the fine level.
    pub(super) fn direction_apply<S: Stencil>(
        &mut self,
        fine: &S,
        zq: &mut [f32],
        p: &mut [f32],
        x: &mut [f32],
        alpha: f32,
        beta: f32,
    ) -> f64 {
        direction_apply(fine, zq, p, x, alpha, beta, &mut self.work)
    }

    /// One CG step's residual update and preconditioning, fused: `r ← r − α A p` (with
    /// `zq = A p` on entry), then — unless `stop(‖r‖²)` — `zq ← M r`. Returns `‖r‖²` and,
    /// if the cycle ran, `rᵀ M r`.
    pub(super) fn step<S: Stencil>(
        &mut self,
        fine: &S,
        r: &mut [f32],
        zq: &mut [f32],
        alpha: f32,
        stop: impl FnOnce(f64) -> bool,
    ) -> (f64, Option<f64>) {
        let Self {
            levels,
            dense,
            work,
        } = self;
        let Some((next, rest)) = levels.split_first_mut() else {
            r.iter_mut()
                .zip(zq.iter())
                .for_each(|(r, &ap)| *r -= alpha * ap);
            let rr = dot_f64(r, r);
            if stop(rr) {
                return (rr, None);
            }
            dense.solve(r, zq);
            return (rr, Some(dot_f64(r, zq)));
        };
        let rr = step_presmooth_restrict(fine, r, zq, alpha, &mut next.b, work);
        if stop(rr) {
            return (rr, None);
        }
        vcycle(&next.st, &next.b, &mut next.x, &mut next.work, rest, dense);
        (rr, Some(prolong_postsmooth(fine, r, zq, &next.x, work)))
    }
}

fn vcycle<S: Stencil>(
    st: &S,
    b: &[f32],
    x: &mut [f32],
    work: &mut Work,
    levels: &mut [Level],
    dense: &Dense,
) -> f64 {
    let Some((next, rest)) = levels.split_first_mut() else {
        dense.solve(b, x);
        return b
            .iter()
            .zip(x.iter())
            .map(|(&u, &v)| f64::from(u) * f64::from(v))
            .sum();
    };
    presmooth_restrict(st, b, x, &mut next.b, work);
    vcycle(&next.st, &next.b, &mut next.x, &mut next.work, rest, dense);
    prolong_postsmooth(st, b, x, &next.x, work)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply_a<S: Stencil>(st: &S, x: &[f32]) -> Vec<f32> {
        let mut out = vec![0f32; x.len()];
        apply(st, x, &mut out);
        out
    }

    fn disc_mask(h: usize, w: usize) -> Vec<bool> {
        (0..h * w)
            .map(|i| {
                let (r, c) = (
                    (i / w) as f64 - h as f64 / 2.0,
                    (i % w) as f64 - w as f64 / 2.0,
                );
                r * r + c * c < (0.4 * h.min(w) as f64).powi(2)
            })
            .collect()
    }

    /// The V-cycle must be symmetric for CG: uᵀ M v = vᵀ M u.
    #[test]
    fn vcycle_is_symmetric_and_positive() {
        let (h, w) = (45, 38);
        let mask = disc_mask(h, w);
        let st = MaskStencil::new(&mask, h, w);
        let mut hier = Hierarchy::new(&st);
        assert!(hier.depth() >= 3);
        let u: Vec<f32> = (0..h * w)
            .map(|i| {
                if mask[i] {
                    ((i * 7919) % 101) as f32 / 50.0 - 1.0
                } else {
                    0.0
                }
            })
            .collect();
        let v: Vec<f32> = (0..h * w)
            .map(|i| {
                if mask[i] {
                    ((i * 104_729) % 97) as f32 / 48.0 - 1.0
                } else {
                    0.0
                }
            })
            .collect();
        let (mut mu, mut mv) = (vec![0f32; h * w], vec![0f32; h * w]);
        hier.apply(&st, &u, &mut mu);
        hier.apply(&st, &v, &mut mv);
        let dot = |a: &[f32], b: &[f32]| -> f64 {
            a.iter()
                .zip(b)
                .map(|(&x, &y)| f64::from(x) * f64::from(y))
                .sum()
        };
        let (a, b) = (dot(&v, &mu), dot(&u, &mv));
        assert!((a - b).abs() < 1e-4 * a.abs().max(b.abs()), "{a} vs {b}");
        assert!(dot(&u, &mu) > 0.0 && dot(&v, &mv) > 0.0);
    }

    /// As a stationary iteration the V-cycle alone must converge fast on a masked problem.
    #[test]
    fn vcycle_reduces_residual() {
        let (h, w) = (130, 97);
        let mask = disc_mask(h, w);
        let st = MaskStencil::new(&mask, h, w);
        let mut hier = Hierarchy::new(&st);
        // Consistent RHS: A of some field.
        let xt: Vec<f32> = (0..h * w)
            .map(|i| {
                if mask[i] {
                    ((i % w) as f32 * 0.1).sin() * 5.0
                } else {
                    0.0
                }
            })
            .collect();
        let b = apply_a(&st, &xt);
        let norm = |v: &[f32]| v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
        let mut x = vec![0f32; h * w];
        let mut r = b.clone();
        let mut e = vec![0f32; h * w];
        let mut last = norm(&r);
        for _ in 0..5 {
            hier.apply(&st, &r, &mut e);
            for i in 0..h * w {
                x[i] += e[i];
            }
            let ax = apply_a(&st, &x);
            for i in 0..h * w {
                r[i] = b[i] - ax[i];
            }
            let now = norm(&r);
            assert!(now < 0.35 * last, "V-cycle factor {}", now / last);
            last = now;
        }
    }
}
