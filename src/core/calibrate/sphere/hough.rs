//! Candidate centres and radii (the sphere's notes, steps 2 and 3): the edge points'
//! gradient lines voting for centres (a Hough transform over centres, and per octave of
//! distance in cells of a constant angle), and per centre the radius whose edge points
//! cover the most 1° sectors of the circle.

use ndarray::Array2;

use super::edges::Edge;
use crate::core::calibrate::circle::Circle;

/// Smallest radius searched, pixels.
pub(super) const MIN_RADIUS: f64 = 8.0;

/// Sectors of the coverage count (per full turn).
pub(super) const SECTORS: usize = 360;

/// Candidate centres tried per ball.
const CANDIDATES: usize = 12;
/// Distance octaves from this far are also voted in coarse cells (the sphere's notes,
/// step 2), pixels.
const OCTAVES_FROM: f64 = 64.0;
/// An octave's cells are its start divided by this.
const OCTAVE_CELLS: f64 = 16.0;
/// Candidates kept per octave.
const OCTAVE_CANDIDATES: usize = 4;

/// The pixels of the (3×3-smoothed) accumulator of the edge points' gradient lines, each
/// voting for the centres of the circles it could lie on: (votes, row, column), the most
/// first.
pub(super) fn ranked_peaks(
    edges: &[Edge],
    w: usize,
    h: usize,
    max_radius: f64,
) -> Vec<(u32, usize, usize)> {
    let mut acc = Array2::<u32>::zeros((h, w));
    for e in edges {
        for sign in [-1.0f32, 1.0] {
            let mut t = MIN_RADIUS as f32;
            while t <= max_radius as f32 {
                let (x, y) = (e.x + sign * t * e.ux, e.y + sign * t * e.uy);
                if x < 0.0 || y < 0.0 || x > (w - 1) as f32 || y > (h - 1) as f32 {
                    break;
                }
                // Rounded (both are at least 0).
                acc[[(y + 0.5) as usize, (x + 0.5) as usize]] += 1;
                t += 1.0;
            }
        }
    }
    let mut smooth = Array2::<u32>::zeros((h, w));
    for r in 1..h - 1 {
        for c in 1..w - 1 {
            let mut s = 0;
            for dr in 0..3 {
                for dc in 0..3 {
                    s += acc[[r + dr - 1, c + dc - 1]];
                }
            }
            smooth[[r, c]] = s;
        }
    }
    drop(acc);
    let mut peaks: Vec<(u32, usize, usize)> = smooth
        .indexed_iter()
        .filter(|&(_, &v)| v > 0)
        .map(|((r, c), &v)| (v, r, c))
        .collect();
    peaks.sort_unstable_by_key(|p| std::cmp::Reverse(p.0));
    peaks
}

