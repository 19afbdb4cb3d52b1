//! The trainable parameters (SPEC §1 stored layout) with their Adam moments, and the row
//! operations densification needs (gather, append copies, remove), applied to every array at
//! once so values and moments never fall out of step.
//!
//! Adam is torch's (`torch.optim.Adam`, no weight decay, no amsgrad), one optimiser per array as
//! gsplat's trainer has, all sharing one step count t (every array steps every iteration):
//!
//! ```text
//! m = b1 m + (1 - b1) g;   v = b2 v + (1 - b2) g^2
//! p -= (lr / (1 - b1^t)) m / (sqrt(v) / sqrt(1 - b2^t) + eps)
//! ```
//!
//! Every row is updated every step, including rows whose gradient is zero (their momentum keeps
//! moving them), as torch does. The one exception changes no bit: SH bands above the degree in
//! use have zero gradients and zero moments until the degree reaches them, so their update is
//! exactly zero and is skipped.
use rayon::prelude::*;

use crate::raster::Simd;
use crate::scene::{sh_rest_count, SceneView};

/// Index of each array in [`Params::groups`].
pub const MEANS: usize = 0;
pub const QUATS: usize = 1;
pub const SCALES: usize = 2;
pub const OPACITY: usize = 3;
pub const SH0: usize = 4;
pub const SH_REST: usize = 5;
pub const GROUPS: usize = 6;
pub const NAMES: [&str; GROUPS] = [
    "means",
    "quats",
    "log_scales",
    "opacity_logits",
    "sh0",
    "sh_rest",
];

/// One parameter array (`width` values per Gaussian) and its Adam moments.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Group {
    pub width: usize,
    pub value: Vec<f32>,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
}

