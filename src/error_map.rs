//! Where the fit is still wrong, per training view: a coarse map of each view's recent per-pixel
//! errors, from which a share of every batch's rays is drawn (instant-NGP's error map, on tiles).
//!
//! A multi-view capture's pixels are visited a few times each over a whole fit, too few to know
//! one pixel's error, so the map keeps one running error per tile of pixels (about 16 x 16 tiles
//! a view, whatever its resolution, so each tile is visited about as often). A tile starts at
//! `UNSEEN` (above any error a pixel can have), so every tile is looked at once before the map
//! is trusted; each visit then moves its tile's error a step `RATE` toward the pixel's. A tile
//! is drawn in proportion to its error plus a floor of `FLOOR` times the view's mean, so a tile
//! the fit explains is still drawn now and then and a regression there is seen.

/// Tiles along a view's longer side.
const TILES_PER_SIDE: usize = 16;

/// A tile's error before its first visit: larger than any pixel's (a pixel's error is at most
/// 1 for its coverage and 1 for its colour), so unseen tiles are drawn first.
pub const UNSEEN: f32 = 2.0;

/// How far one visit moves its tile's error toward the pixel's (an exponential average over
/// about the last ten visits: a tile is visited tens of times over a fit).
const RATE: f32 = 0.1;

/// The least weight of a tile, as a fraction of the view's mean tile error.
const FLOOR: f32 = 0.1;

/// One view's tiles and their running errors.
#[derive(Clone, Debug)]
pub struct ErrorMap {
    width: usize,
    height: usize,
    tile: usize,
    columns: usize,
    errors: Vec<f32>,
}

impl ErrorMap {
    pub fn new(width: usize, height: usize) -> Self {
        let tile = width.max(height).div_ceil(TILES_PER_SIDE).max(1);
        let columns = width.div_ceil(tile).max(1);
        let rows = height.div_ceil(tile).max(1);
        Self { width, height, tile, columns, errors: vec![UNSEEN; columns * rows] }
    }

    fn tile_of(&self, pixel: usize) -> usize {
        let (x, y) = (pixel % self.width, pixel / self.width);
        (y / self.tile) * self.columns + x / self.tile
    }

    /// Every tile's running error, row after row (what a checkpoint keeps).
    pub fn errors(&self) -> &[f32] {
        &self.errors
    }

    /// Tiles' errors from a checkpoint, refused unless there is one per tile and each is a
    /// finite non-negative number or `UNSEEN`.
    pub fn set_errors(&mut self, errors: Vec<f32>) -> Result<(), String> {
        if errors.len() != self.errors.len() {
            return Err(format!("{} tile errors for a map of {} tiles", errors.len(), self.errors.len()));
        }
        if let Some(bad) = errors.iter().find(|e| !(e.is_finite() && **e >= 0.0)) {
            return Err(format!("a tile error of {bad}: errors are finite and non-negative"));
        }
        self.errors = errors;
        Ok(())
    }

    /// The running error of the tile holding `pixel`.
    pub fn error_at(&self, pixel: usize) -> f32 {
        self.errors.get(self.tile_of(pixel)).copied().unwrap_or(UNSEEN)
    }

    /// A pixel's error seen by a training step: its tile's error moves toward it. Non-finite
    /// errors and pixels outside the view are ignored.
    pub fn record(&mut self, pixel: usize, error: f32) {
        if pixel >= self.width * self.height || !error.is_finite() {
            return;
        }
        let t = self.tile_of(pixel);
        let e = &mut self.errors[t];
        *e = if *e >= UNSEEN { error } else { *e + RATE * (error - *e) };
    }