/// The octaves' candidate centres (the sphere's notes, step 2): per octave of distance
/// from [`OCTAVES_FROM`], the edge points' votes cast from that far (every quarter cell)
/// counted in cells 1/[`OCTAVE_CELLS`] of the octave's start wide, summed over 2 × 2
/// cells; the strongest [`OCTAVE_CANDIDATES`] local maxima, as (x, y, cell width).
pub(super) fn octave_peaks(
    edges: &[Edge],
    w: usize,
    h: usize,
    max_radius: f64,
) -> Vec<(f64, f64, f64)> {
    let mut found = Vec::new();
    let mut start = OCTAVES_FROM;
    while start < max_radius {
        let end = (2.0 * start).min(max_radius);
        let cell = start / OCTAVE_CELLS;
        let (cw, ch) = (
            (w as f64 / cell) as usize + 1,
            (h as f64 / cell) as usize + 1,
        );
        let mut acc = Array2::<u32>::zeros((ch, cw));
        for e in edges {
            for sign in [-1.0f32, 1.0] {
                // A vote every quarter cell: about four in each cell the line crosses.
                let (mut t, step) = (start as f32, (cell as f32 / 4.0).max(1.0));
                let per_cell = 1.0 / cell as f32;
                while t < end as f32 {
                    let (x, y) = (e.x + sign * t * e.ux, e.y + sign * t * e.uy);
                    if x < 0.0 || y < 0.0 || x > (w - 1) as f32 || y > (h - 1) as f32 {
                        break;
                    }
                    acc[[(y * per_cell) as usize, (x * per_cell) as usize]] += 1;
                    t += step;
                }
            }
        }
        // sums[i, j] covers cells i..=i + 1, j..=j + 1: centred at (i + 1, j + 1) cells.
        let sums = Array2::from_shape_fn((ch - 1, cw - 1), |(i, j)| {
            acc[[i, j]] + acc[[i + 1, j]] + acc[[i, j + 1]] + acc[[i + 1, j + 1]]
        });
        let (sh, sw) = sums.dim();
        let mut maxima: Vec<(u32, usize, usize)> = sums
            .indexed_iter()
            .filter(|&((i, j), &v)| {
                v > 0
                    && (i.saturating_sub(1)..(i + 2).min(sh))
                        .all(|a| (j.saturating_sub(1)..(j + 2).min(sw)).all(|b| sums[[a, b]] <= v))
            })
            .map(|((i, j), &v)| (v, i, j))
            .collect();
        maxima.sort_unstable_by_key(|m| std::cmp::Reverse(m.0));
        found.extend(
            maxima
                .iter()
                .take(OCTAVE_CANDIDATES)
                .map(|&(_, i, j)| ((j + 1) as f64 * cell, (i + 1) as f64 * cell, cell)),
        );
        start *= 2.0;
    }
    found
}

/// An octave's candidate (x, y) centred from coarse to fine: on a grid of steps from half
/// its `cell` down to a pixel (5 × 5 at first, then 3 × 3 about the last best), each
/// time the point whose best radius covers the most sectors (counting a band as wide as
/// the step); the last (sectors, circle). Only the edge points that could lie on a
/// circle of the octave about the cell count: within its distances (and a margin of two
/// cells), their gradient within about 37° of radial (the centre moves by a cell at most,
/// 3.6° as seen from the octave's start).
pub(super) fn centred(
    edges: &[Edge],
    x: f64,
    y: f64,
    cell: f64,
    max_radius: f64,
) -> Option<(usize, Circle)> {
    let start = cell * OCTAVE_CELLS;
    let (near, far) = (start - 2.0 * cell, 2.0 * start + 2.0 * cell);
    let edges: Vec<Edge> = edges
        .iter()
        .filter(|e| {
            let (dx, dy) = (e.x as f64 - x, e.y as f64 - y);
            let d = (dx * dx + dy * dy).sqrt();
            d >= near && d <= far && (e.ux as f64 * dx + e.uy as f64 * dy).abs() >= 0.8 * d
        })
        .copied()
        .collect();
    let edges = &edges[..];
    let mut step = (0.5 * cell).max(1.0);
    let (mut cx, mut cy) = (x, y);
    let mut reach = 2;
    loop {
        let band = step.round().max(1.0) as usize;
        let mut best: Option<(usize, Circle)> = None;
        for i in -reach..=reach {
            for j in -reach..=reach {
                let (px, py) = (cx + j as f64 * step, cy + i as f64 * step);
                if let Some((cover, r)) =
                    best_radius(edges, px, py, (near, far.min(max_radius)), band)
                    && best.is_none_or(|(b, _)| cover > b)
                {
                    best = Some((cover, Circle { cx: px, cy: py, r }));
                }
            }
        }
        let (_, c) = best?;
        (cx, cy) = (c.cx, c.cy);
        if step <= 1.0 {
            return best;
        }
        step = (0.5 * step).max(1.0);
        reach = 1;
    }
}

