//! Initial Gaussians from a point cloud, as INRIA 3DGS and gsplat build them: one Gaussian per
//! point at the point, isotropic scale sqrt(mean of the squared distances to its 3 nearest
//! neighbours) times a factor (INRIA `distCUDA2`, gsplat `knn(points, 4)[:, 1:]`; squared
//! distances clamped at 1e-7 as INRIA does), identity rotation (INRIA; gsplat draws random
//! quaternions), a given opacity, DC colour from the point colour and higher bands zero.
//!
//! Neighbours come from a k-d tree (median splits, deterministic) queried in parallel; each
//! point's answer is a pure function of the cloud, so the scene is the same for any thread count.
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::rng::Stream;
use crate::scene::{sh_rest_count, Scene, SH_C0};

use super::densify::logit;
use super::rand::{key, OP_INIT};

const LEAF: usize = 16;

/// A k-d tree over points (an implicit layout: a permutation and a node list).
struct KdTree<'a> {
    pts: &'a [[f32; 3]],
    perm: Vec<u32>,
    nodes: Vec<Node>,
}

#[derive(Clone, Copy)]
enum Node {
    Leaf {
        start: u32,
        end: u32,
    },
    Split {
        axis: u8,
        value: f32,
        left: u32,
        right: u32,
    },
}

impl<'a> KdTree<'a> {
    fn build(pts: &'a [[f32; 3]]) -> Self {
        let mut t = KdTree {
            pts,
            perm: (0..pts.len() as u32).collect(),
            nodes: Vec::new(),
        };
        let n = pts.len();
        t.node(0, n);
        t
    }

    fn node(&mut self, start: usize, end: usize) -> u32 {
        let id = self.nodes.len() as u32;
        self.nodes.push(Node::Leaf {
            start: start as u32,
            end: end as u32,
        });
        if end - start <= LEAF {
            return id;
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for &i in &self.perm[start..end] {
            let p = self.pts[i as usize];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        let mid = (start + end) / 2;
        let pts = self.pts;
        self.perm[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
            pts[a as usize][axis]
                .total_cmp(&pts[b as usize][axis])
                .then(a.cmp(&b))
        });
        let value = pts[self.perm[mid] as usize][axis];
        let left = self.node(start, mid);
        let right = self.node(mid, end);
        self.nodes[id as usize] = Node::Split {
            axis: axis as u8,
            value,
            left,
            right,
        };
        id
    }

    /// The 3 smallest squared distances from point `q` to other points (inf where fewer exist).
    fn nearest3(&self, q: usize) -> [f32; 3] {
        let mut best = [f32::INFINITY; 3];
        let p = self.pts[q];
        let mut stack = vec![(0u32, 0.0f32)];
        while let Some((id, bound)) = stack.pop() {
            if bound >= best[2] {
                continue;
            }
            match self.nodes[id as usize] {
                Node::Leaf { start, end } => {
                    for &i in &self.perm[start as usize..end as usize] {
                        if i as usize == q {
                            continue;
                        }
                        let o = self.pts[i as usize];
                        let d =
                            (p[0] - o[0]).powi(2) + (p[1] - o[1]).powi(2) + (p[2] - o[2]).powi(2);
                        if d < best[2] {
                            best[2] = d;
                            if best[2] < best[1] {
                                best.swap(1, 2);
                            }
                            if best[1] < best[0] {
                                best.swap(0, 1);
                            }
                        }
                    }
                }
                Node::Split {
                    axis,
                    value,
                    left,
                    right,
                } => {
                    let d = p[axis as usize] - value;
                    let (near, far) = if d < 0.0 {
                        (left, right)
                    } else {
                        (right, left)
                    };
                    stack.push((far, bound.max(d * d)));
                    stack.push((near, bound));
                }
            }
        }
        best
    }
}

/// Per point, the mean of the squared distances to its 3 nearest other points (fewer when the
/// cloud has fewer; 1e-7 at least).
pub fn knn3_mean_sq(points: &[[f32; 3]]) -> Vec<f32> {
    let tree = KdTree::build(points);
    (0..points.len())
        .into_par_iter()
        .with_min_len(512)
        .map(|i| {
            let b = tree.nearest3(i);
            let found: Vec<f32> = b.iter().copied().filter(|d| d.is_finite()).collect();
            let m = if found.is_empty() {
                1e-7
            } else {
                found.iter().sum::<f32>() / found.len() as f32
            };
            m.max(1e-7)
        })
        .collect()
}

/// The initial scene of a point cloud (`points` (N,3), `colors` (N,3) in [0, 1]).
pub fn scene_from_points(
    points: &[f32],
    colors: &[f32],
    opacity: f32,
    scale_factor: f32,
    sh_degree: u8,
) -> Result<Scene> {
    let n = points.len() / 3;
    if points.len() != n * 3 || colors.len() != n * 3 {
        return Err(Error::InvalidArgument(format!(
            "points and colours must both be (N,3), got {} and {} values",
            points.len(),
            colors.len()
        )));
    }
    if n == 0 {
        return Err(Error::InvalidArgument(
            "the initial point cloud is empty".into(),
        ));
    }
    if let Some(i) = points.iter().position(|v| !v.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "initial point {} has a non-finite coordinate",
            i / 3
        )));
    }
    if !(opacity > 0.0 && opacity < 1.0 && scale_factor > 0.0 && scale_factor.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "initial opacity must be in (0, 1) and the scale factor positive, got {opacity} and {scale_factor}"
        )));
    }
    let pts: Vec<[f32; 3]> = points.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let d2 = knn3_mean_sq(&pts);
    let mut s = Scene::zeroed(n, sh_degree);
    s.means.copy_from_slice(points);
    for i in 0..n {
        s.quats[i * 4] = 1.0;
        let ls = (d2[i].sqrt() * scale_factor).ln();
        s.log_scales[i * 3..i * 3 + 3].fill(ls);
    }
    s.opacity_logits.fill(logit(opacity as f64));
    for (o, c) in s.sh0.iter_mut().zip(colors) {
        *o = (c.clamp(0.0, 1.0) - 0.5) / SH_C0;
    }
    debug_assert_eq!(s.sh_rest.len(), n * sh_rest_count(sh_degree) * 3);
    Ok(s)
}

