//! The material an object's pixels share, from the lobes fitted freely on a sample of its
//! pixels: the family most of them took, and the median roughness of that family's.

use super::fit::Material;
use super::lobe::Facets;
use crate::core::reconstruction::Gloss;

/// Fewest freely fitted lobes a shared material is taken from; with fewer, each pixel
/// fits its own width.
const MIN_FITS: usize = 16;

/// The shared material of the lobes kept in `sample` (the free fits of a sample of the
/// object's pixels), or None where fewer than [`MIN_FITS`] were kept.
pub fn shared(sample: &Gloss) -> Option<Material> {
    let kept: Vec<(bool, f32)> = (sample.used.iter())
        .zip(&sample.beckmann)
        .zip(&sample.roughness)
        .filter(|((u, _), _)| **u)
        .map(|((_, b), r)| (*b, *r))
        .collect();
    if kept.len() < MIN_FITS {
        return None;
    }
    let beckmann = kept.iter().filter(|(b, _)| *b).count();
    let facets = if 2 * beckmann > kept.len() {
        Facets::Beckmann
    } else {
        Facets::Ggx
    };
    let mut widths: Vec<f32> = (kept.iter())
        .filter(|(b, _)| *b == (facets == Facets::Beckmann))
        .map(|(_, r)| *r)
        .collect();
    let mid = widths.len() / 2;
    let roughness = f64::from(*widths.select_nth_unstable_by(mid, f32::total_cmp).1);
    Some(Material { facets, roughness })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(lobes: &[(bool, f32)], matte: usize) -> Gloss {
        let n = lobes.len() + matte;
        let mut g = Gloss::zeros(1, n);
        for (i, &(b, r)) in lobes.iter().enumerate() {
            g.used[[0, i]] = true;
            g.beckmann[[0, i]] = b;
            g.roughness[[0, i]] = r;
        }
        g
    }

    /// The family most lobes took, and its median width; too few lobes give none.
    #[test]
    fn the_majority_family_and_its_median_width() {
        let mut lobes = vec![(false, 0.3); 5];
        lobes.extend([(true, 0.2), (true, 0.25), (true, 0.9)].repeat(4));
        let m = shared(&sample(&lobes, 40)).unwrap();
        assert_eq!(m.facets, Facets::Beckmann);
        assert!((m.roughness - 0.25).abs() < 1e-6, "{m:?}");
        assert_eq!(shared(&sample(&lobes[..MIN_FITS - 1], 100)), None);
    }
}
