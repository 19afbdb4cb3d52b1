//! Densification statistics per Gaussian, accumulated over backward calls as gsplat's
//! `DefaultStrategy._update_state` does: the 2D-mean gradient in normalised screen units
//! (pixels times W/2 and H/2, times the cameras per step to undo a batch mean), its norm summed
//! over the views that see the Gaussian, the same for the per-pixel absolute sums (AbsGS), a
//! visibility count and the largest 2D radius relative to the image's larger side.
use crate::error::{Error, Result};

/// Per-Gaussian densification statistics (all (N,) float32).
#[derive(Debug, Clone, PartialEq)]
pub struct DensifyStats {
    /// Sum over views of |(dL/dx W/2, dL/dy H/2)| * cameras_per_step.
    pub grad2d: Vec<f32>,
    /// The same with gsplat's absgrad (per-pixel absolute values summed) instead.
    pub grad2d_abs: Vec<f32>,
    /// Number of views in which the Gaussian survived culling (radii > 0).
    pub count: Vec<f32>,
    /// Largest max(rx, ry) / max(W, H) over those views.
    pub max_radius: Vec<f32>,
    /// gsplat's `n_cameras` factor: how many cameras one loss averages over.
    pub cameras_per_step: f32,
}

impl Default for DensifyStats {
    fn default() -> Self {
        DensifyStats {
            grad2d: Vec::new(),
            grad2d_abs: Vec::new(),
            count: Vec::new(),
            max_radius: Vec::new(),
            cameras_per_step: 1.0,
        }
    }
}

impl DensifyStats {
    /// Zeroed statistics for `n` Gaussians (keeps the allocations).
    pub fn reset(&mut self, n: usize) {
        for v in [
            &mut self.grad2d,
            &mut self.grad2d_abs,
            &mut self.count,
            &mut self.max_radius,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
    }

    pub(super) fn check(&self, n: usize) -> Result<()> {
        let ok = [
            &self.grad2d,
            &self.grad2d_abs,
            &self.count,
            &self.max_radius,
        ]
        .iter()
        .all(|v| v.len() == n);
        if !ok {
            return Err(Error::InvalidArgument(format!(
                "densification statistics hold {} entries, the scene {n} Gaussians: call reset",
                self.count.len()
            )));
        }
        Ok(())
    }

    pub(super) fn raw(&mut self, (width, height): (u32, u32)) -> Raw {
        Raw {
            grad2d: self.grad2d.as_mut_ptr(),
            grad2d_abs: self.grad2d_abs.as_mut_ptr(),
            count: self.count.as_mut_ptr(),
            max_radius: self.max_radius.as_mut_ptr(),
            sx: width as f32 / 2.0 * self.cameras_per_step,
            sy: height as f32 / 2.0 * self.cameras_per_step,
            inv_side: 1.0 / width.max(height) as f32,
        }
    }
}

/// Base pointers of the statistics for the parallel per-Gaussian pass.
pub(super) struct Raw {
    grad2d: *mut f32,
    grad2d_abs: *mut f32,
    count: *mut f32,
    max_radius: *mut f32,
    sx: f32,
    sy: f32,
    inv_side: f32,
}

impl Raw {
    /// Ask for Gaussian i's statistics ahead of [`Raw::add`].
    #[inline(always)]
    pub(super) fn prefetch(&self, i: usize) {
        for b in [self.grad2d, self.grad2d_abs, self.count, self.max_radius] {
            crate::mem::prefetch_ptr(b, i);
        }
    }

    /// Add one view's statistics of Gaussian i.
    ///
    /// # Safety
    /// `i` is in bounds and no other call uses it concurrently.
    pub(super) unsafe fn add(&self, i: usize, g: [f32; 2], abs: [f32; 2], radius: [f32; 2]) {
        let norm = |v: [f32; 2]| ((v[0] * self.sx).powi(2) + (v[1] * self.sy).powi(2)).sqrt();
        // SAFETY: see the contract above
        unsafe {
            *self.grad2d.add(i) += norm(g);
            *self.grad2d_abs.add(i) += norm(abs);
            *self.count.add(i) += 1.0;
            let r = radius[0].max(radius[1]) * self.inv_side;
            let m = self.max_radius.add(i);
            *m = m.read().max(r);
        }
    }
}
