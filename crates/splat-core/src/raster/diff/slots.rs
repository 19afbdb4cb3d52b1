//! The per-intersection gradient sums ("slots") and the bands of tile rows they are processed
//! in: each (tile, Gaussian) intersection of a band gets a slot of its own, written by the tile
//! backward in tile-list order (`TileSink`), then added to its Gaussian's running sums
//! ([`AccRow`]) in row-major tile order by one task per binning chunk (`Workspace::reduce_band`),
//! so no float is reduced across threads.
use rayon::prelude::*;

use super::{blend_bwd, DepthKind, ImageGrads, Saved, Workspace};
use crate::raster::blend::LANES;
use crate::raster::sort::TileBins;

/// The per-intersection gradient sums ("slots"): layout of one slot's floats.
pub(crate) mod slot {
    /// dL/d(colour) of the r, g, b and depth channels: sum of w g_k (C0 + k).
    pub const C0: usize = 0;
    /// With u = e dL/dalpha per pixel (e = opacity exp(-sigma), so dL/dsigma = -u):
    /// sum u, u dx, u dy, u dx^2, u dx dy, u dy^2 (dx, dy: mean minus pixel centre).
    pub const V0: usize = 4;
    pub const VDX: usize = 5;
    pub const VDY: usize = 6;
    pub const VDX2: usize = 7;
    pub const VDXDY: usize = 8;
    pub const VDY2: usize = 9;
    /// sum |dL/dmean2d| per pixel, per axis (gsplat's absgrad; zero unless asked for).
    pub const ABSX: usize = 10;
    pub const ABSY: usize = 11;
    pub const LEN: usize = 12;
}

/// A slot's bytes.
pub const SLOT_BYTES: usize = slot::LEN * 4;

/// One splat's running sums of its slots: the `slot::LEN` values padded to 16 floats and
/// aligned to 64 bytes, so that each random access of the slot sums (`reduce_band`) and of the
/// per-Gaussian pass touches one cache line (a 48-byte row straddles two lines half the time).
/// The padding stays +0.0.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(64))]
pub(crate) struct AccRow(pub(crate) [f32; 16]);

impl AccRow {
    /// The summed slot values.
    #[inline(always)]
    pub(crate) fn sums(&self) -> &[f32; slot::LEN] {
        self.0[..slot::LEN].try_into().expect("16 >= slot::LEN")
    }

    /// Add one slot's values, element by element, to the sums (`keep`) or to +0.0 (the
    /// splat's first slot: its sums' memory is stale). The plain float additions, 4 lanes at
    /// a time where the target has SSE, so the bits are those of sums that start at +0.0.
    #[inline(always)]
    fn add(&mut self, s: &[f32; slot::LEN], keep: bool) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: SSE is part of x86_64; every access lies inside `self.0` (64-byte aligned,
        // so the aligned loads hold) or `s`.
        unsafe {
            use std::arch::x86_64::*;
            // all ones (keep the sums) or +0.0
            let m = _mm_castsi128_ps(_mm_set1_epi32(-(keep as i32)));
            let a = self.0.as_mut_ptr();
            for q in 0..slot::LEN / 4 {
                let old = _mm_and_ps(_mm_load_ps(a.add(4 * q)), m);
                let v = _mm_add_ps(old, _mm_loadu_ps(s.as_ptr().add(4 * q)));
                _mm_store_ps(a.add(4 * q), v);
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        for (a, v) in self.0.iter_mut().zip(s) {
            *a = if keep { *a } else { 0.0 } + v;
        }
    }
}

/// The summed slots by sorted position as the per-Gaussian pass reads them: the rows, and
/// which of them hold sums (1 once `reduce_band` added a slot; the others read as zeros).
#[derive(Clone, Copy)]
pub(crate) struct Sums<'a> {
    pub(crate) acc: &'a [AccRow],
    pub(crate) touched: &'a [u8],
}

impl Sums<'_> {
    /// Sorted splat p's sums (zeros where no slot was added).
    #[inline(always)]
    pub(crate) fn get(&self, p: usize) -> &[f32; slot::LEN] {
        const ZERO: [f32; slot::LEN] = [0.0; slot::LEN];
        if self.touched[p] != 0 {
            self.acc[p].sums()
        } else {
            &ZERO
        }
    }
}

