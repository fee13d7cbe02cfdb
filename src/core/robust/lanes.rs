//! The robust solve's fast path: one image row at a time, in lanes over its columns, for
//! the pixels whose every observation the Lambertian model explains (lit and within the
//! tolerance, or in attached shadow at the black level, or saturated) and for background
//! pixels with fewer than 3 lit observations. These are most pixels of most captures, and
//! for them the per-pixel search of [`Model::fit`] ends where this ends: at least squares
//! over the lit observations. Every other pixel (a cast shadow, a highlight, a penumbra:
//! something to set aside) is left to the per-pixel fit.
//!
//! The column loops have no branches and run over contiguous rows, so they vectorise.

use super::{Fit, Model, SATURATED, SCALE, implausible};

/// Re-fits the fast path tries; a column whose set still changes after them is left to
/// the per-pixel fit, which has the full search.
const ROUNDS: usize = 3;

/// Per-thread buffers for one row, `cols` lanes each (`keep`: `lights × cols`).
pub(super) struct Lanes {
    g: [Vec<f32>; 3],
    g_all: [Vec<f32>; 3],
    m: [Vec<f32>; 6],
    rhs: [Vec<f32>; 3],
    count: Vec<f32>,
    /// Round 0's count: observations above the dark level and below saturation.
    lit: Vec<f32>,
    keep: Vec<f32>,
    tol: Vec<f32>,
    changed: Vec<f32>,
    bad: Vec<f32>,
    sse: Vec<f32>,
    sse_in: Vec<f32>,
    sse_all: Vec<f32>,
    cost: Vec<f32>,
    cost_all: Vec<f32>,
    within: Vec<f32>,
}

impl Lanes {
    pub(super) fn new(cols: usize, lights: usize) -> Self {
        let v = || vec![0f32; cols];
        Self {
            g: [v(), v(), v()],
            g_all: [v(), v(), v()],
            m: [v(), v(), v(), v(), v(), v()],
            rhs: [v(), v(), v()],
            count: v(),
            lit: v(),
            keep: vec![0.0; cols * lights],
            tol: v(),
            changed: v(),
            bad: v(),
            sse: v(),
            sse_in: v(),
            sse_all: v(),
            cost: v(),
            cost_all: v(),
            within: v(),
        }
    }
}

/// What the fast path decided for one column.
pub(super) enum Settled {
    Fit(Fit),
    /// Left to the per-pixel fit.
    No,
}

/// Settle what can be settled of one row; `rows[k]` is the row in image `k`.
pub(super) fn settle_row(model: &Model, rows: &[&[u16]], s: &mut Lanes, out: &mut Vec<Settled>) {
    settle_row_dispatch(model, rows, s, out)
}

multiversion! {
    fn settle_row_dispatch(model: &Model, rows: &[&[u16]], s: &mut Lanes, out: &mut Vec<Settled>) -> () => settle_row_body
}

