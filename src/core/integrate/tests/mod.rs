//! The integrators' unit tests, by area: `accuracy` (against analytic surfaces),
//! `gradients` (slopes and curl), `solver` (the masked CG and its multigrid),
//! `robust` (`robust-poisson`'s re-weighting), `timings` (ignored measurements);
//! `surfaces` holds the analytic surfaces and helpers they share.

mod accuracy;
mod gradients;
mod robust;
mod solver;
mod surfaces;
mod timings;
