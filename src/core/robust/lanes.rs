//! The robust solve's fast path: one image row at a time, in lanes over its columns, for
//! the pixels whose every observation the Lambertian model explains (lit and within the
//! tolerance, or in attached shadow at the black level, or saturated) and for background
//! pixels with fewer than 3 lit observations. These are most pixels of most captures, and
//! for them the per-pixel search of [`Model::fit`] ends where this ends: at least squares
//! over the lit observations. Every other pixel (a cast shadow, a highlight, a penumbra:
//! something to set aside) is left to the per-pixel fit.
//!
//! Columns go in chunks of [`W`], one vector register wide: each chunk's sums stay in
//! registers while the loop runs over the lights, so a pass over a chunk stores nothing
//! but its inlier sets, and a chunk stops re-fitting as soon as its own sets repeat.

use super::fit::{Fit, Model, SATURATED, SCALE, implausible};

/// Re-fits the fast path tries; a column whose set still changes after them is left to
/// the per-pixel fit, which has the full search.
const ROUNDS: usize = 3;

/// Columns per chunk: eight f32 lanes, one AVX2 register.
const W: usize = 8;
type V = [f32; W];
const ZERO: V = [0.0; W];

/// What the fast path decided for one column.
pub(super) enum Settled {
    Fit(Fit),
    /// Left to the per-pixel fit.
    No,
}

/// Settle what can be settled of one row; `rows[k]` is the row in image `k`.
pub(super) fn settle_row(model: &Model, rows: &[&[u16]], out: &mut Vec<Settled>) {
    settle_row_dispatch(model, rows, out)
}

multiversion! {
    fn settle_row_dispatch(model: &Model, rows: &[&[u16]], out: &mut Vec<Settled>) -> () => settle_row_body
}

#[inline(always)]
fn settle_row_body(model: &Model, rows: &[&[u16]], out: &mut Vec<Settled>) {
    out.clear();
    let cols = rows.first().map_or(0, |r| r.len());
    // The row in [0, 1] units, converted image by image and padded with zeros to whole
    // chunks (lanes whose answer is dropped): one sequential pass per image keeps many
    // loads in flight, where the chunks' first pass, reading every image a few bytes at a
    // time, stalled on each cache miss in turn.
    let stride = cols.next_multiple_of(W);
    let mut values = Vec::with_capacity(rows.len() * stride);
    for row in rows {
        values.extend(row.iter().map(|&x| x as f32 * SCALE));
        values.resize(values.len() + stride - cols, 0.0);
    }
    let rows: Vec<&[f32]> = values.chunks_exact(stride.max(W)).collect();
    // One chunk's inlier sets, `W` lanes per light.
    let mut keep = vec![ZERO; rows.len()];
    for c0 in (0..cols).step_by(W) {
        let fits = settle_chunk(model, &rows, c0, &mut keep);
        out.extend(fits.into_iter().take(cols - c0));
    }
}

/// One chunk's `W` lanes of a padded row from column `c0`.
#[inline(always)]
fn load(row: &[f32], c0: usize) -> V {
    row[c0..c0 + W]
        .try_into()
        .expect("rows are padded to whole chunks")
}

/// Least squares sums: the normal matrix packed (xx, xy, xz, yy, yz, zz), the right-hand
/// side and the number of observations, per lane.
#[derive(Clone, Copy)]
struct Sums {
    m: [V; 6],
    rhs: [V; 3],
    count: V,
}

impl Sums {
    const EMPTY: Sums = Sums {
        m: [ZERO; 6],
        rhs: [ZERO; 3],
        count: ZERO,
    };

    #[inline(always)]
    fn add(&mut self, l: [f32; 3], o: [f32; 6], w: V, y: V) {
        for j in 0..W {
            let wy = w[j] * y[j];
            for i in 0..6 {
                self.m[i][j] += w[j] * o[i];
            }
            for i in 0..3 {
                self.rhs[i][j] += wy * l[i];
            }
            self.count[j] += w[j];
        }
    }
}

