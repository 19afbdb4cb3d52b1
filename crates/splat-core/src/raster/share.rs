//! Colours shared between the scenes of one batch render.
//!
//! A clean scene and its perturbed copy (a training pair) are rendered from the same cameras.
//! Morphological noise and pruning keep each surviving Gaussian's mean and SH coefficients, so
//! its view-dependent colour is the same in both renders of a frame; for the 1M-Gaussian SH-3
//! pair scene, reading 48 SH values per visible Gaussian and summing them is most of what the
//! projection costs beyond its first pass. [`colour_map`] finds, once per batch, the Gaussians
//! of another scene whose mean and SH bits equal a Gaussian of the first scene; the frame's
//! render of the first scene records the colours it computes ([`ColourSlot`]) and the other
//! scenes' renders of that frame take them instead of evaluating the SH again. The colour is a
//! pure function of (mean, SH, degree, camera), so the images are the same bits either way.
use rayon::prelude::*;

use crate::scene::SceneView;

/// `map[j]` of a Gaussian with no equal in the first scene.
pub(crate) const NO_MATCH: u32 = u32::MAX;

/// How far past the last match the greedy matcher looks for a Gaussian's mean (a pruned copy
/// keeps the order, so its next Gaussian is at most a run of pruned ones further; a longer
/// run only costs the share of the Gaussian after it).
const WINDOW: usize = 64;

/// Gaussians of the other scene matched before [`colour_map`] gives up on one of which fewer
/// than an eighth match.
const PROBE: usize = 4096;

/// One Gaussian's colour computed in one frame: `[r, g, b, stamp]` as bits, valid for the
/// frame whose stamp it holds (stamps start at 1, so a zeroed slot is never valid).
pub(crate) type ColourSlot = [u32; 4];

/// A zeroed slot buffer for a first scene of `n` Gaussians (zeroed memory comes from the
/// allocator untouched: only the slots a frame writes are ever faulted in).
pub(crate) fn slots(n: usize) -> Vec<ColourSlot> {
    vec![[0u32; 4]; n]
}

/// For each Gaussian j of `other`, the index of a Gaussian of `base` with the same mean, DC and
/// higher SH bits (`NO_MATCH` when none was found), or `None` when the scenes' SH layouts
/// differ or nothing matches. Greedy in index order (a pruned copy is a subsequence of its
/// source): only a found equality is ever used, so a wrong guess costs a share, never a bit.
pub(crate) fn colour_map(base: &SceneView<'_>, other: &SceneView<'_>) -> Option<Vec<u32>> {
    if base.sh_degree != other.sh_degree || base.is_empty() || other.is_empty() {
        return None;
    }
    let (n, m) = (base.len(), other.len());
    if n > NO_MATCH as usize {
        return None;
    }
    let bits = |v: &[f32], i: usize| {
        [
            v[3 * i].to_bits(),
            v[3 * i + 1].to_bits(),
            v[3 * i + 2].to_bits(),
        ]
    };
    let mut map = vec![NO_MATCH; m];
    let mut next = 0usize;
    let mut found = 0usize;
    for (j, slot) in map.iter_mut().enumerate() {
        // a copy whose means moved (spatial noise) shares nothing: stop looking early rather
        // than scan WINDOW Gaussians for each of its Gaussians
        if j == PROBE && found * 8 < PROBE {
            return None;
        }
        let want = bits(other.means, j);
        let end = (next + WINDOW).min(n);
        if let Some(d) = (next..end).position(|i| bits(base.means, i) == want) {
            *slot = (next + d) as u32;
            next += d + 1;
            found += 1;
        }
    }
    // the SH must match too (a radiometric perturbation keeps the means)
    let k = base.sh_rest_k() * 3;
    let same = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
    map.par_chunks_mut(4096).enumerate().for_each(|(c, part)| {
        for (jj, slot) in part.iter_mut().enumerate() {
            if *slot == NO_MATCH {
                continue;
            }
            let (i, j) = (*slot as usize, c * 4096 + jj);
            let ok = same(&base.sh0[3 * i..3 * i + 3], &other.sh0[3 * j..3 * j + 3])
                && same(
                    &base.sh_rest[k * i..k * i + k],
                    &other.sh_rest[k * j..k * j + k],
                );
            if !ok {
                *slot = NO_MATCH;
            }
        }
    });
    map.iter().any(|&i| i != NO_MATCH).then_some(map)
}

