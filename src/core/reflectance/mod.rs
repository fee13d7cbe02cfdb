//! Reflectance beyond Lambert: a diffuse term plus an isotropic microfacet lobe, fitted
//! per pixel with the normal where the robust solve's Lambertian fit leaves highlights
//! unexplained (glossy paint, glazes, metal), so that highlights inform the normal
//! instead of being set aside, and a material (diffuse albedo, specular albedo,
//! roughness) comes out.

mod fit;
mod linear;
mod lobe;
mod material;
mod rows;

pub use fit::{Fitted, Material, Observation, fit};
pub use lobe::Facets;
pub use material::shared;
pub use rows::{GlossRows, refine_rows};
