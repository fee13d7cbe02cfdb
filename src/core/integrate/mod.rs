//! Heights from normals: gradients p = −nx/nz, q = −ny/nz, then one of several integrators.
//! UNDER CONSTRUCTION by the integration helper.

use ndarray::{Array2, Array3};

use super::options::Integration;

/// Gradients (p, q) = (dz/dx, dz/dy) from unit normals, zero off the mask.
pub fn gradients(normals: &Array3<f32>, mask: &Array2<bool>) -> (Array2<f32>, Array2<f32>) {
    let _ = (normals, mask);
    todo!()
}

/// Integrability residual dp/dy − dq/dx, zero off the mask.
pub fn curl(p: &Array2<f32>, q: &Array2<f32>, mask: &Array2<bool>) -> Array2<f32> {
    let _ = (p, q, mask);
    todo!()
}

/// Heights in pixel units over the mask; off-mask pixels get the lowest height on it.
pub fn integrate(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    method: Integration,
) -> Array2<f32> {
    let _ = (p, q, mask, method);
    todo!()
}
