//! The seeded random stream every stage draws from (training batches, Gaussians' starts,
//! samples of renders and relighting, the synthetic generator): SplitMix64, cheap to split per
//! pixel or per iteration so results never depend on the thread schedule.

/// A small deterministic random stream (SplitMix64), seeded per pixel so that renders are
/// byte-identical whatever the thread schedule.
pub struct Stream(u64);

impl Stream {
    pub fn new(seed: u64, a: u64, b: u64) -> Self {
        let mut s = Stream(seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
        s.next_u64();
        s
    }

    /// The whole state, to checkpoint and resume a stream exactly.
    pub fn state(&self) -> u64 {
        self.0
    }

    pub fn from_state(state: u64) -> Self {
        Stream(state)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// An index in `0..n` (`n` > 0), from one uniform draw.
    pub fn below(&mut self, n: usize) -> usize {
        (self.uniform() * n as f64) as usize % n.max(1)
    }
}
