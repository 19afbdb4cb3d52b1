//! The scene model: stored (pre-activation) Gaussian parameters as float32 structure-of-arrays,
//! exactly the layout of the INRIA PLY and gsplat (SPEC §1).
use crate::error::{Error, Result};

/// DC spherical-harmonic constant: colour = 0.5 + C0 * sh0.
pub const SH_C0: f32 = 0.282_094_8;

/// Number of higher-band SH coefficients per channel for a degree: (d+1)^2 - 1.
pub const fn sh_rest_count(degree: u8) -> usize {
    let d = degree as usize;
    (d + 1) * (d + 1) - 1
}

/// Degree whose rest count is `k`, if any (degrees 0..=4).
pub fn sh_degree_for_rest(k: usize) -> Option<u8> {
    (0u8..=4).find(|&d| sh_rest_count(d) == k)
}

/// An owned scene of `len()` Gaussians. Every array is flat, row-major.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scene {
    /// (N,3) centres.
    pub means: Vec<f32>,
    /// (N,4) rotations (w,x,y,z), normalised.
    pub quats: Vec<f32>,
    /// (N,3) natural-log axis scales.
    pub log_scales: Vec<f32>,
    /// (N,) opacity logits.
    pub opacity_logits: Vec<f32>,
    /// (N,3) DC SH coefficients.
    pub sh0: Vec<f32>,
    /// (N,K,3) higher SH bands, basis-major, channel-last; K = sh_rest_count(sh_degree).
    pub sh_rest: Vec<f32>,
    /// SH degree 0..=4.
    pub sh_degree: u8,
    /// Per-Gaussian extra properties a file carried (name, N values), kept in file order.
    pub extras: Vec<(String, Vec<f32>)>,
}

/// A borrowed scene: the same layout as [`Scene`], over slices (e.g. NumPy buffers).
#[derive(Debug, Clone, Copy)]
pub struct SceneView<'a> {
    pub means: &'a [f32],
    pub quats: &'a [f32],
    pub log_scales: &'a [f32],
    pub opacity_logits: &'a [f32],
    pub sh0: &'a [f32],
    pub sh_rest: &'a [f32],
    pub sh_degree: u8,
}

impl<'a> SceneView<'a> {
    /// Build a view, checking every length against `opacity_logits.len()`.
    pub fn new(
        means: &'a [f32],
        quats: &'a [f32],
        log_scales: &'a [f32],
        opacity_logits: &'a [f32],
        sh0: &'a [f32],
        sh_rest: &'a [f32],
        sh_degree: u8,
    ) -> Result<Self> {
        let view = SceneView {
            means,
            quats,
            log_scales,
            opacity_logits,
            sh0,
            sh_rest,
            sh_degree,
        };
        view.validate()?;
        Ok(view)
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// Higher-band coefficients per channel.
    pub fn sh_rest_k(&self) -> usize {
        sh_rest_count(self.sh_degree)
    }

    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        if self.sh_degree > 4 {
            return Err(Error::InvalidArgument(format!(
                "sh_degree must be 0..=4, got {}",
                self.sh_degree
            )));
        }
        let k = self.sh_rest_k();
        let checks: [(&str, usize, usize); 5] = [
            ("means", self.means.len(), n * 3),
            ("quats", self.quats.len(), n * 4),
            ("log_scales", self.log_scales.len(), n * 3),
            ("sh0", self.sh0.len(), n * 3),
            ("sh_rest", self.sh_rest.len(), n * k * 3),
        ];
        for (name, got, want) in checks {
            if got != want {
                return Err(Error::InvalidArgument(format!(
                    "{name} holds {got} values, expected {want} for {n} Gaussians (SH degree {})",
                    self.sh_degree
                )));
            }
        }
        Ok(())
    }

    /// Axis-aligned bounds of the centres, `None` for an empty scene. Non-finite centres are ignored.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        let mut any = false;
        for p in self.means.chunks_exact(3) {
            if p.iter().all(|v| v.is_finite()) {
                any = true;
                for d in 0..3 {
                    lo[d] = lo[d].min(p[d]);
                    hi[d] = hi[d].max(p[d]);
                }
            }
        }
        any.then_some((lo, hi))
    }

    /// Copy into an owned scene (extras empty).
    pub fn to_owned_scene(&self) -> Scene {
        Scene {
            means: self.means.to_vec(),
            quats: self.quats.to_vec(),
            log_scales: self.log_scales.to_vec(),
            opacity_logits: self.opacity_logits.to_vec(),
            sh0: self.sh0.to_vec(),
            sh_rest: self.sh_rest.to_vec(),
            sh_degree: self.sh_degree,
            extras: Vec::new(),
        }
    }
}

