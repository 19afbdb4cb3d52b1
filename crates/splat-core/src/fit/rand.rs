//! The fit's random draws: every draw is a pure function of (seed, purpose, step, index) through
//! the crate's counter-based generator ([`crate::rng`]), so no draw depends on the thread count,
//! on how many draws came before or on which Gaussians exist elsewhere.
//!
//! Purposes: [`OP_ORDER`] (camera order of an epoch), [`OP_SPLIT`] (split samples),
//! [`OP_RELOCATE`] and [`OP_ADD`] (MCMC multinomial draws), [`OP_NOISE`] (MCMC position
//! noise), [`OP_INIT`] (random initial points).
use crate::rng::{mix64, op_key, Stream, GAMMA};

pub const OP_ORDER: u32 = 101;
pub const OP_SPLIT: u32 = 102;
pub const OP_RELOCATE: u32 = 103;
pub const OP_ADD: u32 = 104;
pub const OP_NOISE: u32 = 105;
pub const OP_INIT: u32 = 106;

/// The stream key of (seed, purpose, step).
pub fn key(seed: u64, op: u32, step: u64) -> u64 {
    mix64(op_key(seed, op) ^ mix64(step.wrapping_add(1).wrapping_mul(GAMMA)))
}

/// A uniform draw in [0, 1) with 53 random bits: word 0 of element `index`'s stream.
pub fn uniform53(key: u64, index: u64) -> f64 {
    (Stream::new(key, index).word(0) >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// The training view order of epoch `epoch`: a permutation of 0..n (views sorted by a hash of
/// (seed, epoch, view)), so each epoch shows every view once, as INRIA's camera stack does.
pub fn epoch_order(seed: u64, epoch: u64, n: usize) -> Vec<u32> {
    let k = key(seed, OP_ORDER, epoch);
    let mut v: Vec<(u64, u32)> = (0..n as u32)
        .map(|i| (Stream::new(k, i as u64).word(0), i))
        .collect();
    v.sort_unstable();
    v.into_iter().map(|(_, i)| i).collect()
}

/// `count` indices drawn with replacement, index i with probability weights[i] / sum (the
/// weights are summed in order in f64; draw j is uniform j of (seed, op, step) times the sum,
/// located by binary search). Empty when the weights sum to zero.
pub fn multinomial(weights: &[f32], count: usize, seed: u64, op: u32, step: u64) -> Vec<usize> {
    let mut cum = Vec::with_capacity(weights.len());
    let mut s = 0.0f64;
    for &w in weights {
        s += w.max(0.0) as f64;
        cum.push(s);
    }
    if s.is_nan() || s <= 0.0 {
        return Vec::new();
    }
    let k = key(seed, op, step);
    (0..count)
        .map(|j| {
            let u = uniform53(k, j as u64) * s;
            // first index whose cumulative weight exceeds u (skips zero-weight entries)
            cum.partition_point(|&c| c <= u).min(weights.len() - 1)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epoch_order_is_a_permutation_that_changes_per_epoch() {
        let a = epoch_order(3, 0, 50);
        let b = epoch_order(3, 1, 50);
        let mut s = a.clone();
        s.sort();
        assert_eq!(s, (0..50).collect::<Vec<u32>>());
        assert_ne!(a, b);
        assert_eq!(a, epoch_order(3, 0, 50));
    }

    #[test]
    fn multinomial_follows_the_weights() {
        let w = [0.0f32, 1.0, 3.0, 0.0];
        let d = multinomial(&w, 40_000, 1, OP_ADD, 7);
        let mut c = [0usize; 4];
        for i in d {
            c[i] += 1;
        }
        assert_eq!(c[0] + c[3], 0);
        let frac = c[2] as f64 / 40_000.0;
        assert!((frac - 0.75).abs() < 0.01, "{frac}");
        assert!(multinomial(&[0.0, 0.0], 3, 1, OP_ADD, 0).is_empty());
    }
}
