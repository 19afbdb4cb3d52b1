//! splat-core: Gaussian-splat scenes without Python.
//!
//! - [`scene`]: the structure-of-arrays scene model (SPEC §1)
//! - [`ply`]: INRIA PLY reading and writing
//! - [`formats`]: .splat, .spz and SuperSplat compressed PLY
pub mod error;
pub mod formats;
pub mod io;
pub mod mem;
pub mod ply;
pub mod scene;

pub use error::{Error, Result};
pub use scene::{Scene, SceneView};
pub mod blur;
