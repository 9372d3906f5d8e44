//! A mask's neighbourhoods, counted in square windows by a summed-area table (the cost does not
//! grow with the reach): the pixels near its edge, where a segmenter's mask is least sure and a
//! batch samples most; and the pixels near its body, which a plate may not be estimated from.
//! Also the plate itself: what a static camera sees behind the body, from its frames.

use crate::imageio::{Mask, RgbImage};

/// How far (pixels, square windows) from a training mask's edge a scene with plates keeps what
/// the camera saw, and a fit lets the colour over the plate decide the silhouette: a
/// segmenter's mask errs by a pixel or two, and its stray blobs are a few pixels across.
pub const EDGE_BAND: usize = 3;

/// Per pixel of a `width` x `height` image: how many body pixels lie within `reach` (a square
/// window, clipped to the image), and how many pixels that window holds.
struct Windows {
    width: usize,
    height: usize,
    /// `table[y * (width + 1) + x]`: body pixels above and left of `(x, y)`.
    table: Vec<u32>,
}

impl Windows {
    fn of(mask: &Mask) -> Self {
        let (w, h) = (mask.width, mask.height);
        let mut table = vec![0u32; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut row = 0u32;
            for x in 0..w {
                row += mask.foreground[y * w + x] as u32;
                table[(y + 1) * (w + 1) + x + 1] = table[y * (w + 1) + x + 1] + row;
            }
        }
        Windows { width: w, height: h, table }
    }

    /// (body pixels, pixels) in the window of `reach` around pixel `p`.
    fn count(&self, p: usize, reach: usize) -> (usize, usize) {
        let (w, h) = (self.width, self.height);
        let (x, y) = (p % w, p / w);
        let (x0, y0, x1, y1) = (x.saturating_sub(reach), y.saturating_sub(reach), (x + reach + 1).min(w), (y + reach + 1).min(h));
        let at = |x: usize, y: usize| self.table[y * (w + 1) + x] as usize;
        (at(x1, y1) + at(x0, y0) - at(x1, y0) - at(x0, y1), (x1 - x0) * (y1 - y0))
    }
}

/// The pixels within `band` pixels (square window) of a pixel of the other kind, ascending: a
/// body pixel whose window holds background, a background pixel whose window holds body.
pub fn edge_pixels(mask: &Mask, band: usize) -> Vec<u32> {
    let windows = Windows::of(mask);
    (0..mask.width * mask.height)
        .filter(|&p| {
            let (body, all) = windows.count(p, band);
            match mask.foreground[p] {
                true => body < all,
                false => body > 0,
            }
        })
        .map(|p| p as u32)
        .collect()
}

/// Per pixel, whether body lies within `reach` pixels of it (itself included).
pub fn near_body(mask: &Mask, reach: usize) -> Vec<bool> {
    let windows = Windows::of(mask);
    (0..mask.width * mask.height).map(|p| windows.count(p, reach).0 > 0).collect()
}

/// What a static camera sees behind the body: per pixel, its colour (linear RGB) where `known`.
#[derive(Clone, Debug, PartialEq)]
pub struct Plate {
    pub colour: RgbImage,
    pub known: Mask,
}

/// How many of a camera's frames must show a pixel as surely background for its plate to be
/// known there: a median of three outvotes one frame's passer-by or moving shadow.
pub const PLATE_SAMPLES: usize = 3;

/// How far (pixels) from a frame's mask a pixel must lie for the frame to tell the plate there:
/// a mask is a pixel off in places; where it is off by more, the median over the frames
/// outvotes the few that show the body.
pub const PLATE_CLEARANCE: usize = 1;

