//! 4-connected components of the mask, stored as labelled row runs (no per-pixel label
//! array: a 4096² mask has a few thousand runs, not 16 M labels).

use rayon::prelude::*;

/// Runs summed per rayon task in [`Components::means`].
const RUNS_PER_TASK: usize = 256;

/// A maximal horizontal run of mask pixels `[c0, c1)` in row `r`.
#[derive(Debug, Clone, Copy)]
struct Run {
    r: usize,
    c0: usize,
    c1: usize,
}

/// Connected components of a row-major mask (4-neighbour connectivity, which is exactly
/// the connectivity of the integration graph: an edge joins two adjacent mask pixels).
#[derive(Debug, Clone)]
pub(super) struct Components {
    w: usize,
    runs: Vec<Run>,
    /// Runs of row `r` are `runs[row_start[r]..row_start[r + 1]]`.
    row_start: Vec<usize>,
    labels: Vec<usize>,
    count: usize,
}

fn find(parent: &mut [usize], mut a: usize) -> usize {
    while parent[a] != a {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    a
}

impl Components {
    pub(super) fn new(mask: &[bool], h: usize, w: usize) -> Self {
        let mut runs = Vec::new();
        let mut row_start = Vec::with_capacity(h + 1);
        for r in 0..h {
            row_start.push(runs.len());
            let row = &mask[r * w..(r + 1) * w];
            let mut c = 0;
            while c < w {
                if row[c] {
                    let c0 = c;
                    while c < w && row[c] {
                        c += 1;
                    }
                    runs.push(Run { r, c0, c1: c });
                } else {
                    c += 1;
                }
            }
        }
        row_start.push(runs.len());

        let mut parent: Vec<usize> = (0..runs.len()).collect();
        for r in 1..h {
            let (mut a, a_end) = (row_start[r - 1], row_start[r]);
            let (mut b, b_end) = (row_start[r], row_start[r + 1]);
            while a < a_end && b < b_end {
                let (ra, rb) = (runs[a], runs[b]);
                if ra.c0 < rb.c1 && rb.c0 < ra.c1 {
                    let (x, y) = (find(&mut parent, a), find(&mut parent, b));
                    if x != y {
                        parent[x.max(y)] = x.min(y);
                    }
                }
                if ra.c1 <= rb.c1 {
                    a += 1;
                } else {
                    b += 1;
                }
            }
        }
        let mut labels = vec![usize::MAX; runs.len()];
        let mut count = 0;
        for i in 0..runs.len() {
            let root = find(&mut parent, i);
            if labels[root] == usize::MAX {
                labels[root] = count;
                count += 1;
            }
            labels[i] = labels[root];
        }
        Self {
            w,
            runs,
            row_start,
            labels,
            count,
        }
    }

    #[cfg(test)]
    pub(super) fn count(&self) -> usize {
        self.count
    }

    /// Mean of `data` over each component, accumulated in f64.
    pub(super) fn means(&self, data: &[f32]) -> Vec<f64> {
        let w = self.w;
        let run_sum = |run: &Run| -> (f64, usize) {
            let s = run.r * w;
            let v = &data[s + run.c0..s + run.c1];
            (v.iter().map(|&v| f64::from(v)).sum(), v.len())
        };
        let (sum, n) = if self.count <= 1 << 12 {
            // Few components: per-task accumulators are small, sum fixed chunks of runs in
            // parallel and add the chunks in order (so the means do not depend on how the
            // work was scheduled).
            let parts: Vec<(Vec<f64>, Vec<usize>)> = (self.runs.par_chunks(RUNS_PER_TASK))
                .zip(self.labels.par_chunks(RUNS_PER_TASK))
                .map(|(runs, labels)| {
                    let (mut sum, mut n) = (vec![0.0f64; self.count], vec![0usize; self.count]);
                    for (run, &l) in runs.iter().zip(labels) {
                        let (s, k) = run_sum(run);
                        sum[l] += s;
                        n[l] += k;
                    }
                    (sum, n)
                })
                .collect();
            let (mut sum, mut n) = (vec![0.0f64; self.count], vec![0usize; self.count]);
            for (s, k) in parts {
                sum.iter_mut().zip(&s).for_each(|(a, b)| *a += b);
                n.iter_mut().zip(&k).for_each(|(a, b)| *a += b);
            }
            (sum, n)
        } else {
            let mut sum = vec![0.0f64; self.count];
            let mut n = vec![0usize; self.count];
            for (run, &l) in self.runs.iter().zip(&self.labels) {
                let (s, k) = run_sum(run);
                sum[l] += s;
                n[l] += k;
            }
            (sum, n)
        };
        sum.iter().zip(&n).map(|(&s, &n)| s / n as f64).collect()
    }

    /// Subtract each component's mean from its pixels (pixels off the mask are untouched).
    pub(super) fn remove_means(&self, data: &mut [f32]) {
        let means = self.means(data);
        let w = self.w;
        if w == 0 {
            return;
        }
        let (runs, labels, starts) = (&self.runs, &self.labels, &self.row_start);
        data.par_chunks_mut(w).enumerate().for_each(|(r, row)| {
            for k in starts[r]..starts[r + 1] {
                let (run, m) = (runs[k], means[labels[k]]);
                for v in &mut row[run.c0..run.c1] {
                    *v = (f64::from(*v) - m) as f32;
                }
            }
        });
    }
}
