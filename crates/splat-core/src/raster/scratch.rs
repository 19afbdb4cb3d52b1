//! A frame's working buffers, kept from frame to frame.
//!
//! A frame of the forward renderer fills four large buffers before its blend: the visible
//! splats per projection chunk, the sort's keys (and their scratch), the depth-sorted splats
//! and the tile lists. Allocated fresh, each 4 KiB of them costs a page fault and a page clear
//! on first write, which on the test VMs costs more than filling them (4-10% of the 1M-Gaussian
//! pair's CPU). A frame takes a [`FrameScratch`] from a pool (its batch's, else the process's)
//! and hands it back when it is done, so the next frames write into memory already mapped. Every buffer is written
//! before it is read, so what an earlier frame left in it never reaches an image.
use std::sync::Mutex;

use super::project::Splat;
use super::sort::{Footprints, TileBins};

/// Bytes of capacity the pool keeps (two grid-5 1080p frames in flight need about 230 MB).
const KEEP_BYTES: usize = 256 << 20;

/// One frame's buffers.
#[derive(Default)]
pub(crate) struct FrameScratch {
    /// Visible splats per projection chunk.
    pub(crate) parts: Vec<Vec<Splat>>,
    /// The sort's (depth bits, payload) keys and their scratch.
    pub(crate) keys: Vec<(u32, u32)>,
    pub(crate) tmp: Vec<(u32, u32)>,
    /// The splats in depth order, and their tile footprints.
    pub(crate) sorted: Vec<Splat>,
    pub(crate) footprints: Footprints,
    pub(crate) bins: TileBins,
}

impl FrameScratch {
    /// Bytes of capacity held.
    fn bytes(&self) -> usize {
        let splat = std::mem::size_of::<Splat>();
        let parts: usize = self.parts.iter().map(Vec::capacity).sum();
        (parts + self.sorted.capacity()) * splat
            + (self.keys.capacity() + self.tmp.capacity()) * 8
            + self.footprints.capacity_bytes()
            + self.bins.capacity_bytes()
    }
}

/// Buffers of finished frames, largest last.
pub(crate) struct Pool {
    held: Mutex<Vec<FrameScratch>>,
    /// Bytes of capacity kept (`usize::MAX`: all).
    keep: usize,
    /// Only `try_lock`: a busy or poisoned lock, or one a `fork` left locked in a child, just
    /// means fresh buffers (the process-wide pool).
    try_only: bool,
}

/// The process-wide pool, for single frames and between batches.
pub(crate) static GLOBAL: Pool = Pool {
    held: Mutex::new(Vec::new()),
    keep: KEEP_BYTES,
    try_only: true,
};

impl Pool {
    /// A pool for one batch render: it keeps the buffers of every frame in flight (their
    /// number is bounded by the thread pool's nesting, usually two or three per thread), so
    /// no frame after the first few allocates; [`Pool::retire`] hands them to [`GLOBAL`].
    pub(crate) fn for_batch() -> Pool {
        let first = GLOBAL.take();
        Pool {
            held: Mutex::new(vec![first]),
            keep: usize::MAX,
            try_only: false,
        }
    }

    fn lock(&self) -> Option<std::sync::MutexGuard<'_, Vec<FrameScratch>>> {
        if self.try_only {
            self.held.try_lock().ok()
        } else {
            self.held.lock().ok()
        }
    }

    /// Buffers for a frame: the largest the pool holds, else empty ones.
    pub(crate) fn take(&self) -> FrameScratch {
        self.lock().and_then(|mut p| p.pop()).unwrap_or_default()
    }

    /// Hand a frame's buffers back (kept while the pool holds at most its `keep` bytes).
    pub(crate) fn give(&self, scratch: FrameScratch) {
        if let Some(mut pool) = self.lock() {
            let fits = self.keep == usize::MAX || {
                let held: usize = pool.iter().map(FrameScratch::bytes).sum();
                held + scratch.bytes() <= self.keep
            };
            if fits {
                pool.push(scratch);
                // largest last: the next frame most likely needs as much
                pool.sort_by_cached_key(FrameScratch::bytes);
            }
        }
    }

    /// Move a batch pool's buffers to [`GLOBAL`], largest first, as far as it keeps them.
    pub(crate) fn retire(self) {
        let held = self.held.into_inner().unwrap_or_default();
        for s in held.into_iter().rev() {
            GLOBAL.give(s);
        }
    }
}