/// `n` points uniform in the box [lo, hi] with uniform random colours, drawn from the
/// counter-based generator under `seed`: (points (N*3), colours (N*3)).
pub fn random_points(n: usize, lo: [f32; 3], hi: [f32; 3], seed: u64) -> (Vec<f32>, Vec<f32>) {
    let k = key(seed, OP_INIT, 0);
    let mut pts = vec![0.0f32; n * 3];
    let mut cols = vec![0.0f32; n * 3];
    pts.par_chunks_mut(3)
        .zip(cols.par_chunks_mut(3))
        .enumerate()
        .with_min_len(4096)
        .for_each(|(i, (p, c))| {
            let s = Stream::new(k, i as u64);
            for a in 0..3 {
                let u = (s.word(a as u64) >> 40) as f32 * (1.0 / 16_777_216.0);
                p[a] = lo[a] + u * (hi[a] - lo[a]);
                c[a] = (s.word(3 + a as u64) >> 40) as f32 * (1.0 / 16_777_216.0);
            }
        });
    (pts, cols)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_matches_brute_force() {
        let (p, _) = random_points(700, [-1.0; 3], [1.0, 2.0, 0.5], 4);
        let pts: Vec<[f32; 3]> = p.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        let got = knn3_mean_sq(&pts);
        for i in (0..700).step_by(37) {
            let mut d: Vec<f32> = (0..700)
                .filter(|&j| j != i)
                .map(|j| (0..3).map(|a| (pts[i][a] - pts[j][a]).powi(2)).sum::<f32>())
                .collect();
            d.sort_by(|a, b| a.total_cmp(b));
            let want = (d[0] + d[1] + d[2]) / 3.0;
            assert!(
                (got[i] - want).abs() <= 1e-6 * want.max(1e-7),
                "{i}: {} vs {want}",
                got[i]
            );
        }
    }

    #[test]
    fn scene_from_points_follows_the_recipe() {
        let pts = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let cols = [0.5; 12];
        let s = scene_from_points(&pts, &cols, 0.1, 1.0, 3).expect("scene");
        assert_eq!(s.len(), 4);
        assert_eq!(s.sh_rest.len(), 4 * 15 * 3);
        // point 0: distances 1, 1, 1 -> scale 1 -> log 0
        assert!(s.log_scales[0].abs() < 1e-6);
        assert!((1.0 / (1.0 + (-s.opacity_logits[0]).exp()) - 0.1).abs() < 1e-6);
        assert!(s.sh0.iter().all(|&v| v.abs() < 1e-6));
        assert!(scene_from_points(&[], &[], 0.1, 1.0, 0).is_err());
    }
}
