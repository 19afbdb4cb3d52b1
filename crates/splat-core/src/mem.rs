//! Large output buffers backed by transparent huge pages, and the crate's prefetch hints (the
//! only `_mm_prefetch` calls: the kernels ask through these).
//!
//! Filling a fresh multi-hundred-MB array costs more in 4 KiB page faults than in the copy itself
//! (one fault and one page clear per 4 KiB). NumPy asks the kernel for huge pages on large
//! allocations (`madvise(MADV_HUGEPAGE)`), which makes `np.fromfile` about 3x faster than with
//! plain pages on these machines; readers that return new arrays do the same through
//! [`zeroed_f32`].

/// Arrays at least this large ask for huge pages.
const HUGE_MIN_BYTES: usize = 4 << 20;

/// A zero-filled vector of `len` floats. Large ones come untouched from the allocator (calloc
/// maps fresh zero pages) and are advised to use transparent huge pages before their first write,
/// so filling them faults once per 2 MiB instead of once per 4 KiB.
pub fn zeroed_f32(len: usize) -> Vec<f32> {
    let mut v = vec![0.0f32; len];
    let bytes = len * std::mem::size_of::<f32>();
    if bytes >= HUGE_MIN_BYTES {
        advise_huge(v.as_mut_ptr().cast(), bytes);
    }
    v
}

/// Output arrays of finished renders, kept for the next ones (see [`OutputPool`]).
pub static OUTPUTS: OutputPool = OutputPool::new(OUTPUT_KEEP_BYTES, OUTPUT_KEEP_BUFFERS);

/// Bytes of idle output buffers [`OUTPUTS`] keeps: three 1920x1080 frames (41.5 MB each with
/// their colour, depth and alpha planes), or 16 garden-sized ones.
pub const OUTPUT_KEEP_BYTES: usize = 128 << 20;
/// Idle buffers [`OUTPUTS`] keeps at most (the oldest go first).
pub const OUTPUT_KEEP_BUFFERS: usize = 24;

/// Float buffers handed back by the owners of released outputs (the binding's numpy arrays
/// return theirs when Python drops the last view), reused by the next outputs of a similar size.
///
/// A fresh output costs the kernel a page fault and a page clear per 4 KiB on its first write
/// (a 1920x1080 frame is 41.5 MB), or the allocator a memset when it recycles heap memory for
/// `calloc`; a reused buffer costs neither. Its values are whatever the last render left:
/// only for writers that write every value (the renderer does). Bounded: at most `keep_bytes`
/// and `keep_buffers` idle buffers; a buffer that would exceed them evicts the oldest. Only
/// `try_lock`: a busy lock, or one a `fork` left locked in a child, means a fresh buffer.
pub struct OutputPool {
    held: std::sync::Mutex<Vec<Vec<f32>>>,
    keep_bytes: usize,
    keep_buffers: usize,
}

impl OutputPool {
    pub const fn new(keep_bytes: usize, keep_buffers: usize) -> OutputPool {
        OutputPool {
            held: std::sync::Mutex::new(Vec::new()),
            keep_bytes,
            keep_buffers,
        }
    }

    /// A buffer of `len` floats for a writer that writes every one: the smallest idle buffer
    /// holding between `len` and `2 len` values (cut to `len`; the values are stale), else a
    /// fresh [`zeroed_f32`].
    pub fn take(&self, len: usize) -> Vec<f32> {
        let found = self.held.try_lock().ok().and_then(|mut held| {
            let best = held
                .iter()
                .enumerate()
                .filter(|(_, v)| v.len() >= len && v.len() / 2 <= len)
                .min_by_key(|(_, v)| v.len())
                .map(|(i, _)| i)?;
            Some(held.remove(best))
        });
        match found {
            Some(mut v) => {
                v.truncate(len);
                v
            }
            None => zeroed_f32(len),
        }
    }

    /// Keep `buf` for a later [`OutputPool::take`] (evicting the oldest idle buffers to stay
    /// within the bounds; one larger than the byte bound alone is dropped).
    pub fn give(&self, buf: Vec<f32>) {
        let bytes = |v: &Vec<f32>| v.len() * std::mem::size_of::<f32>();
        if buf.is_empty() || bytes(&buf) > self.keep_bytes {
            return;
        }
        let mut evicted = Vec::new();
        if let Ok(mut held) = self.held.try_lock() {
            let mut total: usize = held.iter().map(bytes).sum::<usize>() + bytes(&buf);
            while !held.is_empty() && (total > self.keep_bytes || held.len() >= self.keep_buffers) {
                let old = held.remove(0);
                total -= bytes(&old);
                evicted.push(old);
            }
            held.push(buf);
        }
        // the evicted buffers are freed here, after the lock is released
        drop(evicted);
    }

    /// Idle buffers and their bytes.
    pub fn held(&self) -> (usize, usize) {
        self.held
            .try_lock()
            .map_or((0, 0), |h| (h.len(), h.iter().map(|v| v.len() * 4).sum()))
    }
}