    /// A pixel drawn from `u` (a tile in proportion to its error plus the floor) and `v` (a
    /// pixel uniformly within the tile), both uniform in [0, 1).
    pub fn draw(&self, u: f64, v: f64) -> usize {
        let mean = self.errors.iter().map(|&e| e as f64).sum::<f64>() / self.errors.len() as f64;
        let floor = FLOOR as f64 * mean + 1e-9;
        let total: f64 = self.errors.iter().map(|&e| e.max(0.0) as f64 + floor).sum();
        let mut left = u * total;
        let mut tile = self.errors.len() - 1;
        for (t, &e) in self.errors.iter().enumerate() {
            left -= e.max(0.0) as f64 + floor;
            if left < 0.0 {
                tile = t;
                break;
            }
        }
        let (tx, ty) = ((tile % self.columns) * self.tile, (tile / self.columns) * self.tile);
        // The tiles on the right and bottom edges may be cut short by the view's border.
        let w = self.tile.min(self.width - tx);
        let h = self.tile.min(self.height - ty);
        let k = ((v * (w * h) as f64) as usize).min(w * h - 1);
        (ty + k / w) * self.width + tx + k % w
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_view_and_unseen_tiles_come_first() {
        // 70 x 40: tiles of 5 pixels, 14 x 8 of them, every pixel in exactly one.
        let map = ErrorMap::new(70, 40);
        assert_eq!((map.tile, map.columns, map.errors.len()), (5, 14, 14 * 8));
        let mut seen = vec![0usize; 70 * 40];
        let n = 200_000;
        for k in 0..n {
            let u = (k as f64 + 0.5) / n as f64;
            let v = ((k * 7919) % n) as f64 / n as f64;
            seen[map.draw(u, v)] += 1;
        }
        // Every tile the same weight: every pixel drawn, about equally often.
        let (lo, hi) = (*seen.iter().min().unwrap(), *seen.iter().max().unwrap());
        assert!(lo > 0 && (hi as f64) < 1.6 * (n as f64 / 2800.0), "{lo} {hi}");
    }

    #[test]
    fn tiles_are_drawn_in_proportion_to_their_error_plus_a_floor() {
        let mut map = ErrorMap::new(32, 32); // tiles of 2 x 2, 256 of them
        let in_tile = |p: usize| (4..6).contains(&(p % 32)) && (6..8).contains(&(p / 32));
        // Every tile explained but one (pixels (4..6, 6..8)), first seen wrong.
        for p in (0..32 * 32).filter(|&p| !in_tile(p)) {
            map.record(p, 0.0);
        }
        map.record(6 * 32 + 4, 1.0);
        assert_eq!(map.error_at(7 * 32 + 5), 1.0);
        // A second visit moves it a tenth of the way.
        map.record(7 * 32 + 5, 0.0);
        let e = map.error_at(6 * 32 + 4);
        assert!((e - 0.9).abs() < 1e-6, "{e}");
        let n = 100_000;
        let inside = (0..n).map(|k| map.draw((k as f64 + 0.5) / n as f64, ((k * 31) % 97) as f64 / 97.0)).filter(|&p| in_tile(p)).count();
        // Weight 0.9 + floor against 255 tiles of the floor alone: the floor is 0.1 x mean.
        let floor = 0.1 * 0.9 / 256.0;
        let expected = (0.9 + floor) / (0.9 + 256.0 * floor);
        let share = inside as f64 / n as f64;
        assert!((share - expected).abs() < 0.01, "{share} against {expected}");
        // Errors that are not finite, and pixels outside the view, leave the map alone.
        map.record(6 * 32 + 4, f32::NAN);
        map.record(32 * 32, 5.0);
        assert_eq!(map.error_at(6 * 32 + 4), e);
        // A checkpoint's copy restores the same map; a wrong one is refused.
        let mut copy = ErrorMap::new(32, 32);
        copy.set_errors(map.errors().to_vec()).unwrap();
        assert_eq!(copy.draw(0.37, 0.5), map.draw(0.37, 0.5));
        assert!(copy.set_errors(vec![0.0; 10]).is_err());
        assert!(copy.set_errors(vec![f32::NAN; 256]).is_err());
    }
}