/// What a frame's projection does with shared colours.
pub(crate) enum FrameColours<'a> {
    /// Nothing shared.
    Off,
    /// The first scene: Gaussian i's computed colour goes to `slots[i]` with the stamp.
    Record(&'a mut [ColourSlot], u32),
    /// Another scene: Gaussian j takes `slots[map[j]]` when it holds the stamp.
    Reuse(&'a [u32], &'a [ColourSlot], u32),
}

/// [`FrameColours`] for one projection chunk of Gaussians [lo, hi).
pub(crate) enum ChunkColours<'a> {
    Off,
    /// `slots[i - lo]` receives Gaussian i's colour.
    Record(&'a mut [ColourSlot], usize, u32),
    Reuse(&'a [u32], &'a [ColourSlot], u32),
}

impl ChunkColours<'_> {
    /// The colour recorded for Gaussian `i` of this (reusing) scene this frame, if any.
    #[inline(always)]
    pub(crate) fn lookup(&self, i: usize) -> Option<[f32; 3]> {
        match self {
            ChunkColours::Reuse(map, slots, stamp) => {
                let m = map[i];
                if m == NO_MATCH {
                    return None;
                }
                let s = slots[m as usize];
                (s[3] == *stamp).then(|| [s[0], s[1], s[2]].map(f32::from_bits))
            }
            _ => None,
        }
    }

    /// Prefetch what [`ChunkColours::lookup`] will read for Gaussian `i`; false when the
    /// colour will not come from another scene (so its SH will be read).
    #[inline(always)]
    pub(crate) fn prefetch(&self, i: usize) -> bool {
        match self {
            ChunkColours::Reuse(map, slots, _) if map[i] != NO_MATCH => {
                crate::mem::prefetch(&slots[map[i] as usize]);
                true
            }
            _ => false,
        }
    }

    /// Record Gaussian `i`'s colour (a no-op unless this is the recording scene).
    #[inline(always)]
    pub(crate) fn record(&mut self, i: usize, rgb: [f32; 3]) {
        if let ChunkColours::Record(slots, lo, stamp) = self {
            let [r, g, b] = rgb.map(f32::to_bits);
            slots[i - *lo] = [r, g, b, *stamp];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;

    fn cloud(n: usize) -> Scene {
        let mut s = Scene::empty(1);
        let k = s.sh_rest_k() * 3;
        for i in 0..n {
            let v = i as f32;
            s.means.extend([v * 0.001, v * 0.002, 1.0 + v * 0.003]);
            s.quats.extend([1.0, 0.0, 0.0, 0.0]);
            s.log_scales.extend([-3.0; 3]);
            s.opacity_logits.push(0.0);
            s.sh0.extend([0.1, 0.2, 0.3]);
            s.sh_rest.extend((0..k).map(|c| (i * k + c) as f32 * 1e-4));
        }
        s
    }

    /// A pruned copy maps every survivor to its source; a copy whose means all moved maps
    /// nothing (and gives up after the probe); another SH degree maps nothing.
    #[test]
    fn maps_survivors_and_gives_up_on_moved_means() {
        let base = cloud(3 * PROBE);
        let keep: Vec<bool> = (0..base.len()).map(|i| i % 5 != 2).collect();
        let kept = base.filter(&keep);
        let map = colour_map(&base.view(), &kept.view()).expect("a pruned copy matches");
        let want: Vec<u32> = (0..base.len() as u32).filter(|&i| i % 5 != 2).collect();
        assert_eq!(map, want);
        let mut moved = kept.clone();
        for v in moved.means.iter_mut() {
            *v += 0.5;
        }
        assert!(colour_map(&base.view(), &moved.view()).is_none());
        let mut lower = Scene::empty(0);
        lower.means = kept.means.clone();
        lower.quats = kept.quats.clone();
        lower.log_scales = kept.log_scales.clone();
        lower.opacity_logits = kept.opacity_logits.clone();
        lower.sh0 = kept.sh0.clone();
        assert!(colour_map(&base.view(), &lower.view()).is_none());
    }
}
