//! The mask's bounding box: grid solvers pay for every cell of their grid, so one whose
//! object fills a fraction of the frame works on the box around it instead.

/// A window `[r0, r0 + h) × [c0, c0 + w)` of a row-major frame `width` wide.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Crop {
    pub(super) r0: usize,
    pub(super) c0: usize,
    pub(super) h: usize,
    pub(super) w: usize,
    width: usize,
}

impl Crop {
    /// The smallest window holding every mask pixel of the `h × w` frame; None for an empty
    /// mask.
    pub(super) fn of_mask(mask: &[bool], h: usize, w: usize) -> Option<Self> {
        let rows = (0..h).filter(|&r| mask[r * w..(r + 1) * w].iter().any(|&m| m));
        let (mut r0, mut r1) = (usize::MAX, 0);
        let (mut c0, mut c1) = (usize::MAX, 0);
        for r in rows {
            let row = &mask[r * w..(r + 1) * w];
            let first = row.iter().position(|&m| m).expect("row has a mask pixel");
            let last = row.iter().rposition(|&m| m).expect("row has a mask pixel");
            (r0, r1) = (r0.min(r), r + 1);
            (c0, c1) = (c0.min(first), c1.max(last + 1));
        }
        (r0 < r1).then_some(Self {
            r0,
            c0,
            h: r1 - r0,
            w: c1 - c0,
            width: w,
        })
    }

    /// The window's part of a frame-sized slice, row-major.
    pub(super) fn cut<T: Copy>(&self, frame: &[T]) -> Vec<T> {
        (0..self.h)
            .flat_map(|r| {
                let start = (self.r0 + r) * self.width + self.c0;
                frame[start..start + self.w].iter().copied()
            })
            .collect()
    }

    /// A frame-sized vector holding `window` in its place and `fill` elsewhere.
    pub(super) fn paste<T: Copy>(&self, window: &[T], frame_h: usize, fill: T) -> Vec<T> {
        let mut frame = vec![fill; frame_h * self.width];
        for (r, row) in window.chunks_exact(self.w).enumerate() {
            let start = (self.r0 + r) * self.width + self.c0;
            frame[start..start + self.w].copy_from_slice(row);
        }
        frame
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_box_holds_the_mask_and_pasting_undoes_cutting() {
        let (h, w) = (5, 6);
        let mut mask = vec![false; h * w];
        for (r, c) in [(1, 2), (3, 4), (2, 1)] {
            mask[r * w + c] = true;
        }
        let crop = Crop::of_mask(&mask, h, w).unwrap();
        assert_eq!((crop.r0, crop.c0, crop.h, crop.w), (1, 1, 3, 4));
        let values: Vec<usize> = (0..h * w).collect();
        let window = crop.cut(&values);
        assert_eq!(window.len(), 12);
        assert_eq!(window[0], w + 1);
        let back = crop.paste(&window, h, usize::MAX);
        for (i, (&b, &v)) in back.iter().zip(&values).enumerate() {
            let (r, c) = (i / w, i % w);
            let inside = (1..4).contains(&r) && (1..5).contains(&c);
            assert_eq!(b, if inside { v } else { usize::MAX });
        }
        assert!(Crop::of_mask(&[false; 4], 2, 2).is_none());
    }
}
