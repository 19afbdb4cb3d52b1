//! `morphgs fit`: a deterministic 3DGS optimiser on the CPU, built on the differentiable
//! rasterizer ([`crate::raster::diff`]).
//!
//! - [`config`]: the recipe (gsplat 1.5.3 `simple_trainer.py` = INRIA 3DGS defaults, opacity
//!   reset on), strategies `default` and `mcmc`;
//! - [`loss`], [`ssim`]: L1 * 0.8 + (1 - SSIM) * 0.2 and its image gradient;
//! - [`params`]: the parameter arrays, their Adam moments and row operations;
//! - [`densify`] (gsplat `DefaultStrategy`), [`mcmc`] (`MCMCStrategy`);
//! - [`init`]: Gaussians from a point cloud (3-NN scales), random points;
//! - [`trainer`]: one step; [`run`]: the loop with evaluation, checkpoints and hooks;
//! - [`checkpoint`]: atomic save and checked load; [`rand`]: the keyed random draws.
//!
//! Determinism: every stage is either per element, a fixed-order reduction or a draw keyed by
//! (seed, purpose, step, index), so the same config, data, initial scene and seed give
//! bit-identical scenes for any thread count, and a run restored from a checkpoint continues
//! exactly as if it had never stopped.
pub mod checkpoint;
pub mod config;
pub mod densify;
pub mod init;
pub mod loss;
pub mod mcmc;
mod mcmc_kernels;
pub mod params;
pub mod rand;
pub mod run;
pub mod ssim;
pub mod trainer;

pub use config::{DefaultStrategy, FitConfig, LearningRates, McmcStrategy, Strategy};
pub use run::{run, Event, Flow, Hooks, RunEnd, RunOptions};
pub use trainer::{EvalView, StepRecord, Trainer, View};

#[cfg(test)]
mod tests;