/// The final check's sums against a fit (see [`settle_chunk`]).
#[derive(Clone, Copy)]
struct Check {
    changed: V,
    bad: V,
    sse: V,
    sse_in: V,
    sse_all: V,
    cost: V,
    cost_all: V,
    within: V,
}

#[inline(always)]
fn settle_chunk(model: &Model, rows: &[&[f32]], c0: usize, keep: &mut [V]) -> [Settled; W] {
    let n = rows.len();
    let (black, dark) = (model.black, model.dark);
    // Round 0: the observations above the dark level and below saturation, and least
    // squares over all observations (the background's answer, and the final check's
    // other candidate); a second pass sums the kept ones where a column has 3 of them.
    // Two passes, each with few accumulators, keep them all in registers.
    let mut lit = ZERO;
    let mut g_all = [ZERO; 3];
    for (k, row) in rows.iter().enumerate() {
        let p = model.pinv[k];
        let v = load(row, c0);
        let mut w = ZERO;
        for j in 0..W {
            let y = v[j] - black;
            w[j] = if y > dark && v[j] < SATURATED {
                1.0
            } else {
                0.0
            };
            lit[j] += w[j];
            for i in 0..3 {
                g_all[i][j] += p[i] * y;
            }
        }
        keep[k] = w;
    }
    // Fewer than 3 lit observations: the per-pixel fit's answer is least squares over
    // all, flagged; more than 4 are needed for the per-pixel fit to test outliers at all.
    if lit.iter().all(|&l| l < 3.0) {
        // Background: only that answer's residuals are needed.
        return background_chunk(model, rows, c0, &g_all);
    }
    let mut sums = kept_sums(model, rows, c0, keep);
    let mut g = solve(&sums);
    let mut tol = ZERO;
    let mut check;
    let mut round = 1;
    loop {
        // Tolerances of the current fit; then, in one pass, the observations it explains
        // and the final check against it. Whichever round is the last (a repeat, or the
        // last allowed), that pass's check is the answer.
        for j in 0..W {
            tol[j] = model.tol([g[0][j], g[1][j], g[2][j]]);
        }
        check = Check {
            changed: ZERO,
            bad: ZERO,
            sse: ZERO,
            sse_in: ZERO,
            sse_all: ZERO,
            cost: ZERO,
            cost_all: ZERO,
            within: ZERO,
        };
        for (k, row) in rows.iter().enumerate() {
            let l = model.lights[k];
            let v = load(row, c0);
            let mut w = ZERO;
            for j in 0..W {
                let y = v[j] - black;
                let pred = g[0][j] * l[0] + g[1][j] * l[1] + g[2][j] * l[2];
                w[j] = if pred > 0.0 && (y - pred).abs() <= tol[j] && v[j] < SATURATED {
                    1.0
                } else {
                    0.0
                };
                check.changed[j] += (w[j] - keep[k][j]).abs();
                // Every observation explained, and the costs the per-pixel fit compares.
                let r = v[j] - (pred.max(0.0) + black).min(1.0);
                let explained =
                    w[j] > 0.0 || v[j] >= SATURATED || (pred <= 0.0 && y.abs() <= tol[j]);
                check.bad[j] += if explained { 0.0 } else { 1.0 };
                check.sse[j] += r * r;
                check.sse_in[j] += w[j] * r * r;
                let ra = residual_all(&g_all, l, v[j], black, j);
                check.sse_all[j] += ra * ra;
                // The per-pixel fit compares the two candidates over the observations
                // the robust fit re-renders within the tolerance.
                let near = if r.abs() <= tol[j] { 1.0 } else { 0.0 };
                check.cost[j] += near * r * r;
                check.cost_all[j] += near * ra * ra;
                check.within[j] += near;
            }
            keep[k] = w;
        }
        if check.changed.iter().all(|&d| d == 0.0) || round == ROUNDS {
            // Every lane's set repeated (its fit, and `sums`, are final), or no re-fits
            // left: lanes whose set still changes are left to the per-pixel fit.
            break;
        }
        sums = kept_sums(model, rows, c0, keep);
        g = solve(&sums);
        round += 1;
    }
    decide(
        &Ended {
            lit,
            g_all,
            g,
            kept: sums.count,
            check,
        },
        n,
    )
}

