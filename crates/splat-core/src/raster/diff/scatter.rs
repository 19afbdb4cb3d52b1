//! The per-Gaussian pass's writes: each Gaussian's parameter gradients added to [`Gradients`],
//! its view gradients set in [`ViewGrads`] and its densification statistics added, from the
//! parallel tasks through raw pointers (each Gaussian is written by one task only).
use super::{densify, gauss_block, DensifyStats, Gradients, ViewGrads};
use crate::raster::project::Splat;

/// Raw base pointers of the output buffers, taken once before the parallel per-Gaussian pass.
pub(super) struct Scatter<'a> {
    means: *mut f32,
    quats: *mut f32,
    log_scales: *mut f32,
    logits: *mut f32,
    scales: *mut f32,
    opacities: *mut f32,
    sh0: *mut f32,
    sh_rest: *mut f32,
    colors: *mut f32,
    given_colors: bool,
    sh_rest_k: usize,
    view: Option<[*mut f32; 6]>,
    densify: Option<densify::Raw>,
    _life: std::marker::PhantomData<&'a mut Gradients>,
}

// SAFETY: `put` writes only the entries of Gaussian i, and each i is put by one task.
unsafe impl Sync for Scatter<'_> {}

impl<'a> Scatter<'a> {
    pub(super) fn new(
        out: &'a mut Gradients,
        view: Option<&'a mut ViewGrads>,
        densify: Option<&'a mut DensifyStats>,
        sh_rest_k: usize,
        size: (u32, u32),
    ) -> Self {
        Scatter {
            means: out.means.as_mut_ptr(),
            quats: out.quats.as_mut_ptr(),
            log_scales: out.log_scales.as_mut_ptr(),
            logits: out.opacity_logits.as_mut_ptr(),
            scales: out.scales.as_mut_ptr(),
            opacities: out.opacities.as_mut_ptr(),
            sh0: out.sh0.as_mut_ptr(),
            sh_rest: out.sh_rest.as_mut_ptr(),
            colors: out.colors.as_mut_ptr(),
            given_colors: !out.colors.is_empty(),
            sh_rest_k,
            view: view.map(|v| {
                [
                    v.means2d.as_mut_ptr(),
                    v.means2d_abs.as_mut_ptr(),
                    v.conics.as_mut_ptr(),
                    v.colors.as_mut_ptr(),
                    v.opacities.as_mut_ptr(),
                    v.depths.as_mut_ptr(),
                ]
            }),
            densify: densify.map(|d| d.raw(size)),
            _life: std::marker::PhantomData,
        }
    }

    /// Ask for the lines [`Scatter::put_lane`] will update for Gaussian i (a read-modify-write
    /// of a dozen arrays at random-ish rows: cache misses otherwise).
    #[inline(always)]
    pub(super) fn prefetch(&self, i: usize, degree: u8) {
        for (b, k) in [
            (self.means, 3),
            (self.quats, 4),
            (self.log_scales, 3),
            (self.logits, 1),
            (self.scales, 3),
            (self.opacities, 1),
        ] {
            crate::mem::prefetch_ptr(b, i * k);
        }
        if self.given_colors {
            crate::mem::prefetch_ptr(self.colors, i * 3);
        } else {
            crate::mem::prefetch_ptr(self.sh0, i * 3);
            let used = ((degree as usize + 1) * (degree as usize + 1) - 1) * 3;
            let at = i * self.sh_rest_k * 3;
            for o in (0..used).step_by(16).chain((used > 0).then_some(used - 1)) {
                crate::mem::prefetch_ptr(self.sh_rest, at + o);
            }
        }
        if let Some(v) = self.view {
            for (b, k) in v.iter().zip([2, 2, 3, 3, 1, 1]) {
                crate::mem::prefetch_ptr(*b, i * k);
            }
        }
        if let Some(d) = &self.densify {
            d.prefetch(i);
        }
    }

    /// Add the gradients of Gaussian i, lane `l` of a block (set its view gradients, add its
    /// statistics).
    ///
    /// # Safety
    /// No other call may use the same `i` concurrently; `i` is below the buffers' Gaussian
    /// count (checked against the scene before the pass).
    #[inline(always)]
    pub(super) unsafe fn put_lane(
        &self,
        i: usize,
        s: &Splat,
        g: &gauss_block::GradLanes,
        l: usize,
        degree: u8,
    ) {
        #[inline(always)]
        unsafe fn add<const K: usize>(
            base: *mut f32,
            at: usize,
            vals: &[gauss_block::Lane; K],
            l: usize,
        ) {
            for (k, x) in vals.iter().enumerate() {
                // SAFETY: the caller keeps at + k inside the buffer.
                unsafe { *base.add(at + k) += x[l] };
            }
        }
        #[inline(always)]
        unsafe fn set<const K: usize>(
            base: *mut f32,
            at: usize,
            vals: &[gauss_block::Lane; K],
            l: usize,
        ) {
            for (k, x) in vals.iter().enumerate() {
                // SAFETY: as above
                unsafe { *base.add(at + k) = x[l] };
            }
        }
        // SAFETY: every offset below is Gaussian i's entry of a buffer sized for the scene.
        unsafe {
            add(self.means, i * 3, &g.means, l);
            add(self.quats, i * 4, &g.quats, l);
            add(self.log_scales, i * 3, &g.log_scales, l);
            add(self.logits, i, &[g.opacity_logit], l);
            add(self.scales, i * 3, &g.scales, l);
            add(self.opacities, i, &[g.opacity], l);
            if self.given_colors {
                add(self.colors, i * 3, &g.rgb, l);
            } else {
                add(self.sh0, i * 3, &g.sh[0], l);
                let nb = (degree as usize + 1) * (degree as usize + 1);
                for b in 1..nb {
                    add(self.sh_rest, (i * self.sh_rest_k + b - 1) * 3, &g.sh[b], l);
                }
            }
            if let Some(v) = self.view {
                set(v[0], i * 2, &g.means2d, l);
                set(v[1], i * 2, &g.means2d_abs, l);
                set(v[2], i * 3, &g.conic, l);
                set(v[3], i * 3, &g.rgb, l);
                set(v[4], i, &[g.opacity_eff], l);
                set(v[5], i, &[g.depth], l);
            }
            if let Some(d) = &self.densify {
                let m2 = [g.means2d[0][l], g.means2d[1][l]];
                let ma = [g.means2d_abs[0][l], g.means2d_abs[1][l]];
                d.add(i, m2, ma, s.radius);
            }
        }
    }
}
