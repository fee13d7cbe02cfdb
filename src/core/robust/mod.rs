//! The robust per-pixel solve: keep the observations a Lambertian model explains, set
//! aside shadows (too dark), highlights and saturation (too bright), and re-fit.
//!
//! Method: thresholded inlier selection with re-fits (a hard-threshold M-estimator).
//! 1. A global pre-pass on a subsample runs the per-pixel fit below and estimates the
//!    camera's black level (the median of observations the fits put in attached shadow)
//!    and the noise σ (MAD of the residuals of lit observations).
//! 2. Per pixel: subtract the black level, drop observations below 3σ or at saturation,
//!    fit least squares, then set aside, one at a time, the kept observation the fit
//!    misses worst while it misses by more than the tolerance (3σ + 2 % of the pixel's
//!    brightness under a typical light), and re-fit on the observations the fit predicts
//!    lit within the tolerance until the set stops changing. Normal equations are updated
//!    by subtracting the few dropped lights from the precomputed full LᵀL.
//! 3. Judged: fewer than 3 inliers, a fit facing away from the camera (or an exact
//!    3-inlier fit at grazing angle), or one that misses most observations while least
//!    squares explains the median one better: the pixel gets plain least squares over all
//!    its observations and is flagged unreliable.
//!
//! `fit` is one pixel's fit and its judgement; `lanes` settles the pixels whose every
//! observation the model explains, a row at a time, before any of this runs per pixel;
//! `estimate` is the pre-pass; `solver` ([`Robust`]) solves a band's rows with both;
//! `warnings` reports what the estimate and the fallbacks say about the capture;
//! `intensities` estimates distant lights' unknown intensities with the same fit.

mod estimate;
mod fit;
mod intensities;
mod lanes;
mod solver;
mod warnings;

pub use estimate::{CaptureEstimate, estimate};
pub use intensities::estimate_intensities;
pub use solver::{Robust, confidence_of};
pub use warnings::warnings;
