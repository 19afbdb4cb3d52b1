//! Large output buffers backed by transparent huge pages, and a prefetch hint.
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
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing architecturally and never faults; `v` is a valid
    // reference anyway.
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        _mm_prefetch::<_MM_HINT_T0>((v as *const T).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = v;
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
}
