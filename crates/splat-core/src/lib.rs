//! splat-core: Gaussian-splat scenes without Python.
//!
//! - [`scene`]: the structure-of-arrays scene model (SPEC §1)
//! - [`ply`]: INRIA PLY reading and writing
//! - [`formats`]: .splat, .spz and SuperSplat compressed PLY
//! - [`rng`]: the counter-based generator behind every random draw (a stability promise)
//! - [`perturb`]: the paper's six perturbation operations (SPEC §2)
pub mod error;
pub mod fastmath;
pub mod formats;
pub mod io;
pub mod mem;
pub mod perturb;
pub mod ply;
pub mod rng;
pub mod scene;

pub use error::{Error, Result};
pub use scene::{Scene, SceneView};
pub mod blur;
pub mod camera;
pub mod fit;
pub mod image_out;
pub mod raster;
