//! The coarse levels of the multigrid: a level's operator made from the finer one's
//! (2×2 cells → 1, edges summed and scaled), and the dense Cholesky solve of the coarsest.

use rayon::prelude::*;

use super::bands::Work;
use super::stencil::{Stencil, WeightStencil};

/// Coarse edge weight = this × (sum of the fine edge weights it crosses).
pub(super) const COARSE_SCALE: f32 = 0.5;

/// One coarse level: its operator and work vectors.
pub(super) struct Level {
    pub(super) st: WeightStencil,
    pub(super) x: Vec<f32>,
    pub(super) b: Vec<f32>,
    pub(super) work: Work,
}

pub(super) fn coarsen<S: Stencil>(fine: &S) -> Level {
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
pub(super) struct Dense {
    cells: Vec<usize>,
    chol: Vec<f64>,
}

impl Dense {
    pub(super) fn new<S: Stencil>(st: &S) -> Self {
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

    pub(super) fn solve(&self, b: &[f32], x: &mut [f32]) {
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