impl Workspace {
    /// The summed slots of the last backward, by sorted position.
    pub(super) fn sums(&self) -> Sums<'_> {
        Sums {
            acc: &self.acc,
            touched: &self.touched,
        }
    }

    /// Bands of tile rows [r0, r1) whose slots fit the budget (at least one row each).
    pub(super) fn bands(&self, budget: usize) -> Vec<(u32, u32)> {
        let (tx, ty) = (self.bins.tiles_x as usize, self.bins.tiles_y as usize);
        let cap = (budget / SLOT_BYTES).max(1);
        let mut bands = Vec::new();
        let (mut r0, mut sum) = (0usize, 0usize);
        for r in 0..ty {
            let row: usize = (r * tx..(r + 1) * tx).map(|t| self.bins.tile_len(t)).sum();
            if r > r0 && sum + row > cap {
                bands.push((r0 as u32, r as u32));
                r0 = r;
                sum = 0;
            }
            sum += row;
        }
        if ty > r0 {
            bands.push((r0 as u32, ty as u32));
        }
        bands
    }

    /// The band of tile rows [r0, r1)'s slot layout: chunk c's entries of those rows are one
    /// contiguous run of its list entries, put at `band_base[c]`. Returns the band's slots.
    pub(super) fn band_layout(&mut self, r0: u32, r1: u32) -> usize {
        let tx = self.bins.tiles_x as usize;
        self.band_base.clear();
        self.band_lo.clear();
        let mut sum = 0usize;
        for c in 0..self.bins.n_chunks() {
            let lo = self.bins.start(c, r0 as usize * tx);
            let hi = self.bins.start(c, r1 as usize * tx);
            self.band_base.push(sum);
            self.band_lo.push(lo);
            sum += (hi - lo) as usize;
        }
        sum
    }

    /// Run the tile backward over the tiles of rows [r0, r1); returns the evaluations and the
    /// band's share of dL/d(background).
    pub(super) fn blend_band(
        &mut self,
        sv: &Saved,
        grads: &ImageGrads<'_>,
        r0: u32,
        r1: u32,
    ) -> (u64, [f64; 3]) {
        let tiles_x = self.bins.tiles_x as usize;
        let sink = SlotWriter {
            base: self.slots.as_mut_ptr(),
            written: self.written.as_mut_ptr(),
            len: self.slots.len().min(self.written.len()),
        };
        let (sorted, bins, tiles) = (&self.sorted, &self.bins, &self.tiles);
        let (band_base, band_lo) = (&self.band_base, &self.band_lo);
        let (width, height) = (sv.cam.width as usize, sv.cam.height as usize);
        let expected = sv.opts.depth == DepthKind::Expected;
        let per_tile: Vec<(u64, [f64; 3])> = (r0 as usize * tiles_x..r1 as usize * tiles_x)
            .into_par_iter()
            .map(|t| {
                let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
                let empty = bins.lists(t).all(|l| l.is_empty());
                if empty && grads.skip_background {
                    return (0, [0.0; 3]);
                }
                let mut pix = blend_bwd::PixIn::default();
                let bg = blend_bwd::tile_inputs(
                    x0,
                    y0,
                    width,
                    height,
                    &tiles[t],
                    grads,
                    sv.blend.background,
                    expected,
                    !grads.skip_background,
                    sv.blend.simd,
                    &mut pix,
                );
                if empty {
                    return (0, bg);
                }
                let mut out = TileSink {
                    w: &sink,
                    bins,
                    band_base,
                    band_lo,
                    t,
                    chunk: 0,
                    next: 0,
                    end: 0,
                };
                let evals = blend_bwd::bwd_tile(
                    x0 as u32,
                    y0 as u32,
                    &sv.blend,
                    sorted,
                    bins.lists(t),
                    &pix,
                    &mut out,
                    sv.opts.absgrad,
                    grads.depth.is_some(),
                );
                out.finish();
                (evals, bg)
            })
            .collect();
        let mut bg = [0.0f64; 3];
        let mut evals = 0;
        for (e, b) in per_tile {
            evals += e;
            for c in 0..3 {
                bg[c] += b[c];
            }
        }
        (evals, bg)
    }

    /// Add each visible splat's slots of rows [r0, r1) to its running sums, in row-major
    /// tile order: one task per binning chunk walks the chunk's slots of the band in storage
    /// order (tile by tile), adding each to its splat's sums, which only that task touches.
    /// Slots the tile pass did not write (`written` 0: zero sums, which would leave the
    /// running sums' bits unchanged, see `SlotSink::zero`) are skipped. With `first` (the
    /// frame's first band) each task clears its chunk's touched flags first; a splat's first
    /// slot is then added to +0.0 rather than to its stale sums (no zeroing pass over the
    /// sums, 64 bytes per visible splat, which costs about a millisecond per frame).
    pub(super) fn reduce_band(&mut self, r0: u32, r1: u32, first: bool) {
        let tx = self.bins.tiles_x as usize;
        let (t0, t1) = (r0 as usize * tx, r1 as usize * tx);
        let (slots, written) = (&self.slots, &self.written);
        let (bins, band_base) = (&self.bins, &self.band_base);
        self.acc
            .par_chunks_mut(TileBins::CHUNK)
            .zip(self.touched.par_chunks_mut(TileBins::CHUNK))
            .enumerate()
            .for_each(|(c, (accs, touched))| {
                if first {
                    touched.fill(0);
                }
                let base = c * TileBins::CHUNK;
                let items = bins.chunk_items(c, t0, t1);
                let run = &slots[band_base[c]..band_base[c] + items.len()];
                let wr = &written[band_base[c]..band_base[c] + items.len()];
                for (k, ((&p, s), &w)) in items.iter().zip(run).zip(wr).enumerate() {
                    // the sums are a random access (L2 at best): fetch them ahead
                    if let (Some(&ahead), Some(&1)) =
                        (items.get(k + REDUCE_PREFETCH), wr.get(k + REDUCE_PREFETCH))
                    {
                        crate::mem::prefetch_at(accs, ahead as usize - base);
                    }
                    if w == 0 {
                        continue;
                    }
                    let q = p as usize - base;
                    accs[q].add(s, touched[q] != 0);
                    touched[q] = 1;
                }
            });
    }
}

