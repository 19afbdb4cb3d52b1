//! splat-core: Gaussian-splat scenes without Python.
//!
//! - [`scene`]: the structure-of-arrays scene model (SPEC §1)
//! - [`ply`]: INRIA PLY reading and writing
pub mod error;
pub mod io;
pub mod ply;
pub mod scene;

pub use error::{Error, Result};
pub use scene::{Scene, SceneView};
pub mod camera;
pub mod image_out;
pub mod raster;
