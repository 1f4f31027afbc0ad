//! Process settings: allocator tuning for the training loops, and what a closed pipe does.

/// Keep freed memory for reuse. glibc hands blocks of 128 KiB and more back to the OS
/// (munmap, heap trimming), so a training loop, which frees and reallocates the same
/// activations every step, pays a page fault per 4 KiB of them (~110 K faults per d512 LM
/// step; a batch-256 tokenizer step's 100 MB im2col buffers are far past even the largest
/// mmap threshold glibc accepts, 32 MiB). Every block then comes from the heap, and the heap
/// is never trimmed. And a pad of 64 MiB above each heap's top: a worker thread's arena lives
/// in mmapped heaps of 64 MiB (glibc's largest) that glibc unmaps whenever one falls empty,
/// whatever the trim threshold, unless the pad asks to keep that much. Without it a d512 LM
/// step still faulted 5,000–470,000 times over eight timed steps, erratic from run to run
/// (and up to a third slower); with it 3,300–9,600, d256 and the tokenizer unchanged
/// (`docs/results/bench.md`, #40). One arena for all threads would also stop the faults, but
/// cost the d256 step 3–6% in lock waits.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only tunes the allocator; it is called before any worker thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}

/// Let writing to a closed pipe end the process quietly, as it does for other command-line
/// tools (`motionscale corpus stats … | head -1`). Rust ignores SIGPIPE, so a write to a
/// closed pipe fails and `println!` panics on it instead.
pub fn end_quietly_on_closed_pipe() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: restores the default disposition of one signal before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