/// How many slots ahead the slot sums prefetch the running sums they add to.
const REDUCE_PREFETCH: usize = 16;

/// The band's slot buffer and its written flags, written from the tile tasks.
struct SlotWriter {
    base: *mut [f32; slot::LEN],
    written: *mut u8,
    len: usize,
}

// SAFETY: each slot index (slot and flag) is written by exactly one (tile, splat) pair, hence
// one task (see `TileSink::put`), and nothing reads the buffers during the tile pass.
unsafe impl Sync for SlotWriter {}

/// Puts one tile's slots in list order: chunk c's entries of tile t go to consecutive slots
/// from band_base[c] + start(c, t) - band_lo[c].
struct TileSink<'a> {
    w: &'a SlotWriter,
    bins: &'a TileBins,
    band_base: &'a [usize],
    band_lo: &'a [u32],
    t: usize,
    /// The next chunk to start, and the current chunk's next and end slots.
    chunk: usize,
    next: usize,
    end: usize,
}

impl TileSink<'_> {
    /// Every entry was put (the kernels' contract).
    fn finish(&mut self) {
        while self.next == self.end && self.chunk < self.bins.n_chunks() {
            self.advance();
        }
        assert!(
            self.next == self.end,
            "a kernel left entries of tile {} without a slot",
            self.t
        );
    }

    fn advance(&mut self) {
        let c = self.chunk;
        let (s0, s1) = (self.bins.start(c, self.t), self.bins.start(c, self.t + 1));
        self.next = self.band_base[c] + (s0 - self.band_lo[c]) as usize;
        self.end = self.next + (s1 - s0) as usize;
        self.chunk += 1;
    }
}

impl TileSink<'_> {
    /// The next entry's slot index.
    #[inline(always)]
    fn next_slot(&mut self) -> usize {
        while self.next == self.end {
            assert!(
                self.chunk < self.bins.n_chunks(),
                "more slots than list entries"
            );
            self.advance();
        }
        let i = self.next;
        assert!(i < self.w.len, "slot index out of range");
        self.next += 1;
        i
    }
}

impl blend_bwd::SlotSink for TileSink<'_> {
    #[inline]
    fn put(&mut self, _pos: u32, vals: &[f32; slot::LEN]) {
        let i = self.next_slot();
        // SAFETY: i is in bounds (checked) and belongs to this tile's entries only: chunk c's
        // entries of tile t are [start(c, t), start(c, t + 1)), a run no other tile shares.
        unsafe {
            *self.w.base.add(i) = *vals;
            *self.w.written.add(i) = 1;
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[inline]
    unsafe fn put_m512(&mut self, _pos: u32, v: std::arch::x86_64::__m512) {
        let i = self.next_slot();
        // SAFETY: as in `put`; lanes 0..12 are stored, the slot's 12 floats; AVX-512F is
        // present (the caller's contract).
        unsafe {
            std::arch::x86_64::_mm512_mask_storeu_ps(
                self.w.base.add(i) as *mut f32,
                (1 << slot::LEN) - 1,
                v,
            );
            *self.w.written.add(i) = 1;
        }
    }

    #[inline]
    fn zero(&mut self, _pos: u32) {
        let i = self.next_slot();
        // SAFETY: as in `put`
        unsafe { *self.w.written.add(i) = 0 };
    }
}