#[inline(always)]
fn settle_row_body(model: &Model, rows: &[&[u16]], s: &mut Lanes, out: &mut Vec<Settled>) {
    let n = rows.len();
    let cols = rows[0].len();
    debug_assert!(cols <= s.tol.len());
    let (black, dark) = (model.black, model.dark);
    // Round 0: least squares over the observations above the dark level and below
    // saturation, and (for the background) over all of them.
    clear(&mut s.m);
    clear(&mut s.rhs);
    clear(&mut s.g_all);
    s.count.fill(0.0);
    for (k, row) in rows.iter().enumerate() {
        let (l, p, o) = (model.lights[k], model.pinv[k], outer(model.lights[k]));
        let row = &row[..cols];
        let [m0, m1, m2, m3, m4, m5] = &mut s.m;
        let (m0, m1, m2, m3, m4, m5) = (
            &mut m0[..cols],
            &mut m1[..cols],
            &mut m2[..cols],
            &mut m3[..cols],
            &mut m4[..cols],
            &mut m5[..cols],
        );
        let [b0, b1, b2] = &mut s.rhs;
        let (b0, b1, b2) = (&mut b0[..cols], &mut b1[..cols], &mut b2[..cols]);
        let [a0, a1, a2] = &mut s.g_all;
        let (a0, a1, a2) = (&mut a0[..cols], &mut a1[..cols], &mut a2[..cols]);
        let count = &mut s.count[..cols];
        let keep = &mut s.keep[k * cols..(k + 1) * cols];
        for c in 0..cols {
            let v = row[c] as f32 * SCALE;
            let y = v - black;
            let w = if y > dark && v < SATURATED { 1.0 } else { 0.0 };
            keep[c] = w;
            let wy = w * y;
            m0[c] += w * o[0];
            m1[c] += w * o[1];
            m2[c] += w * o[2];
            m3[c] += w * o[3];
            m4[c] += w * o[4];
            m5[c] += w * o[5];
            b0[c] += wy * l[0];
            b1[c] += wy * l[1];
            b2[c] += wy * l[2];
            count[c] += w;
            a0[c] += p[0] * y;
            a1[c] += p[1] * y;
            a2[c] += p[2] * y;
        }
    }
    // Fewer than 3 lit observations: the per-pixel fit's answer is least squares over
    // all, flagged; more than 4 are needed for the per-pixel fit to test outliers at all.
    s.lit.copy_from_slice(&s.count);
    solve_lanes(s);
    for round in 1..=ROUNDS {
        // Tolerances of the current fit, then the observations it explains.
        for c in 0..cols {
            let g = [s.g[0][c], s.g[1][c], s.g[2][c]];
            s.tol[c] = model.tol(g);
        }
        clear(&mut s.m);
        clear(&mut s.rhs);
        s.count.fill(0.0);
        s.changed.fill(0.0);
        for (k, row) in rows.iter().enumerate() {
            let (l, o) = (model.lights[k], outer(model.lights[k]));
            let row = &row[..cols];
            let keep = &mut s.keep[k * cols..(k + 1) * cols];
            let [gx, gy, gz] = &s.g;
            let (gx, gy, gz) = (&gx[..cols], &gy[..cols], &gz[..cols]);
            let [m0, m1, m2, m3, m4, m5] = &mut s.m;
            let (m0, m1, m2, m3, m4, m5) = (
                &mut m0[..cols],
                &mut m1[..cols],
                &mut m2[..cols],
                &mut m3[..cols],
                &mut m4[..cols],
                &mut m5[..cols],
            );
            let [b0, b1, b2] = &mut s.rhs;
            let (b0, b1, b2) = (&mut b0[..cols], &mut b1[..cols], &mut b2[..cols]);
            let (count, changed, tol) =
                (&mut s.count[..cols], &mut s.changed[..cols], &s.tol[..cols]);
            for c in 0..cols {
                let v = row[c] as f32 * SCALE;
                let y = v - black;
                let pred = gx[c] * l[0] + gy[c] * l[1] + gz[c] * l[2];
                let w = if pred > 0.0 && (y - pred).abs() <= tol[c] && v < SATURATED {
                    1.0
                } else {
                    0.0
                };
                changed[c] += (w - keep[c]).abs();
                keep[c] = w;
                let wy = w * y;
                m0[c] += w * o[0];
                m1[c] += w * o[1];
                m2[c] += w * o[2];
                m3[c] += w * o[3];
                m4[c] += w * o[4];
                m5[c] += w * o[5];
                b0[c] += wy * l[0];
                b1[c] += wy * l[1];
                b2[c] += wy * l[2];
                count[c] += w;
            }
        }
        if s.changed.iter().all(|&d| d == 0.0) {
            break; // every column's set repeated: the fits are final
        }
        if round < ROUNDS {
            solve_lanes(s);
        }
    }
    // The final check, against the current fits `g` and the last sets `keep` (which the
    // fits were solved from only where `changed` is 0): every observation explained,
    // and the costs the per-pixel fit compares.
    s.bad.fill(0.0);
    s.sse.fill(0.0);
    s.sse_in.fill(0.0);
    s.sse_all.fill(0.0);
    s.cost.fill(0.0);
    s.cost_all.fill(0.0);
    s.within.fill(0.0);
    for (k, row) in rows.iter().enumerate() {
        let l = model.lights[k];
        let row = &row[..cols];
        let keep = &s.keep[k * cols..(k + 1) * cols];
        let [gx, gy, gz] = &s.g;
        let (gx, gy, gz) = (&gx[..cols], &gy[..cols], &gz[..cols]);
        let [a0, a1, a2] = &s.g_all;
        let (a0, a1, a2) = (&a0[..cols], &a1[..cols], &a2[..cols]);
        let tol = &s.tol[..cols];
        let (bad, sse, sse_in, sse_all) = (
            &mut s.bad[..cols],
            &mut s.sse[..cols],
            &mut s.sse_in[..cols],
            &mut s.sse_all[..cols],
        );
        let (cost, cost_all, within) = (
            &mut s.cost[..cols],
            &mut s.cost_all[..cols],
            &mut s.within[..cols],
        );
        for c in 0..cols {
            let v = row[c] as f32 * SCALE;
            let y = v - black;
            let pred = gx[c] * l[0] + gy[c] * l[1] + gz[c] * l[2];
            let r = v - (pred.max(0.0) + black).min(1.0);
            let explained = keep[c] > 0.0 || v >= SATURATED || (pred <= 0.0 && y.abs() <= tol[c]);
            bad[c] += if explained { 0.0 } else { 1.0 };
            sse[c] += r * r;
            sse_in[c] += keep[c] * r * r;
            let pa = a0[c] * l[0] + a1[c] * l[1] + a2[c] * l[2];
            let ra = v - (pa.max(0.0) + black).min(1.0);
            sse_all[c] += ra * ra;
            // The per-pixel fit compares the two candidates over the observations the
            // robust fit re-renders within the tolerance.
            let w = if r.abs() <= tol[c] { 1.0 } else { 0.0 };
            cost[c] += w * r * r;
            cost_all[c] += w * ra * ra;
            within[c] += w;
        }
    }
    out.clear();
    out.extend((0..cols).map(|c| {
        let g_all = [s.g_all[0][c], s.g_all[1][c], s.g_all[2][c]];
        if s.lit[c] < 3.0 {
            return Settled::Fit(Fit {
                g: g_all,
                inliers: 0,
                reliable: false,
                sse_all: s.sse_all[c],
                sse_inliers: s.sse_all[c],
            });
        }
        let g = [s.g[0][c], s.g[1][c], s.g[2][c]];
        let kept = s.count[c] as usize;
        let clean = s.lit[c] > 4.0
            && s.changed[c] == 0.0
            && s.bad[c] == 0.0
            && kept >= 3
            && g.iter().all(|v| v.is_finite());
        if !clean {
            return Settled::No;
        }
        // Least squares over every observation is the per-pixel fit's other candidate
        // when it set any aside; the lower shadow-aware cost wins.
        if kept < n && s.cost_all[c] < s.cost[c] {
            let inliers = s.within[c] as usize;
            if implausible(g_all, inliers) {
                return Settled::No;
            }
            return Settled::Fit(Fit {
                g: g_all,
                inliers,
                reliable: true,
                sse_all: s.sse_all[c],
                sse_inliers: s.cost_all[c],
            });
        }
        if implausible(g, kept) {
            return Settled::No;
        }
        Settled::Fit(Fit {
            g,
            inliers: kept,
            reliable: true,
            sse_all: s.sse[c],
            sse_inliers: s.sse_in[c],
        })
    }));
}

