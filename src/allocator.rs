//! Process-wide heap tuning: keep freed tensor buffers in glibc's heap instead of returning them.
//!
//! burn's CPU backend allocates a fresh buffer for most tensor ops and frees it soon after. glibc
//! serves every block above its mmap threshold (128 KiB at start, raised adaptively to at most
//! 32 MiB) with a new `mmap` and hands it back with `munmap` on free, and trims the heap's top
//! once more than twice that threshold is free. Every such buffer's pages are then faulted in and
//! zeroed by the kernel again on first touch. Measured on a 15-step reacher run (2 cores): 6.5
//! million minor page faults and 24 of 45 s wall in the kernel; with both thresholds at 1 GiB,
//! 0.24 million faults, 1 s in the kernel and 25 s wall, the same weights to the byte, and a
//! peak resident size of 926 MB against 859 MB.

/// The mmap and trim thresholds set by [`retain_freed_memory`]: 1 GiB, above any single tensor
/// procl allocates, so large blocks come from (and go back to) the heap.
pub const RETAINED_BLOCK_BYTES: i32 = 1 << 30;

/// Make glibc keep freed memory in the heap for reuse (see the module docs). It changes
/// allocator behaviour for the whole process, so the binary calls it at start and the test
/// helpers before their training runs (it is idempotent), never the training code itself.
/// Returns whether the allocator took both settings;
/// on targets other than Linux with glibc it does nothing and returns `false`.
pub fn retain_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only adjusts glibc's allocator parameters; any value is accepted or
        // rejected by glibc (returning 0), and the call is safe at any point in the process.
        let mmap_set = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, RETAINED_BLOCK_BYTES) };
        let trim_set = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, RETAINED_BLOCK_BYTES) };
        mmap_set == 1 && trim_set == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_accepts_both_thresholds() {
        let taken = retain_freed_memory();
        assert_eq!(taken, cfg!(all(target_os = "linux", target_env = "gnu")));
    }

    /// Minor page faults of the calling thread so far.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn thread_minor_faults() -> i64 {
        // SAFETY: getrusage writes into the zeroed struct it is given and reads nothing else.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        let status = unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut usage) };
        assert_eq!(status, 0, "getrusage(RUSAGE_THREAD) failed");
        usage.ru_minflt
    }

    /// Allocate a 48 MiB block and write one byte per page, so every page is touched. The size
    /// is above the 32 MiB that glibc's adaptive threshold can reach, so by default the block is
    /// always mapped afresh, and below the 64 MiB heaps of the arenas of threads other than the
    /// main one (a larger block is mapped afresh whatever the threshold; the test runs on a
    /// harness thread).
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn touched_block() -> Vec<u8> {
        let mut block = vec![0u8; 48 << 20];
        for page in block.iter_mut().step_by(4096) {
            *page = 1;
        }
        block
    }

    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn a_freed_large_block_is_reused_without_new_page_faults() {
        // Without the thresholds, glibc maps the block afresh each time and the kernel faults in
        // all 12288 of its pages again; with them, the second block reuses the first one's pages
        // from the heap.
        assert!(retain_freed_memory());
        drop(std::hint::black_box(touched_block()));
        let before = thread_minor_faults();
        let second = std::hint::black_box(touched_block());
        let faults = thread_minor_faults() - before;
        drop(second);
        assert!(
            faults < 1024,
            "{faults} page faults for a reused 48 MiB block"
        );
    }
}