impl Scene {
    /// An empty scene of the given SH degree.
    /// `n` Gaussians of the given SH degree with every stored value zero (decoders fill it in).
    pub fn zeroed(n: usize, sh_degree: u8) -> Self {
        let k = sh_rest_count(sh_degree);
        Scene {
            means: crate::mem::zeroed_f32(n * 3),
            quats: crate::mem::zeroed_f32(n * 4),
            log_scales: crate::mem::zeroed_f32(n * 3),
            opacity_logits: crate::mem::zeroed_f32(n),
            sh0: crate::mem::zeroed_f32(n * 3),
            sh_rest: crate::mem::zeroed_f32(n * k * 3),
            sh_degree,
            extras: Vec::new(),
        }
    }

    pub fn empty(sh_degree: u8) -> Self {
        Scene {
            sh_degree,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    pub fn sh_rest_k(&self) -> usize {
        sh_rest_count(self.sh_degree)
    }

    pub fn view(&self) -> SceneView<'_> {
        SceneView {
            means: &self.means,
            quats: &self.quats,
            log_scales: &self.log_scales,
            opacity_logits: &self.opacity_logits,
            sh0: &self.sh0,
            sh_rest: &self.sh_rest,
            sh_degree: self.sh_degree,
        }
    }

    /// Check array lengths (including extras) against the Gaussian count.
    pub fn validate(&self) -> Result<()> {
        self.view().validate()?;
        for (name, values) in &self.extras {
            if values.len() != self.len() {
                return Err(Error::InvalidArgument(format!(
                    "extra property '{name}' holds {} values, expected {}",
                    values.len(),
                    self.len()
                )));
            }
        }
        Ok(())
    }

    /// Normalise every quaternion in place; a zero quaternion becomes the identity.
    pub fn normalize_quats(&mut self) {
        normalize_quats(&mut self.quats);
    }

    /// Keep the Gaussians whose `keep` flag is set, in order (extras follow).
    pub fn filter(&self, keep: &[bool]) -> Scene {
        let idx: Vec<usize> = keep
            .iter()
            .enumerate()
            .filter_map(|(i, &k)| k.then_some(i))
            .collect();
        self.gather(&idx)
    }

    /// Remove the Gaussians at `rows` (sorted or not, in range), keeping the others in order.
    pub fn drop_rows(&mut self, rows: &[usize]) {
        let mut keep = vec![true; self.len()];
        for &i in rows {
            keep[i] = false;
        }
        self.retain(&keep);
    }

    /// Keep the Gaussians whose `keep` flag is set, in order, compacting every array in place
    /// (no second copy of the scene).
    pub fn retain(&mut self, keep: &[bool]) {
        let k = self.sh_rest_k() * 3;
        retain_rows(&mut self.means, 3, keep);
        retain_rows(&mut self.quats, 4, keep);
        retain_rows(&mut self.log_scales, 3, keep);
        retain_rows(&mut self.opacity_logits, 1, keep);
        retain_rows(&mut self.sh0, 3, keep);
        retain_rows(&mut self.sh_rest, k, keep);
        for (_, v) in &mut self.extras {
            retain_rows(v, 1, keep);
        }
    }

    /// Gather Gaussians by index (indices must be < len; callers check).
    pub fn gather(&self, idx: &[usize]) -> Scene {
        let k = self.sh_rest_k();
        Scene {
            means: gather_rows(&self.means, 3, idx),
            quats: gather_rows(&self.quats, 4, idx),
            log_scales: gather_rows(&self.log_scales, 3, idx),
            opacity_logits: gather_rows(&self.opacity_logits, 1, idx),
            sh0: gather_rows(&self.sh0, 3, idx),
            sh_rest: gather_rows(&self.sh_rest, k * 3, idx),
            sh_degree: self.sh_degree,
            extras: self
                .extras
                .iter()
                .map(|(n, v)| (n.clone(), gather_rows(v, 1, idx)))
                .collect(),
        }
    }

    /// Indices of Gaussians with any non-finite stored value.
    pub fn invalid_rows(&self) -> Vec<usize> {
        let k = self.sh_rest_k() * 3;
        (0..self.len())
            .filter(|&i| {
                let rows: [&[f32]; 6] = [
                    &self.means[i * 3..i * 3 + 3],
                    &self.quats[i * 4..i * 4 + 4],
                    &self.log_scales[i * 3..i * 3 + 3],
                    &self.opacity_logits[i..i + 1],
                    &self.sh0[i * 3..i * 3 + 3],
                    &self.sh_rest[i * k..i * k + k],
                ];
                rows.iter().any(|r| r.iter().any(|v| !v.is_finite()))
            })
            .collect()
    }
}

/// Quaternions whose squared norm is this close to 1 are kept bit for bit: normalising is not
/// idempotent in float32, and load -> save -> load must be exact. One float32 division leaves
/// the squared norm within 3 ulp of 1, so normalised quaternions always pass this test.
pub const QUAT_NORM2_TOL: f32 = 8.0 * f32::EPSILON;

/// Normalise (w,x,y,z) quaternions whose squared norm is not within [`QUAT_NORM2_TOL`] of 1, by
/// one division by the float32 norm sqrt(((w*w + x*x) + y*y) + z*z). A zero quaternion becomes the
/// identity; one with a non-finite component is left for the NaN/Inf check; one whose float32
/// squared norm overflows or is subnormal (too imprecise to divide by) is normalised in float64.
pub fn normalize_quats(quats: &mut [f32]) {
    for q in quats.chunks_exact_mut(4) {
        let n2 = ((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3];
        if (n2 - 1.0).abs() <= QUAT_NORM2_TOL {
            continue;
        }
        if n2 == 0.0 {
            q.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        } else if n2.is_normal() {
            let n = n2.sqrt();
            for v in q.iter_mut() {
                *v /= n;
            }
        } else if q.iter().all(|v| v.is_finite()) {
            let n = q
                .iter()
                .map(|&v| f64::from(v) * f64::from(v))
                .sum::<f64>()
                .sqrt();
            for v in q.iter_mut() {
                *v = (f64::from(*v) / n) as f32;
            }
        }
    }
}

fn retain_rows(v: &mut Vec<f32>, width: usize, keep: &[bool]) {
    if width == 0 {
        return;
    }
    let mut w = 0;
    for (r, &k) in keep.iter().enumerate() {
        if k {
            if w != r {
                v.copy_within(r * width..(r + 1) * width, w * width);
            }
            w += 1;
        }
    }
    v.truncate(w * width);
    v.shrink_to_fit();
}

fn gather_rows(src: &[f32], width: usize, idx: &[usize]) -> Vec<f32> {
    let mut out = Vec::with_capacity(idx.len() * width);
    for &i in idx {
        out.extend_from_slice(&src[i * width..(i + 1) * width]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rest_counts_match_degrees() {
        assert_eq!(
            (0..=4).map(sh_rest_count).collect::<Vec<_>>(),
            [0, 3, 8, 15, 24]
        );
        assert_eq!(sh_degree_for_rest(15), Some(3));
        assert_eq!(sh_degree_for_rest(7), None);
    }

    #[test]
    fn quats_normalise_and_zero_becomes_identity() {
        let mut q = vec![2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        normalize_quats(&mut q);
        assert_eq!(q, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn normalising_twice_changes_no_bit() {
        // A cheap deterministic spread of quaternions, norms from 1e-3 to 1e3.
        let mut q: Vec<f32> = (0..40_000u32)
            .map(|i| {
                let h = i.wrapping_mul(2_654_435_761).rotate_left(13) ^ 0x9e37_79b9;
                (h as f32 / u32::MAX as f32 - 0.5) * 10f32.powi((i % 7) as i32 - 3)
            })
            .collect();
        normalize_quats(&mut q);
        let once = q.clone();
        normalize_quats(&mut q);
        assert_eq!(q, once);
        for r in q.chunks_exact(4) {
            let n2: f32 = r.iter().map(|v| v * v).sum();
            assert!((n2 - 1.0).abs() < 1e-6, "{r:?}");
        }
    }

    #[test]
    fn retain_compacts_every_array_in_order() {
        let mut s = Scene {
            means: (0..9).map(|v| v as f32).collect(),
            quats: [1.0, 0.0, 0.0, 0.0].repeat(3),
            log_scales: vec![0.0; 9],
            opacity_logits: vec![0.0, 1.0, 2.0],
            sh0: vec![0.0; 9],
            sh_rest: (0..27).map(|v| v as f32).collect(),
            sh_degree: 1,
            extras: vec![("f".into(), vec![5.0, 6.0, 7.0])],
        };
        s.retain(&[true, false, true]);
        assert_eq!(s.means, [0.0, 1.0, 2.0, 6.0, 7.0, 8.0]);
        assert_eq!(s.opacity_logits, [0.0, 2.0]);
        assert_eq!(
            &s.sh_rest[9..],
            (18..27).map(|v| v as f32).collect::<Vec<_>>()
        );
        assert_eq!(s.extras[0].1, [5.0, 7.0]);
        s.validate().expect("consistent");
    }
}