impl Group {
    fn new(width: usize, value: Vec<f32>) -> Self {
        let n = value.len();
        Group {
            width,
            value,
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }
}

/// Adam hyper-parameters shared by the arrays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamParams {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamParams {
    fn default() -> Self {
        AdamParams {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

/// The six parameter arrays of N Gaussians (sh_rest sized for `sh_degree`).
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    pub groups: [Group; GROUPS],
    pub sh_degree: u8,
}

/// Elements per parallel Adam work unit.
const ADAM_CHUNK: usize = 1 << 14;

impl Params {
    /// Parameters from a scene's arrays (moments zero).
    pub fn from_view(scene: &SceneView<'_>) -> Self {
        let k = scene.sh_rest_k();
        Params {
            groups: [
                Group::new(3, scene.means.to_vec()),
                Group::new(4, scene.quats.to_vec()),
                Group::new(3, scene.log_scales.to_vec()),
                Group::new(1, scene.opacity_logits.to_vec()),
                Group::new(3, scene.sh0.to_vec()),
                Group::new(k * 3, scene.sh_rest.to_vec()),
            ],
            sh_degree: scene.sh_degree,
        }
    }

    pub fn len(&self) -> usize {
        self.groups[OPACITY].value.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The parameters as a scene view (for the rasterizer).
    pub fn view(&self) -> SceneView<'_> {
        let g = &self.groups;
        SceneView {
            means: &g[MEANS].value,
            quats: &g[QUATS].value,
            log_scales: &g[SCALES].value,
            opacity_logits: &g[OPACITY].value,
            sh0: &g[SH0].value,
            sh_rest: &g[SH_REST].value,
            sh_degree: self.sh_degree,
        }
    }

    /// Rows `idx` of every array, moments included (in `idx` order).
    pub fn gather(&self, idx: &[usize]) -> Params {
        let take = |v: &[f32], w: usize| -> Vec<f32> {
            let mut out = Vec::with_capacity(idx.len() * w);
            for &i in idx {
                out.extend_from_slice(&v[i * w..(i + 1) * w]);
            }
            out
        };
        Params {
            groups: std::array::from_fn(|k| {
                let g = &self.groups[k];
                Group {
                    width: g.width,
                    value: take(&g.value, g.width),
                    m: take(&g.m, g.width),
                    v: take(&g.v, g.width),
                }
            }),
            sh_degree: self.sh_degree,
        }
    }

    /// Append `other`'s rows (values and moments as they are).
    pub fn append(&mut self, other: &Params) {
        for (g, o) in self.groups.iter_mut().zip(&other.groups) {
            g.value.extend_from_slice(&o.value);
            g.m.extend_from_slice(&o.m);
            g.v.extend_from_slice(&o.v);
        }
    }

    /// Keep the rows where `keep` is true, in order.
    pub fn retain(&mut self, keep: &[bool]) {
        for g in &mut self.groups {
            let w = g.width;
            for arr in [&mut g.value, &mut g.m, &mut g.v] {
                let mut j = 0;
                for (i, &k) in keep.iter().enumerate() {
                    if k {
                        arr.copy_within(i * w..(i + 1) * w, j * w);
                        j += 1;
                    }
                }
                arr.truncate(j * w);
            }
        }
    }

    /// Zero the moments of rows `idx` in every array.
    pub fn zero_moments(&mut self, idx: &[usize]) {
        for g in &mut self.groups {
            let w = g.width;
            for &i in idx {
                g.m[i * w..(i + 1) * w].fill(0.0);
                g.v[i * w..(i + 1) * w].fill(0.0);
            }
        }
    }

    /// Copy row `src` over row `dst` in every array (values and moments).
    pub fn copy_row(&mut self, src: usize, dst: usize) {
        for g in &mut self.groups {
            let w = g.width;
            for arr in [&mut g.value, &mut g.m, &mut g.v] {
                arr.copy_within(src * w..(src + 1) * w, dst * w);
            }
        }
    }

    /// One Adam step of every array with gradients `grads` (same layout as the values),
    /// learning rates `lrs`, step count `t` (1 for the first step). SH bands above
    /// `active_degree` are skipped (their update is exactly zero, see the module docs).
    ///
    /// Each gradient value the step reads is zeroed in the same pass (the active prefix of
    /// every row; the skipped bands are left as they are), so the next backward, which adds
    /// into the gradients, needs no separate clear of these arrays.
    pub fn adam_step(
        &mut self,
        grads: [&mut [f32]; GROUPS],
        lrs: [f32; GROUPS],
        t: u64,
        adam: &AdamParams,
        active_degree: u8,
    ) {
        let (b1, b2) = (adam.beta1, adam.beta2);
        let bc1 = 1.0 - (b1 as f64).powf(t as f64);
        let bc2_sqrt = (1.0 - (b2 as f64).powf(t as f64)).sqrt() as f32;
        let active_rest = sh_rest_count(active_degree.min(self.sh_degree)) * 3;
        for ((k, g), grad) in self.groups.iter_mut().enumerate().zip(grads) {
            let step_size = (lrs[k] as f64 / bc1) as f32;
            let width = g.width;
            // the active prefix of each row (all of it but for sh_rest)
            let active = if k == SH_REST { active_rest } else { width };
            if active == 0 || g.value.is_empty() {
                continue;
            }
            let k = AdamStep {
                b1,
                b2,
                step_size,
                bc2_sqrt,
                eps: adam.eps,
                width,
                active,
            };
            let chunk = if active == width {
                ADAM_CHUNK
            } else {
                (ADAM_CHUNK / width).max(1) * width
            };
            let level = Simd::Auto.resolve();
            g.value
                .par_chunks_mut(chunk)
                .zip(g.m.par_chunks_mut(chunk))
                .zip(g.v.par_chunks_mut(chunk))
                .zip(grad.par_chunks_mut(chunk))
                .for_each(|(((p, m), v), gr)| k.run(level, p, m, v, gr));
        }
    }
}

/// One array's Adam update over a chunk of whole rows.
#[derive(Clone, Copy)]
struct AdamStep {
    b1: f32,
    b2: f32,
    step_size: f32,
    bc2_sqrt: f32,
    eps: f32,
    width: usize,
    active: usize,
}

impl AdamStep {
    #[inline(always)]
    fn update(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &mut [f32]) {
        let (b1, b2) = (self.b1, self.b2);
        for (((p, m), v), g) in p.iter_mut().zip(m).zip(v).zip(g) {
            let gr = std::mem::take(g);
            *m = b1 * *m + (1.0 - b1) * gr;
            *v = b2 * *v + (1.0 - b2) * gr * gr;
            let denom = v.sqrt() / self.bc2_sqrt + self.eps;
            *p -= self.step_size * *m / denom;
        }
    }

    #[inline(always)]
    fn chunk(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &mut [f32]) {
        if self.active == self.width {
            self.update(p, m, v, g);
        } else {
            let (w, a) = (self.width, self.active);
            for (((p, m), v), g) in p
                .chunks_mut(w)
                .zip(m.chunks_mut(w))
                .zip(v.chunks_mut(w))
                .zip(g.chunks_mut(w))
            {
                self.update(&mut p[..a], &mut m[..a], &mut v[..a], &mut g[..a]);
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
    unsafe fn chunk_avx512(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &mut [f32]) {
        self.chunk(p, m, v, g)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn chunk_avx2(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &mut [f32]) {
        self.chunk(p, m, v, g)
    }

    /// The update with the widest kernel the CPU has (plain multiplies, adds, divides and
    /// square roots, no FMA contraction: every kernel gives the same bits).
    fn run(&self, level: Simd, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &mut [f32]) {
        match level {
            // SAFETY: `Simd::resolve` checked the CPU has these features.
            #[cfg(target_arch = "x86_64")]
            Simd::Avx512 => unsafe { self.chunk_avx512(p, m, v, g) },
            // SAFETY: as above
            #[cfg(target_arch = "x86_64")]
            Simd::Avx2 => unsafe { self.chunk_avx2(p, m, v, g) },
            _ => self.chunk(p, m, v, g),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;

    fn params(n: usize) -> Params {
        let mut s = Scene::zeroed(n, 1);
        for (i, v) in s.means.iter_mut().enumerate() {
            *v = i as f32;
        }
        Params::from_view(&s.view())
    }

    #[test]
    fn adam_matches_the_torch_formula() {
        let mut p = params(2);
        let n = p.groups[MEANS].value.len();
        let g: Vec<f32> = (0..n).map(|i| 0.1 * (i as f32 - 2.0)).collect();
        let empty = |k: usize| vec![0.0f32; p.groups[k].value.len()];
        let (mut z1, mut z2, mut z3, mut z4, mut z5) =
            (empty(1), empty(2), empty(3), empty(4), empty(5));
        let before = p.groups[MEANS].value.clone();
        let adam = AdamParams::default();
        for t in 1..=3u64 {
            let mut gt = g.clone();
            let zs = [&mut z1, &mut z2, &mut z3, &mut z4, &mut z5];
            let [a, b, c, d, e] = zs.map(|z| &mut z[..]);
            p.adam_step([&mut gt, a, b, c, d, e], [0.01; GROUPS], t, &adam, 1);
            // the step zeroes the gradients it read
            assert!(gt.iter().all(|&v| v.to_bits() == 0));
        }
        // reference in f64: with a constant gradient m_hat = g and v_hat = g^2 exactly, so each
        // step moves by lr * sign(g) (up to eps)
        for i in 0..n {
            let want =
                before[i] as f64 - 3.0 * 0.01 * (g[i] as f64).signum() * (g[i] != 0.0) as u8 as f64;
            assert!((p.groups[MEANS].value[i] as f64 - want).abs() < 1e-5, "{i}");
        }
        // zero gradient and zero moments: no change
        assert!(p.groups[SCALES].value.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn row_operations_keep_values_and_moments_together() {
        let mut p = params(4);
        p.groups[MEANS].m[3] = 7.0; // row 1, x
        let g = p.gather(&[1, 1]);
        assert_eq!(g.len(), 2);
        assert_eq!(&g.groups[MEANS].value[..3], &[3.0, 4.0, 5.0]);
        assert_eq!(g.groups[MEANS].m[0], 7.0);
        p.append(&g);
        assert_eq!(p.len(), 6);
        p.retain(&[true, false, true, true, false, true]);
        assert_eq!(p.len(), 4);
        assert_eq!(&p.groups[MEANS].value[..6], &[0.0, 1.0, 2.0, 6.0, 7.0, 8.0]);
        assert_eq!(p.groups[MEANS].m[9], 7.0);
        p.zero_moments(&[3]);
        assert_eq!(p.groups[MEANS].m[9], 0.0);
        p.copy_row(0, 1);
        assert_eq!(&p.groups[MEANS].value[3..6], &[0.0, 1.0, 2.0]);
    }
}
