//! The pieces of an integrated surface: the parts of the mask that depth steps separate.
//! Normals cannot say how far apart two pieces are (each could slide along its rays), but
//! near lights can, so each large piece gets its own scale.

use ndarray::Array2;

use crate::core::integrate::LogDepth;

/// A 4-neighbour pair is a step when the integrated `ζ` (`−fx ln D`, pixels) changes
/// across it by more than this beyond the mean of the two pixels' own slopes.
const STEP_PX: f32 = 1.0;

/// Pieces at least this fraction of the mask get their own scale; the others keep the
/// whole surface's.
pub const MIN_PIECE: f64 = 0.02;

/// Each mask pixel's piece (0, 1, …; `usize::MAX` off the mask) and the pieces' sizes:
/// connected through pairs that are neither steps of the integrated `ζ` under the slopes
/// `p` (along columns) and `q` (along rows) nor edges the integration cut. Its cuts count
/// where the jump does not: a rim that grazes the rays has slopes of many pixels, within
/// which the step it leaves hides.
pub fn pieces(
    surface: &LogDepth,
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
) -> (Array2<usize>, Vec<usize>) {
    let (h, w) = mask.dim();
    let zeta = &surface.zeta;
    let mut label = Array2::from_elem((h, w), usize::MAX);
    let mut sizes = Vec::new();
    let mut stack = Vec::new();
    let cut = |(r, c): (usize, usize), east: bool| {
        surface.cuts.as_ref().is_some_and(|k| {
            let edges = if east { &k.east } else { &k.south };
            edges[r * w + c]
        })
    };
    // `a` before `b`, east of it or south.
    let joined = |a: (usize, usize), b: (usize, usize), east: bool| {
        let g = if east { p } else { q };
        mask[b] && !cut(a, east) && ((zeta[b] - zeta[a]) - 0.5 * (g[a] + g[b])).abs() <= STEP_PX
    };
    for start in 0..h * w {
        let s = (start / w, start % w);
        if !mask[s] || label[s] != usize::MAX {
            continue;
        }
        let id = sizes.len();
        let mut size = 0;
        label[s] = id;
        stack.push(s);
        while let Some((r, c)) = stack.pop() {
            size += 1;
            let here = (r, c);
            let mut visit = |n: (usize, usize), east: bool, forward: bool| {
                let (a, b) = if forward { (here, n) } else { (n, here) };
                if label[n] == usize::MAX && joined(a, b, east) && mask[a] {
                    label[n] = id;
                    stack.push(n);
                }
            };
            if c + 1 < w {
                visit((r, c + 1), true, true);
            }
            if c > 0 {
                visit((r, c - 1), true, false);
            }
            if r + 1 < h {
                visit((r + 1, c), false, true);
            }
            if r > 0 {
                visit((r - 1, c), false, false);
            }
        }
        sizes.push(size);
    }
    (label, sizes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::integrate::Cuts;

    fn plain(zeta: Array2<f32>) -> LogDepth {
        LogDepth { zeta, cuts: None }
    }

    /// A plane with a raised square: two pieces; without the step, one.
    #[test]
    fn a_step_all_round_makes_two_pieces() {
        let n = 20;
        let flat = Array2::<f32>::zeros((n, n));
        let mask = Array2::from_elem((n, n), true);
        let zeta = Array2::from_shape_fn((n, n), |(r, c)| {
            if (5..10).contains(&r) && (5..10).contains(&c) {
                5.0
            } else {
                0.0
            }
        });
        let (label, sizes) = pieces(&plain(zeta), &flat, &flat, &mask);
        assert_eq!(sizes, vec![n * n - 25, 25]);
        assert_eq!(label[[7, 7]], 1);
        let (_, sizes) = pieces(&plain(flat.clone()), &flat, &flat, &mask);
        assert_eq!(sizes, vec![n * n]);
    }

    /// The integration's cuts separate a piece whose jump hides within its rim's slopes.
    #[test]
    fn cut_edges_separate_pieces_without_a_jump() {
        let n = 12;
        let flat = Array2::<f32>::zeros((n, n));
        let mask = Array2::from_elem((n, n), true);
        let inside = |r: usize, c: usize| (3..7).contains(&r) && (3..7).contains(&c);
        let mut cuts = Cuts {
            east: vec![false; n * n],
            south: vec![false; n * n],
        };
        for r in 0..n {
            for c in 0..n {
                cuts.east[r * n + c] = c + 1 < n && inside(r, c) != inside(r, c + 1);
                cuts.south[r * n + c] = r + 1 < n && inside(r, c) != inside(r + 1, c);
            }
        }
        let surface = LogDepth {
            zeta: flat.clone(),
            cuts: Some(cuts),
        };
        let (label, sizes) = pieces(&surface, &flat, &flat, &mask);
        assert_eq!(sizes, vec![n * n - 16, 16]);
        assert_eq!(label[[4, 4]], 1);
    }
}
