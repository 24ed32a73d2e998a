//! Process-wide allocator settings for programs that run policies: an opt-in call for
//! binaries and benchmarks, never made by the library itself.
//!
//! candle allocates a fresh buffer for every operation's output and frees it when the
//! tensor drops, so one PGD iteration on the `cpu` image preset allocates and frees
//! hundreds of buffers of 10 KB to a few MB. glibc's `malloc` gives memory at the top of its
//! heap back to the kernel once more than `M_TRIM_THRESHOLD` bytes are free there, and serves
//! the largest requests with fresh `mmap`s; either way the next operation touches new pages
//! and pays a page fault per 4 KiB (5-8% of a PGD iteration's samples were in the kernel's
//! fault path). [`keep_freed_memory`] keeps freed memory in the heap instead.

/// The largest request glibc serves from its heap after [`keep_freed_memory`] (bytes): its
/// own ceiling for the dynamic mmap threshold on 64-bit targets (32 MiB,
/// `DEFAULT_MMAP_THRESHOLD_MAX`). Larger requests still get their own `mmap`.
pub const HEAP_REQUEST_MAX: i32 = 32 << 20;

/// Keeps freed memory in the process (glibc only): requests up to [`HEAP_REQUEST_MAX`]
/// come from the heap and the heap is never trimmed, so a steady-state loop of tensor
/// operations reuses its pages. The process keeps its peak heap size until it exits, which
/// for an evaluation or training run is the size it needs anyway.
///
/// Returns whether the settings were applied: `false` on targets other than Linux with
/// glibc (their allocators are left as they are) or where glibc refused a value.
/// Call it once, at the start of `main`, before threads start.
pub fn keep_freed_memory() -> bool {
    imp::keep_freed_memory()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
mod imp {
    pub fn keep_freed_memory() -> bool {
        // SAFETY: `mallopt` only changes two tunables of glibc's allocator; it takes its own
        // lock, and the values are in the ranges its manual documents (0 on rejection).
        let (mmap, trim) = unsafe {
            (
                libc::mallopt(libc::M_MMAP_THRESHOLD, super::HEAP_REQUEST_MAX),
                libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX),
            )
        };
        mmap == 1 && trim == 1
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
mod imp {
    pub fn keep_freed_memory() -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn glibc_accepts_both_settings_and_allocation_still_works() {
        assert!(super::keep_freed_memory());
        // Allocate and free across both sides of the new threshold.
        for len in [1usize << 10, 1 << 20, 16 << 20, 40 << 20] {
            let v = vec![1u8; len];
            assert_eq!(v.iter().map(|&b| b as usize).sum::<usize>(), len);
        }
    }
}
