//! The layout of a batch of text-prefixed motion sequences, which the prefix LM and its fused
//! kernels read.

/// How a batch of sequences is stored: every sequence has `prefix_slots` text slots (the
/// first `prefix_lens[b]` real, the rest padding that no position attends to) and
/// `motion_slots` motion slots. Rows hold all motion slots first (sample-major), then all
/// prefix slots, so the motion rows the head reads are one contiguous block.
///
/// Slot `s` of a sequence is a text slot for `s < prefix_slots`, else motion slot
/// `s − prefix_slots`. Positions are contiguous over the real tokens: text slot j sits at j,
/// motion slot t at `prefix_lens[b] + t`, so padding never shifts a rotary position.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SeqLayout {
    /// Sequences.
    pub batch: usize,
    /// Text slots per sequence.
    pub prefix_slots: usize,
    /// Motion slots per sequence.
    pub motion_slots: usize,
    /// Real text tokens of each sequence.
    pub prefix_lens: Vec<usize>,
}

impl SeqLayout {
    /// A layout padded to the longest prefix of `prefix_lens`.
    pub fn new(prefix_lens: Vec<usize>, motion_slots: usize) -> Self {
        Self {
            batch: prefix_lens.len(),
            prefix_slots: prefix_lens.iter().copied().max().unwrap_or(0),
            motion_slots,
            prefix_lens,
        }
    }

    /// Slots per sequence.
    pub fn slots(&self) -> usize {
        self.prefix_slots + self.motion_slots
    }

    /// Rows of the whole batch.
    pub fn rows(&self) -> usize {
        self.batch * self.slots()
    }

    /// Row of slot `s` of sequence `b`.
    pub fn row(&self, b: usize, s: usize) -> usize {
        if s < self.prefix_slots {
            self.batch * self.motion_slots + b * self.prefix_slots + s
        } else {
            b * self.motion_slots + s - self.prefix_slots
        }
    }

    /// Rotary position of slot `s` of sequence `b`.
    pub fn position(&self, b: usize, s: usize) -> usize {
        if s < self.prefix_slots {
            s
        } else {
            self.prefix_lens[b] + s - self.prefix_slots
        }
    }

    /// Highest position in the batch.
    pub fn max_position(&self) -> usize {
        (0..self.batch)
            .map(|b| self.position(b, self.slots().saturating_sub(1)))
            .max()
            .unwrap_or(0)
    }

    /// Whether slot `i` of sequence `b` attends to slot `j`: real text slots are seen by
    /// every slot; motion slots only by motion slots at or after them.
    pub fn allowed(&self, b: usize, i: usize, j: usize) -> bool {
        if j < self.prefix_slots {
            j < self.prefix_lens[b]
        } else {
            i >= self.prefix_slots && j <= i
        }
    }
}
