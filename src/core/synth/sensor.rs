//! The camera: exposure, black level, shot and read noise, clipping and quantisation.

use ndarray::Array3;

/// How scene light (pixel units: a unit light on albedo 1 facing it gives 1) maps to
/// full scale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Exposure {
    /// A fixed gain.
    Gain(f64),
    /// Expose for the highlights: the brightest value over all images lands at this
    /// multiple of full scale (above 1, the brightest highlights clip).
    Highlights(f64),
}

impl Exposure {
    /// The gain for a set of images whose brightest value is `peak`.
    pub(super) fn gain(self, peak: f64) -> f64 {
        match self {
            Self::Gain(g) => g,
            Self::Highlights(k) => k / peak,
        }
    }
}

/// The sensor's noise and offset, as fractions of full scale.
#[derive(Debug, Clone, Copy)]
pub(super) struct Noise {
    pub black_level: f64,
    /// Read noise: Gaussian, signal-independent.
    pub read_sigma: f64,
    /// Electrons at full scale, for photon shot noise (Poisson, here its Gaussian limit);
    /// None for none.
    pub full_well: Option<f64>,
}

/// Expose, add noise and quantise one image `(rows, cols, channels)` to 0..=`max`;
/// `rng` gives one Gaussian per sample in row-major order.
pub(super) fn capture(
    light: &Array3<f64>,
    gain: f64,
    noise: Noise,
    max: f64,
    rng: &mut Rng,
) -> Array3<u16> {
    Array3::from_shape_fn(light.dim(), |i| {
        let signal = gain * light[i];
        let sigma = match noise.full_well {
            None => noise.read_sigma,
            Some(well) => (noise.read_sigma.powi(2) + signal.max(0.0) / well).sqrt(),
        };
        let v = noise.black_level + signal + sigma * rng.gaussian();
        (v.clamp(0.0, 1.0) * max).round() as u16
    })
}

/// A small, fast, seedable generator (SplitMix64) for reproducible noise and sampling.
pub(super) struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// Standard normal by Box–Muller.
    pub fn gaussian(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_has_the_requested_spread() {
        let mut rng = Rng::new(3);
        let v: Vec<f64> = (0..20000).map(|_| rng.gaussian()).collect();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64;
        assert!(mean.abs() < 0.03 && (var.sqrt() - 1.0).abs() < 0.03);
    }

    #[test]
    fn shot_noise_grows_with_the_square_root_of_the_signal() {
        let noise = Noise {
            black_level: 0.0,
            read_sigma: 0.0,
            full_well: Some(10_000.0),
        };
        let spread = |level: f64| {
            let img = capture(
                &Array3::from_elem((100, 100, 1), level),
                1.0,
                noise,
                65535.0,
                &mut Rng::new(9),
            );
            let v: Vec<f64> = img.iter().map(|&x| x as f64 / 65535.0).collect();
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        };
        // σ = sqrt(signal / full well): 0.001 at 0.01, 0.004 at 0.16.
        let (low, high) = (spread(0.01), spread(0.16));
        assert!((low / 0.001 - 1.0).abs() < 0.05, "{low}");
        assert!((high / low - 4.0).abs() < 0.3, "{high} / {low}");
    }
}
