//! A set of a view's pixels kept as runs of consecutive indices (a body's rows are a run or two
//! each), drawn from by position: the k-th pixel in ascending order, as a sorted list of them
//! would give it, at 8 bytes a run instead of 4 a pixel.

/// Ascending pixel indices as runs: each run's first pixel and how many pixels come before it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PixelRuns {
    starts: Vec<u32>,
    before: Vec<u32>,
    len: usize,
}

impl PixelRuns {
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Whether `pixel` is one of the set.
    pub fn contains(&self, pixel: u32) -> bool {
        let run = self.starts.partition_point(|&s| s <= pixel);
        if run == 0 {
            return false;
        }
        let end = self.before.get(run).map_or(self.len as u32, |&b| b) - self.before[run - 1];
        pixel < self.starts[run - 1] + end
    }

    /// The `k`-th pixel in ascending order (`k < len`).
    pub fn get(&self, k: usize) -> u32 {
        let run = self.before.partition_point(|&b| b as usize <= k) - 1;
        self.starts[run] + (k as u32 - self.before[run])
    }
}

impl FromIterator<u32> for PixelRuns {
    /// From ascending pixel indices.
    fn from_iter<I: IntoIterator<Item = u32>>(pixels: I) -> Self {
        let mut runs = PixelRuns::default();
        let mut last: Option<u32> = None;
        for p in pixels {
            if last.is_none_or(|l| p != l + 1) {
                runs.starts.push(p);
                runs.before.push(runs.len as u32);
            }
            runs.len += 1;
            last = Some(p);
        }
        runs
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kth_pixel_is_the_sorted_lists() {
        let pixels: Vec<u32> = vec![3, 4, 5, 9, 12, 13, 40, 41, 42, 43, 100];
        let runs: PixelRuns = pixels.iter().copied().collect();
        assert_eq!(runs.len(), pixels.len());
        assert!((0..pixels.len()).all(|k| runs.get(k) == pixels[k]));
        assert_eq!(runs.starts.len(), 5);
        assert!(PixelRuns::default().is_empty());
        assert!((0..120).all(|p| runs.contains(p) == pixels.contains(&p)));
        assert!(!PixelRuns::default().contains(0));
    }
}
