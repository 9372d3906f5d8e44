//! The pixel footprint of a capture: whether a pixel holds the image at its centre (a renderer
//! that shoots one ray per pixel, like `umbra synth` by default) or its average over the pixel's
//! area (a camera's sensor, a path tracer: anti-aliased). scene/1 does not say, so it is read
//! off the training images: under an area footprint the foreground pixels along the silhouette
//! are only partly covered by the body, and so darker than their neighbours inside it.

use super::{Scene, Split};

/// How a pixel's value relates to the image plane.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Footprint {
    /// The image at the pixel's centre.
    Centre,
    /// The image averaged over the pixel's square.
    Area,
}

/// What the training images say of their footprint.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct FootprintEstimate {
    pub footprint: Footprint,
    /// Luminance of the foreground pixels that touch the background (4-neighbours), over the
    /// mean luminance of their foreground neighbours that do not: about 1 when pixels are
    /// sampled at their centres, about 0.87-0.89 when a box filter averages them (measured on
    /// the anti-aliased `human-sun-128` walker and on the independent renderer's quadruped of
    /// `../shared/examples`; 0.98-1.01 on five centre-sampled captures). `None` without
    /// such pixels (no training masks, or a body that never meets the background).
    pub edge_ratio: Option<f64>,
    /// How many silhouette pixels the ratio was taken over.
    pub edge_pixels: usize,
}

/// Below this ratio the silhouette is taken to be anti-aliased: halfway between a box
/// filter's 0.88 and a centre sample's 1.
pub const AREA_BELOW: f64 = 0.94;

/// Reads the footprint off the scene's training images and masks.
pub fn estimate(scene: &Scene) -> FootprintEstimate {
    let luminance = |c: [f32; 3]| (c[0] + c[1] + c[2]) as f64;
    let (mut edge_sum, mut inner_sum, mut edge_pixels) = (0.0, 0.0, 0usize);
    for view in scene.views_in(Split::Train) {
        let Some(mask) = &view.mask else { continue };
        let (w, h) = (mask.width, mask.height);
        if view.colour.width() * view.colour.height() != w * h {
            continue;
        }
        let fg = |x: isize, y: isize| x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && mask.foreground[y as usize * w + x as usize];
        let is_edge = |x: isize, y: isize| fg(x, y) && [(-1, 0), (1, 0), (0, -1), (0, 1)].iter().any(|(dx, dy)| !fg(x + dx, y + dy));
        for y in 0..h as isize {
            for x in 0..w as isize {
                if !is_edge(x, y) {
                    continue;
                }
                let (mut sum, mut count) = (0.0, 0usize);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if fg(x + dx, y + dy) && !is_edge(x + dx, y + dy) {
                            sum += luminance(view.colour.pixel((y + dy) as usize * w + (x + dx) as usize));
                            count += 1;
                        }
                    }
                }
                if count > 0 {
                    edge_sum += luminance(view.colour.pixel(y as usize * w + x as usize));
                    inner_sum += sum / count as f64;
                    edge_pixels += 1;
                }
            }
        }
    }
    let edge_ratio = (inner_sum > 0.0).then(|| edge_sum / inner_sum);
    let footprint = match edge_ratio {
        Some(r) if r < AREA_BELOW => Footprint::Area,
        _ => Footprint::Centre,
    };
    FootprintEstimate { footprint, edge_ratio, edge_pixels }
}

/// Where a pixel's `rays` (a square number) sample it, in pixel units from its corner: the
/// centre of each of the `n x n` strata, moved within its stratum by `jitter` (pairs in
/// [0, 1); none: the strata's centres). One ray is the pixel's centre.
pub fn subpixel_offsets(rays: usize, jitter: Option<&[f64]>) -> Vec<[f64; 2]> {
    let n = (rays as f64).sqrt().round().max(1.0) as usize;
    (0..n * n)
        .map(|s| {
            let (u, v) = jitter.map(|j| (j[2 * s], j[2 * s + 1])).unwrap_or((0.5, 0.5));
            [((s % n) as f64 + u) / n as f64, ((s / n) as f64 + v) / n as f64]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_cover_the_pixel_in_strata() {
        assert_eq!(subpixel_offsets(1, None), vec![[0.5, 0.5]]);
        let four = subpixel_offsets(4, None);
        assert_eq!(four, vec![[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]);
        let jitter = [0.0, 0.99, 0.5, 0.5, 0.99, 0.0, 0.1, 0.2];
        for (s, o) in subpixel_offsets(4, Some(&jitter)).iter().enumerate() {
            let (sx, sy) = ((s % 2) as f64 * 0.5, (s / 2) as f64 * 0.5);
            assert!(o[0] >= sx && o[0] < sx + 0.5 && o[1] >= sy && o[1] < sy + 0.5, "{s}: {o:?}");
        }
    }
}