/// Candidate centres: the strongest [`CANDIDATES`] peaks at least `apart` px apart,
/// leaving out those `skip` says (x, y).
pub(super) fn pick_centres(
    peaks: &[(u32, usize, usize)],
    apart: f64,
    skip: &impl Fn(f64, f64) -> bool,
) -> Vec<(f64, f64)> {
    let mut chosen: Vec<(f64, f64)> = Vec::new();
    for &(_, r, c) in peaks {
        let (x, y) = (c as f64, r as f64);
        if !skip(x, y)
            && chosen
                .iter()
                .all(|&(px, py)| (px - x).hypot(py - y) >= apart)
        {
            chosen.push((x, y));
            if chosen.len() == CANDIDATES {
                break;
            }
        }
    }
    chosen
}

/// The share of `circle`'s outline its edge points trace: of its sectors (1° or, on a
/// small circle, about a pixel of its circumference each), those holding an edge point
/// within 1.5 px of it whose gradient points radially (as [`best_radius`] counts them).
pub(super) fn traced_share(edges: &[Edge], circle: &Circle) -> f64 {
    let n = ((std::f64::consts::TAU * circle.r) as usize).clamp(1, SECTORS);
    let mut hit = vec![false; n];
    for e in edges {
        let (dx, dy) = (e.x as f64 - circle.cx, e.y as f64 - circle.cy);
        let d = dx.hypot(dy);
        if (d - circle.r).abs() > 1.5 || d == 0.0 {
            continue;
        }
        if ((e.ux as f64 * dx + e.uy as f64 * dy) / d).abs() < 0.9 {
            continue;
        }
        let angle = dy.atan2(dx).rem_euclid(std::f64::consts::TAU);
        hit[((angle / std::f64::consts::TAU * n as f64) as usize).min(n - 1)] = true;
    }
    hit.iter().filter(|&&h| h).count() as f64 / n as f64
}

/// The radius about (cx, cy), between `radii` (and at least [`MIN_RADIUS`]), whose
/// radially oriented edge points cover the most 1° sectors (counting a ±`band` px band),
/// and that count.
pub(super) fn best_radius(
    edges: &[Edge],
    cx: f64,
    cy: f64,
    radii: (f64, f64),
    band: usize,
) -> Option<(usize, f64)> {
    let (near, far) = (radii.0.max(MIN_RADIUS), radii.1);
    if far < near {
        return None;
    }
    // Bin i holds the distances that round to first + i.
    let first = (near.round() as usize).saturating_sub(band);
    let bins = far.round() as usize + band + 1 - first;
    let mut sectors = vec![[0u64; SECTORS.div_ceil(64)]; bins];
    let mut sums = vec![(0.0f64, 0usize); bins];
    for e in edges {
        let (dx, dy) = (e.x as f64 - cx, e.y as f64 - cy);
        let d = (dx * dx + dy * dy).sqrt();
        if d < near || d > far {
            continue;
        }
        if ((e.ux as f64 * dx + e.uy as f64 * dy) / d).abs() < 0.9 {
            continue;
        }
        let bin = d.round() as usize - first;
        // Single precision is ample for 1° sectors, and twice as fast.
        let angle = (dy as f32)
            .atan2(dx as f32)
            .rem_euclid(std::f32::consts::TAU);
        let s = ((angle / std::f32::consts::TAU * SECTORS as f32) as usize).min(SECTORS - 1);
        sectors[bin][s / 64] |= 1 << (s % 64);
        sums[bin].0 += d;
        sums[bin].1 += 1;
    }
    let mut best: Option<(usize, f64)> = None;
    for bin in band..bins - band {
        let mut words = [0u64; SECTORS.div_ceil(64)];
        for b in bin - band..=bin + band {
            for (w, s) in words.iter_mut().zip(&sectors[b]) {
                *w |= s;
            }
        }
        let cover = words.iter().map(|w| w.count_ones() as usize).sum();
        if best.is_none_or(|b| cover > b.0) {
            let (s, n) = (bin - band..=bin + band)
                .fold((0.0, 0), |acc, b| (acc.0 + sums[b].0, acc.1 + sums[b].1));
            best = Some((cover, s / n.max(1) as f64));
        }
    }
    best
}