/// A chunk's state when its rounds have ended.
struct Ended {
    lit: V,
    g_all: [V; 3],
    g: [V; 3],
    kept: V,
    check: Check,
}

/// Each lane's answer from its chunk's final state. Not inlined on purpose: reading lanes
/// by a run-time index here would keep the chunk's sums in memory for the whole of
/// [`settle_chunk`] (every accumulation a load and a store); given a copy, they stay in
/// registers.
#[inline(never)]
fn decide(e: &Ended, n: usize) -> [Settled; W] {
    let check = &e.check;
    std::array::from_fn(|j| {
        let g_all = [e.g_all[0][j], e.g_all[1][j], e.g_all[2][j]];
        if e.lit[j] < 3.0 {
            return unlit(g_all, check.sse_all[j]);
        }
        let g = [e.g[0][j], e.g[1][j], e.g[2][j]];
        let kept = e.kept[j] as usize;
        let clean = e.lit[j] > 4.0
            && check.changed[j] == 0.0
            && check.bad[j] == 0.0
            && kept >= 3
            && g.iter().all(|v| v.is_finite());
        if !clean {
            return Settled::No;
        }
        // Least squares over every observation is the per-pixel fit's other candidate
        // when it set any aside; the lower shadow-aware cost wins.
        if kept < n && check.cost_all[j] < check.cost[j] {
            let inliers = check.within[j] as usize;
            if implausible(g_all, inliers) {
                return Settled::No;
            }
            return Settled::Fit(Fit {
                g: g_all,
                inliers,
                reliable: true,
                sse_all: check.sse_all[j],
                sse_inliers: check.cost_all[j],
            });
        }
        if implausible(g, kept) {
            return Settled::No;
        }
        Settled::Fit(Fit {
            g,
            inliers: kept,
            reliable: true,
            sse_all: check.sse[j],
            sse_inliers: check.sse_in[j],
        })
    })
}

/// The least squares sums over the observations in `keep`.
#[inline(always)]
fn kept_sums(model: &Model, rows: &[&[f32]], c0: usize, keep: &[V]) -> Sums {
    let mut sums = Sums::EMPTY;
    for (k, row) in rows.iter().enumerate() {
        let y = load(row, c0).map(|v| v - model.black);
        sums.add(model.lights[k], outer(model.lights[k]), keep[k], y);
    }
    sums
}

/// A chunk none of whose columns has 3 lit observations: least squares over all of them,
/// flagged, with the same residual sums as [`settle_chunk`]'s check forms.
#[inline(always)]
fn background_chunk(model: &Model, rows: &[&[f32]], c0: usize, g_all: &[V; 3]) -> [Settled; W] {
    let black = model.black;
    let mut sse_all = ZERO;
    for (k, row) in rows.iter().enumerate() {
        let l = model.lights[k];
        let v = load(row, c0);
        for j in 0..W {
            let ra = residual_all(g_all, l, v[j], black, j);
            sse_all[j] += ra * ra;
        }
    }
    decide_unlit(*g_all, sse_all)
}

/// [`decide`] for a chunk of background lanes.
#[inline(never)]
fn decide_unlit(g_all: [V; 3], sse_all: V) -> [Settled; W] {
    std::array::from_fn(|j| unlit([g_all[0][j], g_all[1][j], g_all[2][j]], sse_all[j]))
}

/// Lane `j`'s observation `v` of light `l` less least squares over all observations'
/// rendering of it (clipped as the image is).
#[inline(always)]
fn residual_all(g_all: &[V; 3], l: [f32; 3], v: f32, black: f32, j: usize) -> f32 {
    let pa = g_all[0][j] * l[0] + g_all[1][j] * l[1] + g_all[2][j] * l[2];
    v - (pa.max(0.0) + black).min(1.0)
}