#[cfg(target_os = "linux")]
fn advise_huge(ptr: *mut u8, bytes: usize) {
    const PAGE: usize = 4096;
    let start = (ptr as usize).next_multiple_of(PAGE);
    let end = (ptr as usize + bytes) / PAGE * PAGE;
    if end > start {
        // SAFETY: [start, end) lies inside the allocation `ptr..ptr + bytes` that the caller owns
        // exclusively; MADV_HUGEPAGE only changes how the kernel backs the range, never its
        // contents (zero pages stay zero). A refusal (THP disabled, old kernel) is harmless.
        unsafe {
            libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge(_ptr: *mut u8, _bytes: usize) {}

/// Ask the CPU for the cache line holding `v` ahead of its use (a hint: it changes no value).
#[inline(always)]
pub fn prefetch<T>(v: &T) {
    prefetch_ptr(v as *const T, 0);
}

/// [`prefetch`] of `v[i]`; nothing when `i` is out of bounds.
#[inline(always)]
pub fn prefetch_at<T>(v: &[T], i: usize) {
    if let Some(x) = v.get(i) {
        prefetch(x);
    }
}

/// Ask for both ends of `*v`: the two cache lines a value of up to 64 bytes may span.
#[inline(always)]
pub fn prefetch_ends<T>(v: &T) {
    let p = (v as *const T).cast::<u8>();
    prefetch_ptr(p, 0);
    prefetch_ptr(p, std::mem::size_of::<T>().saturating_sub(1));
}

/// Ask the CPU for the cache line holding `base + i` (`i` counted in values of `T`). A prefetch
/// reads nothing architecturally and never faults, so the address need not be valid.
#[inline(always)]
pub fn prefetch_ptr<T>(base: *const T, i: usize) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing architecturally and never faults.
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(i).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (base, i);
}

/// Ask for `bytes` bytes from `p`: one hint per 64 bytes from `p` (the address need not be
/// valid, as for [`prefetch_ptr`]).
#[inline(always)]
pub fn prefetch_bytes<T>(p: *const T, bytes: usize) {
    let p = p.cast::<u8>();
    let mut off = 0;
    while off < bytes {
        prefetch_ptr(p, off);
        off += 64;
    }
}

/// Ask for every cache line of the `n >= 1` values from `p`, for writing (the CPU fetches the
/// lines ready to be modified). A hint: the address need not be valid.
#[inline(always)]
pub fn prefetch_for_write<T>(p: *const T, n: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_ET0};
        let (a, b) = (p as usize, p as usize + std::mem::size_of::<T>() * n - 1);
        for line in (a & !63..=b).step_by(64) {
            // SAFETY: prefetching never faults.
            unsafe { _mm_prefetch::<_MM_HINT_ET0>(line.max(a) as *const i8) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (p, n);
}

#[cfg(test)]
mod tests {
    #[test]
    fn zeroed_buffers_are_zero_at_any_size() {
        for len in [0, 1, 1000, (8 << 20) / 4 + 3] {
            let v = super::zeroed_f32(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
        }
    }

    #[test]
    fn output_pool_reuses_buffers_of_similar_size_within_its_bounds() {
        let pool = super::OutputPool::new(1000 * 4, 3);
        let mut a = pool.take(100);
        assert!(a.iter().all(|&x| x == 0.0));
        a.fill(7.0);
        let ptr = a.as_ptr();
        pool.give(a);
        assert_eq!(pool.held(), (1, 400));
        // too small (a 100-value buffer never serves 101) and too large (nor 49)
        let (big, small) = (pool.take(101), pool.take(49));
        assert!(big.as_ptr() != ptr && small.as_ptr() != ptr);
        assert_eq!((big.len(), small.len()), (101, 49));
        drop((big, small));
        assert_eq!(pool.held(), (1, 400));
        // a fitting request gets it back, stale values and all, cut to its length
        let b = pool.take(60);
        assert_eq!((b.as_ptr(), b.len()), (ptr, 60));
        assert!(b.iter().all(|&x| x == 7.0));
        assert_eq!(pool.held(), (0, 0));
        // bounds: at most 3 buffers and 1000 values; the oldest go first
        for n in [10, 20, 30, 40] {
            pool.give(vec![0.0; n]);
        }
        assert_eq!(pool.held(), (3, (20 + 30 + 40) * 4));
        pool.give(vec![0.0; 950]);
        assert_eq!(pool.held(), (2, (40 + 950) * 4));
        pool.give(vec![0.0; 1001]);
        assert_eq!(pool.held(), (2, (40 + 950) * 4));
        pool.give(vec![1.0; 600]);
        assert_eq!(pool.held(), (1, 600 * 4));
        // the smallest fitting buffer is taken
        pool.give(vec![2.0; 900]);
        assert_eq!(pool.held(), (1, 900 * 4));
        pool.give(vec![1.0; 40]);
        pool.give(vec![3.0; 30]);
        assert_eq!(pool.take(30)[0], 3.0);
        assert_eq!(pool.held(), (2, (900 + 40) * 4));
    }
}