fn clear<const K: usize>(v: &mut [Vec<f32>; K]) {
    for x in v.iter_mut() {
        x.fill(0.0);
    }
}

/// lᵢlᵢᵀ packed (xx, xy, xz, yy, yz, zz).
fn outer(l: [f32; 3]) -> [f32; 6] {
    [
        l[0] * l[0],
        l[0] * l[1],
        l[0] * l[2],
        l[1] * l[1],
        l[1] * l[2],
        l[2] * l[2],
    ]
}

/// g = M⁻¹ rhs per column by cofactors; a (near-)singular M gives non-finite g, which
/// the final check leaves to the per-pixel fit.
fn solve_lanes(s: &mut Lanes) {
    let [m0, m1, m2, m3, m4, m5] = &s.m;
    let [b0, b1, b2] = &s.rhs;
    let [gx, gy, gz] = &mut s.g;
    for c in 0..gx.len() {
        let (a, b, cc, d, e, f) = (m0[c], m1[c], m2[c], m3[c], m4[c], m5[c]);
        let c00 = d * f - e * e;
        let c01 = cc * e - b * f;
        let c02 = b * e - cc * d;
        let c11 = a * f - cc * cc;
        let c12 = b * cc - a * e;
        let c22 = a * d - b * b;
        let det = a * c00 + b * c01 + cc * c02;
        let scale = a.max(d).max(f);
        let inv = if det.abs() > 1e-6 * scale * scale * scale {
            1.0 / det
        } else {
            f32::NAN
        };
        gx[c] = (c00 * b0[c] + c01 * b1[c] + c02 * b2[c]) * inv;
        gy[c] = (c01 * b0[c] + c11 * b1[c] + c12 * b2[c]) * inv;
        gz[c] = (c02 * b0[c] + c12 * b1[c] + c22 * b2[c]) * inv;
    }
}
