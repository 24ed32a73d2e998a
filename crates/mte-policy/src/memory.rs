//! Process-wide allocator settings for programs that run policies: an opt-in call for
//! binaries and benchmarks, never made by the library itself.
//!
//! candle allocates a fresh buffer for every operation's output and frees it when the
//! tensor drops, so one PGD iteration on the `cpu` image preset allocates and frees
//! hundreds of buffers of 10 KB to a few MB, and a lockstep batch of 50 attacked queries
//! (100 camera frames) buffers of 50-100 MB. glibc's `malloc` gives memory at the top of its
//! heap back to the kernel once more than `M_TRIM_THRESHOLD` bytes are free there, serves
//! requests above its mmap threshold (at most 32 MiB) with fresh `mmap`s, and gives each
//! thread that allocates an arena of its own, made of 64 MiB `mmap`ed heaps that are unmapped
//! again when they empty. Each of those gives pages back, and the next operation pays a page
//! fault (and the kernel's zeroing) per 4 KiB: 5-8% of a batch-1 PGD iteration's samples were
//! in the kernel's fault path, and 22% of a two-worker sweep's CPU time was system time
//! (the protocol cell of issue 19, 50-episode lockstep groups). [`keep_freed_memory`] keeps
//! freed memory in the process instead.

/// The mmap threshold [`keep_freed_memory`] sets (bytes): glibc's own ceiling on 64-bit
/// targets (32 MiB, `DEFAULT_MMAP_THRESHOLD_MAX`). With `mmap` turned off for requests
/// (`M_MMAP_MAX` = 0) it matters only where the heap cannot grow and glibc falls back to
/// `mmap`.
pub const HEAP_REQUEST_MAX: i32 = 32 << 20;

/// Keeps freed memory in the process (glibc only): every thread allocates from the one main
/// heap (`M_ARENA_MAX` = 1), requests of any size come from it (`M_MMAP_MAX` = 0), and it is
/// never trimmed, so a steady-state loop of tensor operations reuses its pages. The process
/// keeps its peak heap size until it exits, which for an evaluation or training run is the
/// size it needs anyway (a one-worker pixel-PGD sweep's peak resident size fell, 381 to 296
/// MB, since freed blocks are reused across threads). Threads share the heap's lock; the
/// allocations are few and large next to the arithmetic between them.
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
        // SAFETY: `mallopt` only changes tunables of glibc's allocator; it takes its own
        // lock, and the values are in the ranges its manual documents (0 on rejection).
        let set = |option, value| unsafe { libc::mallopt(option, value) } == 1;
        [
            set(libc::M_ARENA_MAX, 1),
            set(libc::M_MMAP_MAX, 0),
            set(libc::M_MMAP_THRESHOLD, super::HEAP_REQUEST_MAX),
            set(libc::M_TRIM_THRESHOLD, i32::MAX),
        ]
        .iter()
        .all(|&ok| ok)
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
    fn glibc_accepts_every_setting_and_allocation_still_works() {
        assert!(super::keep_freed_memory());
        // Allocate and free across both sides of the old mmap threshold, on two threads
        // (one arena now serves both).
        let work = || {
            for len in [1usize << 10, 1 << 20, 16 << 20, 40 << 20, 96 << 20] {
                let v = vec![1u8; len];
                assert_eq!(v.iter().map(|&b| b as usize).sum::<usize>(), len);
            }
        };
        let other = std::thread::spawn(work);
        work();
        other.join().expect("the other thread allocates too");
    }
}
