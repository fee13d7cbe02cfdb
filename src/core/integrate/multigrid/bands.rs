//! Row-band buffers of the multigrid's passes.
//!
//! Every pass over a level is parallel over bands of rows (an even number of rows each, so
//! that coarse rows belong to exactly one band) and sequential inside a band, streaming the
//! rows through small ring buffers. Each pass fuses several sweeps, so one pass reads and
//! writes each large array once. Kernels that update an array in place first copy the
//! rows just outside every band ("ghosts"), so bands never read rows another band writes.

use super::stencil::Stencil;

/// Band partition of `h` rows.
#[derive(Clone, Copy)]
pub(crate) struct Bands {
    pub(crate) rows: usize,
    pub(super) count: usize,
}

impl Bands {
    pub(crate) fn new(h: usize, w: usize) -> Self {
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
pub(super) fn ghosts(x: &[f32], h: usize, w: usize, bands: Bands, halo: usize, g: &mut [f32]) {
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
pub(super) struct Work {
    pub(super) bands: Bands,
    pub(super) scratch: Vec<Scratch>,
    pub(super) ghost: [Vec<f32>; 2],
}

impl Work {
    pub(super) fn new(h: usize, w: usize) -> Self {
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
    pub(super) fn split(
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
pub(super) fn fetch<'a>(
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
pub(super) struct Ring {
    data: Vec<f32>,
    w: usize,
}

impl Ring {
    pub(super) fn new(w: usize) -> Self {
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
    pub(super) fn row(&self, k: isize) -> &[f32] {
        let s = Self::slot(k) * self.w;
        &self.data[s..s + self.w]
    }
    #[inline(always)]
    pub(super) fn row_mut(&mut self, k: isize) -> &mut [f32] {
        let s = Self::slot(k) * self.w;
        &mut self.data[s..s + self.w]
    }
    /// Rows `k − 1`, `k`, `k + 1`.
    #[inline(always)]
    pub(super) fn window(&self, k: isize) -> [&[f32]; 3] {
        [self.row(k - 1), self.row(k), self.row(k + 1)]
    }
}

/// Per-task scratch: two ring buffers of values, rings of the diagonal and its inverse, a
/// row buffer and a zero row.
pub(super) struct Scratch {
    pub(super) a: Ring,
    pub(super) b: Ring,
    /// Right-hand-side rows.
    pub(super) f: Ring,
    pub(super) d: Ring,
    pub(super) inv: Ring,
    pub(super) nb: Vec<f32>,
    pub(super) zeros: Vec<f32>,
    /// `!0` on the cells with `c` even, then on the cells with `c` odd; 0 elsewhere.
    pub(super) parity: [Vec<u32>; 2],
}

impl Scratch {
    pub(super) fn new(w: usize) -> Self {
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
    pub(super) fn load_diag<S: Stencil>(&mut self, st: &S, k: isize, h: usize) {
        let (d, inv) = (self.d.row_mut(k), self.inv.row_mut(k));
        if in_grid(k, h) {
            st.diag_row(k as usize, &mut d[..], &mut inv[..]);
        } else {
            d.fill(0.0);
            inv.fill(0.0);
        }
    }
}

#[inline(always)]
pub(super) fn in_grid(k: isize, h: usize) -> bool {
    k >= 0 && (k as usize) < h
}

/// Ghost rows needed by the pre-smoother (two sweeps deep).
pub(super) const PRE_HALO: usize = 2;

/// Ghost rows needed by the post-smoother (two sweeps deep).
pub(super) const POST_HALO: usize = 2;
