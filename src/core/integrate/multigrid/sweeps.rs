//! The multigrid's fused band passes (see [`super::bands`]): red–black Gauss–Seidel
//! pre-smoothing fused with the restriction of its residual (and with CG's residual
//! update), the prolongation fused with post-smoothing, and CG's direction update fused
//! with the operator. Each band body is compiled twice (`multiversion!`: baseline and
//! AVX2).

use rayon::prelude::*;

use super::bands::{POST_HALO, PRE_HALO, Scratch, Work, fetch, in_grid};
use super::stencil::Stencil;
use super::sums::{dot_f64, ordered_sum};

/// Bit mask selecting the cells of `colour` (red = 0: `r + c` even) in row `r`.
#[inline(always)]
pub(super) fn colour(parity: &[Vec<u32>; 2], r: usize, colour: usize) -> &[u32] {
    &parity[(r + colour) & 1]
}

/// Gauss–Seidel update of the cells of one colour in row `r`: `out = (b + Σ w x_j) / d`
/// there (0 on inactive cells), `out = keep` elsewhere. `nb` holds the neighbour sum.
#[inline(always)]
pub(super) fn gs_row(
    sel: &[u32],
    b: &[f32],
    nb: &[f32],
    inv: &[f32],
    keep: &[f32],
    out: &mut [f32],
) {
    let n = out.len();
    let (sel, b, nb, inv, keep) = (&sel[..n], &b[..n], &nb[..n], &inv[..n], &keep[..n]);
    // Every cell is computed and the colour picked bitwise, so the loop vectorises.
    for c in 0..n {
        let v = (b[c] + nb[c]) * inv[c];
        out[c] = f32::from_bits((v.to_bits() & sel[c]) | (keep[c].to_bits() & !sel[c]));
    }
}

/// Where the pre-smoother's right-hand side comes from.
pub(super) enum Rhs<'a> {
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
pub(super) fn presmooth_band_body<S: Stencil>(
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

/// Pre-smoothing from a zero guess (red half-sweep, then black) into `x`, fused with the
/// restriction of the resulting residual: `cb = Pᵀ (b − A x)`.
pub(super) fn presmooth_restrict<S: Stencil>(
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
pub(super) fn step_presmooth_restrict<S: Stencil>(
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
pub(super) fn postsmooth_band_body<S: Stencil>(
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

/// Coarse correction and post-smoothing, fused: `x += P xc`, then a black half-sweep, then
/// a red one. Returns `bᵀ x` of the result.
pub(super) fn prolong_postsmooth<S: Stencil>(
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
pub(super) fn direction_band_body<S: Stencil>(
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
pub(super) fn direction_apply<S: Stencil>(
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
pub(crate) fn apply<S: Stencil>(st: &S, x: &[f32], out: &mut [f32]) -> f64 {
    let mut p = vec![0f32; x.len()];
    let mut dummy = vec![0f32; x.len()];
    out.copy_from_slice(x);
    let (h, w) = st.dims();
    direction_apply(st, out, &mut p, &mut dummy, 0.0, 0.0, &mut Work::new(h, w))
}
