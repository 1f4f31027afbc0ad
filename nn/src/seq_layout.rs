//! The layout of a batch of text-prefixed motion sequences, which the prefix LM and its fused
//! kernels read.

/// How a batch of sequences is stored: every sequence has `prefix_slots` text slots (the
/// first `prefix_lens[b]` real, the rest padding that no position attends to) and
/// `motion_slots` motion slots (the first `motion_lens[b]` real, the rest padding after the
/// sequence's end). Only real slots have rows: all motion rows first (sequence-major), then
/// all text rows, so the motion rows the head reads are one contiguous block and no matmul
/// runs on padding (a batch padded to its longest clip is about half padding).
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
    /// Real motion slots of each sequence.
    pub motion_lens: Vec<usize>,
    /// First motion row of each sequence, then the total.
    motion_starts: Vec<usize>,
    /// First text row of each sequence, then the total (after every motion row).
    prefix_starts: Vec<usize>,
}

/// Running sums of `lens` from `start`: each one's first index, then the end.
fn starts(start: usize, lens: &[usize]) -> Vec<usize> {
    std::iter::once(start)
        .chain(lens.iter().scan(start, |at, &n| {
            *at += n;
            Some(*at)
        }))
        .collect()
}

impl SeqLayout {
    /// A layout whose sequences all have `motion_slots` real motion slots (generation runs
    /// them in lock step), text padded to the longest prefix of `prefix_lens`.
    pub fn new(prefix_lens: Vec<usize>, motion_slots: usize) -> Self {
        let motion_lens = vec![motion_slots; prefix_lens.len()];
        Self::packed(prefix_lens, motion_lens)
    }

    /// A layout of sequences with `prefix_lens` text and `motion_lens` motion slots.
    pub fn packed(prefix_lens: Vec<usize>, motion_lens: Vec<usize>) -> Self {
        assert_eq!(prefix_lens.len(), motion_lens.len());
        let motion_starts = starts(0, &motion_lens);
        let prefix_starts = starts(motion_starts[motion_lens.len()], &prefix_lens);
        Self {
            batch: prefix_lens.len(),
            prefix_slots: prefix_lens.iter().copied().max().unwrap_or(0),
            motion_slots: motion_lens.iter().copied().max().unwrap_or(0),
            prefix_lens,
            motion_lens,
            motion_starts,
            prefix_starts,
        }
    }

    /// Slots per sequence.
    pub fn slots(&self) -> usize {
        self.prefix_slots + self.motion_slots
    }

    /// Rows of the whole batch (real slots only).
    pub fn rows(&self) -> usize {
        self.prefix_starts[self.batch]
    }

    /// Motion rows of the whole batch.
    pub fn motion_rows(&self) -> usize {
        self.motion_starts[self.batch]
    }

    /// Row of slot `s` of sequence `b`, or `None` for a padding slot.
    pub fn row(&self, b: usize, s: usize) -> Option<usize> {
        if s < self.prefix_slots {
            (s < self.prefix_lens[b]).then(|| self.prefix_starts[b] + s)
        } else {
            let t = s - self.prefix_slots;
            (t < self.motion_lens[b]).then(|| self.motion_starts[b] + t)
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
        prefix_lm_allows(self.prefix_slots, self.prefix_lens[b], i, j)
    }
}

/// The prefix-LM mask: whether slot `i` attends to slot `j` in a sequence whose captions fill
/// `prefix_len` of the `prefix_slots` (caption keys by every slot, motion keys causally by
/// motion slots only).
pub fn prefix_lm_allows(prefix_slots: usize, prefix_len: usize, i: usize, j: usize) -> bool {
    if j < prefix_slots {
        j < prefix_len
    } else {
        i >= prefix_slots && j <= i
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packed_rows_skip_padding_motion_first_then_text() {
        // Sequence 0: 2 text + 3 motion slots; sequence 1: 3 text + 1 motion slot.
        let l = SeqLayout::packed(vec![2, 3], vec![3, 1]);
        assert_eq!(
            (l.prefix_slots, l.motion_slots, l.rows(), l.motion_rows()),
            (3, 3, 9, 4)
        );
        let rows: Vec<Vec<Option<usize>>> = (0..2)
            .map(|b| (0..l.slots()).map(|s| l.row(b, s)).collect())
            .collect();
        assert_eq!(rows[0], [Some(4), Some(5), None, Some(0), Some(1), Some(2)]);
        assert_eq!(rows[1], [Some(6), Some(7), Some(8), Some(3), None, None]);
        // Positions run over the real tokens only.
        assert_eq!((l.position(0, 3), l.position(1, 3)), (2, 3));
    }
}