/// A lane with fewer than 3 lit observations: least squares over all of them, flagged.
fn unlit(g_all: [f32; 3], sse_all: f32) -> Settled {
    Settled::Fit(Fit {
        g: g_all,
        inliers: 0,
        reliable: false,
        sse_all,
        sse_inliers: sse_all,
    })
}

/// lᵢlᵢᵀ packed (xx, xy, xz, yy, yz, zz).
#[inline(always)]
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

/// g = M⁻¹ rhs per lane by cofactors; a (near-)singular M gives non-finite g, which
/// the final check leaves to the per-pixel fit.
#[inline(always)]
fn solve(s: &Sums) -> [V; 3] {
    let [m0, m1, m2, m3, m4, m5] = &s.m;
    let [b0, b1, b2] = &s.rhs;
    let mut g = [ZERO; 3];
    for c in 0..W {
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
        g[0][c] = (c00 * b0[c] + c01 * b1[c] + c02 * b2[c]) * inv;
        g[1][c] = (c01 * b0[c] + c11 * b1[c] + c12 * b2[c]) * inv;
        g[2][c] = (c02 * b0[c] + c12 * b1[c] + c22 * b2[c]) * inv;
    }
    g
}

#[cfg(test)]
mod tests {
    use super::super::fit::{Buffers, gather};
    use super::*;

    /// Every column the fast path settles gets the per-pixel fit's answer: one row of 21
    /// columns (two chunks and part of a third, so the padding is read) with lit, shadowed,
    /// highlighted and background pixels.
    #[test]
    fn settled_columns_get_the_per_pixel_answer() {
        let lights: Vec<[f32; 3]> = (0..12)
            .map(|k| {
                let (a, e) = (k as f32 * 0.52, 0.5 + 0.08 * (k % 4) as f32);
                [a.cos() * e.cos(), a.sin() * e.cos(), e.sin()]
            })
            .collect();
        let (black, quantum) = (0.01, SCALE / 12f32.sqrt());
        let model = Model::new(lights.clone(), black, 0.002, quantum);
        let cols = 21;
        let mut seed = 7u32;
        let mut noise = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1 << 24) as f32 - 0.5
        };
        let mut images = vec![vec![0u16; cols]; lights.len()];
        for c in 0..cols {
            let tilt = [
                0.4 * (c as f32 * 0.7).sin(),
                0.3 * (c as f32 * 1.3).cos(),
                1.0,
            ];
            let n = tilt.map(|v| v / (tilt[0] * tilt[0] + tilt[1] * tilt[1] + 1.0).sqrt());
            let albedo = if c % 7 == 6 {
                0.0
            } else {
                0.3 + 0.02 * c as f32
            };
            for (k, l) in lights.iter().enumerate() {
                let mut v = black + albedo * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0);
                if c % 5 == 1 && k == c % 12 {
                    v = black; // cast shadow
                }
                if c % 5 == 3 && k == (c + 4) % 12 {
                    v += 0.3; // highlight
                }
                v += 0.002 * noise();
                images[k][c] = (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
            }
        }
        let rows: Vec<&[u16]> = images.iter().map(|r| r.as_slice()).collect();
        let mut settled = Vec::new();
        settle_row(&model, &rows, &mut settled);
        assert_eq!(settled.len(), cols);
        let (mut obs, mut b) = (vec![0f32; lights.len()], Buffers::new(lights.len()));
        let mut fits = 0;
        for (c, s) in settled.iter().enumerate() {
            let Settled::Fit(fast) = s else { continue };
            fits += 1;
            gather(&rows, c, &mut obs);
            let slow = model.judged(&obs, &mut b);
            assert_eq!(
                (fast.inliers, fast.reliable),
                (slow.inliers, slow.reliable),
                "column {c}"
            );
            for k in 0..3 {
                assert!(
                    (fast.g[k] - slow.g[k]).abs() < 1e-4,
                    "column {c}: {fast:?} {slow:?}",
                    fast = fast.g,
                    slow = slow.g
                );
            }
        }
        // Clean and background columns are settled; some others may not be.
        assert!(fits >= 12, "{fits} of {cols} settled");
    }
}