/// A camera's plate from its frames (sRGB bytes and masks, all one size): per pixel and channel,
/// the median over the frames in which no body lies within `PLATE_CLEARANCE`; known where at
/// least `PLATE_SAMPLES` frames are. None when no pixel is.
pub fn plate_of(frames: &[(Vec<[u8; 3]>, Mask)]) -> Option<Plate> {
    let (first, mask) = frames.first()?;
    let (w, h) = (mask.width, mask.height);
    let clear: Vec<Vec<bool>> = frames.iter().map(|(_, m)| near_body(m, PLATE_CLEARANCE).into_iter().map(|near| !near).collect()).collect();
    let mut colour = RgbImage::new(w, h);
    let mut known = Vec::with_capacity(first.len());
    let mut samples: Vec<u8> = Vec::with_capacity(frames.len());
    for p in 0..w * h {
        let count = clear.iter().filter(|c| c[p]).count();
        known.push(count >= PLATE_SAMPLES);
        if count < PLATE_SAMPLES {
            continue;
        }
        let mut linear = [0.0f32; 3];
        for (c, value) in linear.iter_mut().enumerate() {
            samples.clear();
            samples.extend(frames.iter().zip(&clear).filter(|(_, clear)| clear[p]).map(|((bytes, _), _)| bytes[p][c]));
            samples.sort_unstable();
            *value = crate::imageio::srgb_to_linear(samples[samples.len() / 2] as f32 / 255.0);
        }
        colour.pixels[p] = linear;
    }
    if !known.iter().any(|&k| k) {
        return None;
    }
    Some(Plate { colour, known: Mask { width: w, height: h, foreground: known.into() } })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random_mask(w: usize, h: usize, seed: u64) -> Mask {
        let mut stream = crate::random::Stream::new(seed, 0, 0);
        let foreground: Vec<bool> = (0..w * h).map(|_| stream.uniform() < 0.3).collect();
        Mask { width: w, height: h, foreground: foreground.into() }
    }

    /// Both neighbourhoods against their definitions, pixel by pixel, on random masks.
    #[test]
    fn windows_match_the_definition() {
        for (w, h, band) in [(7, 5, 0), (7, 5, 1), (9, 6, 2), (4, 11, 3), (1, 1, 2)] {
            let mask = random_mask(w, h, (w * 100 + h * 10 + band) as u64);
            let neighbours = |p: usize| {
                let (x, y) = ((p % w) as i64, (p / w) as i64);
                let b = band as i64;
                let mask = &mask;
                (-b..=b)
                    .flat_map(move |dy| (-b..=b).map(move |dx| (x + dx, y + dy)))
                    .filter(move |&(u, v)| u >= 0 && v >= 0 && (u as usize) < w && (v as usize) < h)
                    .map(move |(u, v)| mask.foreground[v as usize * w + u as usize])
            };
            let edge: Vec<u32> = (0..w * h).filter(|&p| neighbours(p).any(|f| f != mask.foreground[p])).map(|p| p as u32).collect();
            assert_eq!(edge_pixels(&mask, band), edge, "{w}x{h}, band {band}");
            let near: Vec<bool> = (0..w * h).map(|p| neighbours(p).any(|f| f)).collect();
            assert_eq!(near_body(&mask, band), near, "{w}x{h}, reach {band}");
        }
    }

    /// A body walking across a striped wall: the plate is the wall wherever enough frames show
    /// it clear, the median ignores one frame's odd colour, and pixels always near the body stay
    /// unknown.
    #[test]
    fn a_plate_is_the_median_of_the_frames_that_see_past_the_body() {
        let (w, h) = (40, 8);
        let wall = |x: usize| if x % 4 < 2 { 200u8 } else { 40 };
        let masks: Vec<Mask> = (0..5)
            .map(|f| Mask { width: w, height: h, foreground: (0..w * h).map(|p| (p % w) / 4 == 2 * f || (p % w) >= 38).collect::<Vec<_>>().into() })
            .collect();
        let frames: Vec<(Vec<[u8; 3]>, Mask)> = masks
            .iter()
            .enumerate()
            .map(|(f, m)| {
                let bytes = (0..w * h)
                    .map(|p| {
                        if m.foreground[p] {
                            [0, 255, 0]
                        } else if f == 4 && p % w == 20 {
                            [255, 0, 0]
                        } else {
                            [wall(p % w); 3]
                        }
                    })
                    .collect();
                (bytes, m.clone())
            })
            .collect();
        let plate = plate_of(&frames).expect("a plate");
        for x in 0..w {
            let p = 3 * w + x;
            let clear = masks.iter().filter(|m| !near_body(m, PLATE_CLEARANCE)[p]).count();
            assert_eq!(plate.known.foreground[p], clear >= PLATE_SAMPLES, "x = {x}");
            if plate.known.foreground[p] {
                let expected = crate::imageio::srgb_to_linear(wall(x) as f32 / 255.0);
                assert_eq!(plate.colour.pixels[p], [expected; 3], "x = {x}");
            }
        }
        // The column the body always stands beside is never known; x = 20 is, past one red frame.
        assert!(!plate.known.foreground[3 * w + 37]);
        assert!(plate.known.foreground[3 * w + 20]);
        assert_eq!(plate_of(&frames[..2]), None);
    }
}
