//! Allocator settings for the training loops.

/// Keep freed memory for reuse. glibc hands blocks of 128 KiB and more back to the OS
/// (munmap, heap trimming), so a training loop, which frees and reallocates the same
/// activations every step, pays a page fault per 4 KiB of them (~110 K faults per d512 LM
/// step; a batch-256 tokenizer step's 100 MB im2col buffers are far past even the largest
/// mmap threshold glibc accepts, 32 MiB). Every block then comes from the heap, and the heap
/// is never trimmed.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only tunes the allocator; it is called before any worker thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}
