//! Where a view's pixels are rendered over their area and how: which pixels need it
//! (`needs_area`), the windows along their rays that hold the surface (`surface_window`,
//! `silhouette_window`), and their 3 x 3 strata interpolated from the centres around them or
//! averaged (`strata_from_centres`, `strata_mean`).

use super::{Traced, LIGHTS_PER_TRACE, TRACE_CHUNK, VIEW_PIXEL_RAYS};
use crate::avatar::Avatar;
use crate::skeleton::PoseTensors;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use rayon::prelude::*;

/// The distances along the rays within pixel `p` that hold the surface, from the centre rays
/// of its 3 x 3 neighbourhood (`pixels`, `w x h`, focal length `fx` in pixels): when every
/// one of them is wholly covered and their depths differ by at most `WINDOW_SLOPE` pixels'
/// width at that depth (no silhouette, no step in depth, no grazing surface), the surface
/// under any point of the pixel lies between their depths (a smooth surface between the
/// centres it passes through), and the window is that span widened on each side by itself or
/// one pixel's width, whichever is more. `None` otherwise: the rays search their whole bound.
pub(super) fn surface_window(pixels: &[Traced], w: usize, h: usize, p: usize, fx: f64) -> Option<(f64, f64)> {
    let depths = neighbourhood(w, h, p).map(|q| {
        let q = &pixels[q];
        (q.coverage >= 1.0 - 1.0 / 255.0 && q.depth.is_finite()).then_some(q.depth as f64)
    });
    window_of(depths.collect::<Option<Vec<f64>>>()?, fx, WINDOW_SLOPE)
}

/// A window for a pixel along a silhouette (`surface_window` refuses it): where the centres
/// around it that meet the body at all (coverage above an 8-bit step) meet it within
/// `SILHOUETTE_SLOPE` pixels' widths of each other, the surface any ray through the pixel can meet
/// lies between their depths, as inside the body; the centres that miss it say only that a ray
/// there may miss it too. `None` where none meets it or where they lie on surfaces at
/// different depths (a limb before the body): those rays search their whole bound.
pub(super) fn silhouette_window(pixels: &[Traced], w: usize, h: usize, p: usize, fx: f64) -> Option<(f64, f64)> {
    let depths: Vec<f64> =
        neighbourhood(w, h, p).map(|q| &pixels[q]).filter(|q| q.coverage > 1.0 / 255.0 && q.depth.is_finite()).map(|q| q.depth as f64).collect();
    window_of(depths, fx, SILHOUETTE_SLOPE)
}

/// The pixels of `p`'s 3 x 3 neighbourhood inside the image, `p` among them.
pub(super) fn neighbourhood(w: usize, h: usize, p: usize) -> impl Iterator<Item = usize> {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    (-1..=1)
        .flat_map(move |dy| (-1..=1).map(move |dx| (x + dx, y + dy)))
        .filter(move |&(i, j)| i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h)
        .map(move |(i, j)| j as usize * w + i as usize)
}

/// The window of a neighbourhood's surface depths (`surface_window`): their span widened on each
/// side by itself or one pixel's width (focal length `fx` in pixels), whichever is more, when it
/// is at most `slope` pixels' widths; `None` otherwise or without depths.
pub(super) fn window_of(depths: Vec<f64>, fx: f64, slope: f64) -> Option<(f64, f64)> {
    let lo = depths.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = depths.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if depths.is_empty() {
        return None;
    }
    let pixel = hi / fx.max(1e-9);
    (hi - lo <= slope * pixel).then(|| {
        let margin = (hi - lo).max(pixel);
        (lo - margin, hi + margin)
    })
}

/// The most a window's neighbourhood's depths may differ, in pixels' widths at that depth
/// (`surface_window`): a surface tilted up to about 70 degrees from facing the camera.
pub(super) const WINDOW_SLOPE: f64 = 3.0;

/// How far the depths of the four centres around a stratum may differ, in pixels' widths, for
/// the stratum to be read off them where its pixel's whole neighbourhood does not allow it
/// (`quadrant_interpolates`, along silhouettes and depth steps): a surface turned at most 14
/// degrees from the camera. Nearer grazing, a traced ray's colour is a composite over a longer
/// stretch of the surface than one lookup sees, and the fitted albedo has learnt the
/// composite: at 1 (45 degrees) `human-sun-128-aa`'s novel views lost 0.06 dB over the
/// foreground and `quadruped-tiny`'s novel poses 0.03 dB; at 0.25 neither lost 0.01 dB, and
/// the 148 images below took as long (49 s against 51).
pub(super) const QUADRANT_SLOPE: f64 = 0.25;

/// `WINDOW_SLOPE` for a silhouette's window (`silhouette_window`): there the centres that meet
/// the body partly have their depth on its far, grazed side, so the depths around a pixel spread
/// more than on a surface facing the camera (on the 148 images below, most silhouette pixels
/// refused at 3 spread 3 to 16 pixels' widths). A window of 8 pixels' widths, widened by as
/// much on each side, holds 24 at most, about 30 cm on a 2 m human at 128 x 128, which the
/// window's 8 coarse samples then space no wider than a whole ray's 24 do over its bound.
/// Measured on the 148 novel-pose images of an area capture: the same scores (27.43 / 22.89
/// dB foreground image / albedo; each image within 0.3 dB), 61 s against 72 s with 3.
pub(super) const SILHOUETTE_SLOPE: f64 = 8.0;

/// The 3 x 3 strata of a refined pixel (row-major, as `subpixel_offsets` lays them out): the
/// four corners and the middles of the four sides; the centre, 4, is the pixel's centre ray,
/// traced already.
pub(super) const CORNER_STRATA: [usize; 4] = [0, 2, 6, 8];
pub(super) const SIDE_STRATA: [usize; 4] = [1, 3, 5, 7];
const _: () = assert!(VIEW_PIXEL_RAYS == 9);
/// The two corners (places in `CORNER_STRATA`) each side stratum lies midway between.
pub(super) const SIDE_CORNERS: [(usize, usize); 4] = [(0, 1), (0, 2), (1, 3), (2, 3)];

/// The stratum midway between strata `a` and `b`, as their mean.
pub(super) fn midway(a: &Traced, b: &Traced) -> Traced {
    let mean = |x: [f32; 3], y: [f32; 3]| [0, 1, 2].map(|c| 0.5 * (x[c] + y[c]));
    Traced {
        colours: std::array::from_fn(|light| mean(a.colours[light], b.colours[light])),
        albedo: mean(a.albedo, b.albedo),
        raw: mean(a.raw, b.raw),
        coverage: 0.5 * (a.coverage + b.coverage),
        depth: 0.5 * (a.depth + b.depth),
    }
}

/// How far (sRGB, every channel) a refined pixel's centre ray may lie from its four corner
/// rays' mean for its sides to be taken as their corners' means (`strata_agree`).
pub(super) const STRATA_AGREE: f32 = 1.0 / 255.0;

/// Whether a refined pixel's sides may be taken from its corners: its centre ray and four
/// corner rays agree on coverage within an 8-bit step, and its colour in every light (and its
/// albedo, when it is rendered) is bilinear over the pixel to within `STRATA_AGREE`: the centre lies that close
/// to the corners' mean. A ramp (a shading gradient, a blurred border) passes; a straight
/// sharp edge (a silhouette, a checker's border, a shadow's) that crosses any of the 3 x 3
/// strata does not: it splits the corners from each other (one from three leaves the centre
/// a quarter of the contrast from their mean, two from two half of it) or from the centre.
pub(super) fn strata_agree(centre: &Traced, corners: &[Traced], albedo: bool) -> bool {
    let (lo, hi) = std::iter::once(centre).chain(corners).fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), t| (lo.min(t.coverage), hi.max(t.coverage)));
    let srgb = |v: f32| crate::imageio::linear_to_srgb(v.max(0.0));
    let bilinear = |of: &dyn Fn(&Traced) -> [f32; 3]| {
        (0..3).all(|c| (srgb(of(centre)[c]) - corners.iter().map(|t| srgb(of(t)[c])).sum::<f32>() / corners.len() as f32).abs() <= STRATA_AGREE)
    };
    hi - lo <= 1.0 / 255.0 && (0..LIGHTS_PER_TRACE).all(|light| bilinear(&|t| t.colours[light])) && (!albedo || bilinear(&|t| t.albedo))
}

/// A refined pixel as the mean of its 3 x 3 strata: the centre, the corners and the sides'
/// middles, or where the sides were not found (`strata_agree`) each side as its two corners'
/// mean (`midway`), so every corner counts twice. The depth stays the centre's.
pub(super) fn strata_mean(centre: &Traced, corners: &[Traced], sides: Option<&[Traced]>) -> Traced {
    let midways: Vec<Traced>;
    let sides = match sides {
        Some(sides) => sides,
        None => {
            midways = SIDE_CORNERS.iter().map(|&(a, b)| midway(&corners[a], &corners[b])).collect();
            &midways
        }
    };
    let ninth = 1.0 / 9.0;
    let strata = || std::iter::once(centre).chain(corners).chain(sides);
    let mean =
        |of: &dyn Fn(&Traced) -> [f32; 3]| strata().fold([0.0f32; 3], |a, t| [a[0] + of(t)[0] * ninth, a[1] + of(t)[1] * ninth, a[2] + of(t)[2] * ninth]);
    Traced {
        colours: std::array::from_fn(|light| mean(&|t| t.colours[light])),
        albedo: mean(&|t| t.albedo),
        raw: mean(&|t| t.raw),
        coverage: strata().map(|t| t.coverage * ninth).sum(),
        depth: centre.depth,
    }
}

/// Whether pixel `p` of a centre-sampled render (sRGB `encoded`, `coverage`, `w x h`) must be
/// rendered over its area to stand for its mean there: where its 3 x 3 neighbourhood's
/// coverage differs by more than an 8-bit step (a silhouette), or where its colour is curved:
/// over a box the mean of a smooth image is its centre plus a ninth of how far the centre lies
/// from its 8 neighbours' mean (both `(f_xx + f_yy) / 24` and `3 (f_xx + f_yy) / 8` on a
/// quadratic; taken over opposite pairs of neighbours, so that a linear image gives 0 at the
/// image's border too), so a pixel whose centre is within `REFINE_CURVATURE` of that mean is within
/// half an 8-bit step of its area's mean already. A linear shading ramp is never refined; an
/// edge through the pixel (a checker, a stripe, a shadow's border) is.
pub(super) fn needs_area(encoded: &[[f32; 3]], coverage: &[f32], w: usize, h: usize, p: usize) -> bool {
    let step = 1.0 / 255.0;
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    let neighbours: Vec<usize> = (-1..=1)
        .flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy)))
        .filter(|&(i, j)| (i, j) != (x, y) && i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h)
        .map(|(i, j)| j as usize * w + i as usize)
        .collect();
    if neighbours.iter().any(|&q| (coverage[p] - coverage[q]).abs() > step) {
        return true;
    }
    // The neighbours in opposite pairs (both inside the image, so a linear image gives zero at
    // its border too): how far the centre lies from the pairs' mean.
    let at = |dx: isize, dy: isize| {
        let (i, j) = (x + dx, y + dy);
        (i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h).then(|| j as usize * w + i as usize)
    };
    let pairs: Vec<(usize, usize)> = [(1, 0), (0, 1), (1, 1), (1, -1)].into_iter().filter_map(|(dx, dy)| Some((at(dx, dy)?, at(-dx, -dy)?))).collect();
    if pairs.is_empty() {
        return false;
    }
    let n = pairs.len() as f32;
    (0..3).any(|c| (pairs.iter().map(|&(a, b)| (encoded[a][c] + encoded[b][c]) / 2.0).sum::<f32>() / n - encoded[p][c]).abs() > REFINE_CURVATURE)
}

/// How far (sRGB) a pixel's centre may lie from its 8 neighbours' mean before it is rendered
/// over its area (`needs_area`): nine times half an 8-bit step.
pub(super) const REFINE_CURVATURE: f32 = 4.5 / 255.0;
/// The least fitted albedo (linear, every channel) a centre may have for its shading term, its
/// colour over its albedo, to be read off it (`quadrant_interpolates`).
pub(super) const SHADING_ALBEDO_FLOOR: f32 = 1e-3;

/// Whether every centre of pixel `p`'s 3 x 3 neighbourhood lies in the image and has an albedo
/// above `SHADING_ALBEDO_FLOOR` in every channel.
pub(super) fn albedo_above_floor(pixels: &[Traced], w: usize, h: usize, p: usize) -> bool {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy))).all(|(i, j)| {
        i >= 0 && j >= 0 && (i as usize) < w && (j as usize) < h && pixels[j as usize * w + i as usize].raw.iter().all(|&a| a > SHADING_ALBEDO_FLOOR)
    })
}

/// The centres of the quadrant of a pixel that its stratum `offset` lies in, as steps `(dx,
/// dy)` from the pixel (its own first; -1 or 1 on each axis, the side of its middle the stratum
/// lies on), with their bilinear weights at the stratum.
pub(super) fn quadrant(offset: [f64; 2]) -> [((isize, isize), f32); 4] {
    let (ox, oy) = (offset[0] - 0.5, offset[1] - 0.5);
    let (sx, sy) = (if ox < 0.0 { -1 } else { 1 }, if oy < 0.0 { -1 } else { 1 });
    let (fx, fy) = (ox.abs() as f32, oy.abs() as f32);
    [((0, 0), (1.0 - fx) * (1.0 - fy)), ((sx, 0), fx * (1.0 - fy)), ((0, sy), (1.0 - fx) * fy), ((sx, sy), fx * fy)]
}

/// Whether stratum `offset` of pixel `p` can be read off the centres of its quadrant
/// (`stratum_from_centres`; `w x h` centres, focal length `fx` in pixels): each one that weighs
/// in lies in the image, is wholly covered, has an albedo above `SHADING_ALBEDO_FLOOR` in every
/// channel (its shading term is its colour over its albedo) and a depth within `QUADRANT_SLOPE`
/// pixels' widths of the others (`window_of`: one smooth surface, no step, no silhouette
/// between them). Along a silhouette the quadrants facing into the body pass, those facing out
/// do not.
pub(super) fn quadrant_interpolates(pixels: &[Traced], w: usize, h: usize, p: usize, offset: [f64; 2], fx: f64) -> bool {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    let mut depths = Vec::with_capacity(4);
    for ((dx, dy), weight) in quadrant(offset) {
        if weight == 0.0 {
            continue;
        }
        let (i, j) = (x + dx, y + dy);
        if i < 0 || j < 0 || i as usize >= w || j as usize >= h {
            return false;
        }
        let q = &pixels[j as usize * w + i as usize];
        if q.coverage < 1.0 - 1.0 / 255.0 || !q.depth.is_finite() || !q.raw.iter().all(|&a| a > SHADING_ALBEDO_FLOOR) {
            return false;
        }
        depths.push(q.depth as f64);
    }
    window_of(depths, fx, QUADRANT_SLOPE).is_some()
}

/// Stratum `offset` (within the pixel, `[0, 1)^2`) of pixel `p` from the centres around it:
/// the four centres of its quadrant, bilinearly, give its depth, coverage and shading term
/// (colour over albedo, per channel, in each light). Returns `(depth, coverage, shading)`.
pub(super) fn stratum_from_centres(pixels: &[Traced], w: usize, p: usize, offset: [f64; 2]) -> (f32, f32, [[f32; 3]; LIGHTS_PER_TRACE]) {
    // A centre of zero weight is never read: it may lie outside the image.
    let corners: Vec<(&Traced, f32)> =
        quadrant(offset).into_iter().filter(|&(_, k)| k > 0.0).map(|((dx, dy), k)| (&pixels[(p as isize + dy * w as isize + dx) as usize], k)).collect();
    let blend = |of: &dyn Fn(&Traced) -> f32| corners.iter().map(|(t, k)| of(t) * k).sum::<f32>();
    let shading = std::array::from_fn(|light| [0, 1, 2].map(|c| blend(&|t| t.colours[light][c] / t.raw[c])));
    (blend(&|t| t.depth), blend(&|t| t.coverage), shading)
}

/// Strata `at` (a pixel, its stratum `offsets[s]` within it) read off the centres around them
/// (`quadrant_interpolates` holds): each one's depth, coverage and shading term are its
/// quadrant's centres' interpolated (`stratum_from_centres`), and its albedo is looked up at
/// its own surface point (that depth along its own ray). What varies there within a pixel is
/// the albedo's pattern; the surface, its light and its shadows are smooth across the centres,
/// so tracing the stratum would find what interpolation does, at about 50 field evaluations
/// instead of one.
#[allow(clippy::too_many_arguments)]
pub(super) fn strata_from_centres(
    model: &Avatar,
    camera: &crate::scene::Camera,
    pose: &PoseTensors,
    pixels: &[Traced],
    w: usize,
    offsets: &[[f64; 2]],
    at: &[(usize, usize)],
    albedo_scale: Option<DVec3>,
    device: &Device,
) -> Vec<Traced> {
    let located: Vec<(f32, f32, [[f32; 3]; LIGHTS_PER_TRACE], DVec3)> = at
        .iter()
        .map(|&(p, s)| {
            let offset = offsets[s];
            let (depth, coverage, shading) = stratum_from_centres(pixels, w, p, offset);
            let ray = camera.ray_through(glam::DVec2::new((p % w) as f64 + offset[0], (p / w) as f64 + offset[1]));
            (depth, coverage, shading, ray.origin + ray.direction * depth as f64)
        })
        .collect();
    let albedos: Vec<f32> = located
        .par_chunks(TRACE_CHUNK)
        .flat_map_iter(|chunk| {
            let points: Vec<f32> = chunk.iter().flat_map(|l| l.3.as_vec3().to_array()).collect();
            let points = Tensor::<2>::from_data(TensorData::new(points, [chunk.len(), 3]), device);
            let decoded = model.field.decode(points, pose);
            let albedo = crate::backend::host_values(model.field.albedo_at(&decoded, None));
            albedo.into_iter()
        })
        .collect();
    let scale = albedo_scale.map(|s| s.as_vec3().to_array());
    located
        .iter()
        .enumerate()
        .map(|(j, &(depth, coverage, shading, _))| {
            let raw = [0, 1, 2].map(|c| albedos.get(3 * j + c).copied().unwrap_or(f32::NAN) * coverage);
            Traced {
                colours: shading.map(|shading| [0, 1, 2].map(|c| raw[c] * shading[c])),
                albedo: scale.map_or([0.0; 3], |s| [0, 1, 2].map(|c| raw[c] * s[c])),
                raw,
                coverage,
                depth,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::super::*;
    use super::*;

    /// Which pixels of an 8 x 8 image `needs_area` picks, as (x, y).
    fn picked(image: impl Fn(usize, usize) -> [f32; 3], coverage: impl Fn(usize, usize) -> f32) -> Vec<(usize, usize)> {
        let (w, h) = (8, 8);
        let encoded: Vec<[f32; 3]> = (0..w * h).map(|p| image(p % w, p / w)).collect();
        let cover: Vec<f32> = (0..w * h).map(|p| coverage(p % w, p / w)).collect();
        (0..w * h).filter(|&p| needs_area(&encoded, &cover, w, h, p)).map(|p| (p % w, p / w)).collect()
    }

    /// The 3 x 3 strata of a pixel traced through `image(x, y)` (x, y in [0, 1]), in
    /// `subpixel_offsets` order, colour and albedo alike, wholly covered.
    fn strata(image: &dyn Fn(f64, f64) -> f32) -> Vec<Traced> {
        crate::scene::footprint::subpixel_offsets(9, None)
            .iter()
            .map(|o| {
                let v = image(o[0], o[1]);
                Traced { colours: [[v; 3]; LIGHTS_PER_TRACE], albedo: [v; 3], raw: [v; 3], coverage: 1.0, depth: 1.0 }
            })
            .collect()
    }

    #[test]
    fn the_corners_stand_for_the_sides_on_ramps_and_never_across_a_straight_edge() {
        let pick = |s: &[Traced], which: &[usize]| which.iter().map(|&k| s[k]).collect::<Vec<_>>();
        let nine_mean = |s: &[Traced]| s.iter().map(|t| t.colours[0][0]).sum::<f32>() / 9.0;
        // A bilinear ramp (dim, where sRGB is steepest, and bright): the five agree and give the
        // nine strata's mean.
        for (base, slope) in [(0.02f32, 0.01f32), (0.4, 0.2)] {
            let ramp = |x: f64, y: f64| base + slope * (x as f32 - 0.3 * y as f32 + 0.5 * (x * y) as f32);
            let s = strata(&ramp);
            let corners = pick(&s, &CORNER_STRATA);
            assert!(strata_agree(&s[4], &corners, true), "ramp {base} {slope}");
            let mean = strata_mean(&s[4], &corners, None);
            assert!((mean.colours[0][0] - nine_mean(&s)).abs() < 1e-6, "{} against {}", mean.colours[0][0], nine_mean(&s));
            let traced = strata_mean(&s[4], &corners, Some(&pick(&s, &SIDE_STRATA)));
            assert!((traced.colours[0][0] - mean.colours[0][0]).abs() < 1e-6 && (traced.coverage - 1.0).abs() < 1e-6);
        }
        // Any straight edge of a few 8-bit steps' contrast that splits the nine strata is seen by
        // the centre and corners: lines at 64 angles, through 64 offsets across the pixel.
        let (dark, light) = (crate::imageio::srgb_to_linear(0.40), crate::imageio::srgb_to_linear(0.40 + 6.0 / 255.0));
        let mut split = 0;
        for a in 0..64 {
            let angle = a as f64 * std::f64::consts::TAU / 64.0 + 0.01;
            let (nx, ny) = (angle.cos(), angle.sin());
            for o in 0..64 {
                let offset = -0.75 + 1.5 * o as f64 / 63.0;
                let edge = |x: f64, y: f64| if (x - 0.5) * nx + (y - 0.5) * ny > offset { light } else { dark };
                let s = strata(&edge);
                if s.iter().all(|t| t.colours[0][0] == s[0].colours[0][0]) {
                    continue;
                }
                split += 1;
                assert!(!strata_agree(&s[4], &pick(&s, &CORNER_STRATA), false), "angle {angle} offset {offset}");
            }
        }
        assert!(split > 1000, "{split} lines split the strata");
        // A silhouette: coverage that differs between the five.
        let mut s = strata(&|_, _| 0.3);
        s[8].coverage = 0.0;
        assert!(!strata_agree(&s[4], &pick(&s, &CORNER_STRATA), false));
    }

    #[test]
    fn a_window_holds_a_smooth_surface_and_is_refused_at_silhouettes_and_steps() {
        // 8 x 8 centres of a plane tilted along x, 2 m away, 100 pixels of focal length: a
        // pixel is 2 cm wide there; the plane recedes `slope` pixels' widths a pixel.
        let (w, h, fx) = (8, 8, 100.0);
        let plane = |slope: f32, covered: &dyn Fn(usize, usize) -> bool| -> Vec<Traced> {
            (0..w * h)
                .map(|p| {
                    let (x, y) = (p % w, p / w);
                    let coverage = if covered(x, y) { 1.0 } else { 0.0 };
                    Traced { colours: [[0.5; 3]; LIGHTS_PER_TRACE], albedo: [0.5; 3], raw: [0.5; 3], coverage, depth: 2.0 + slope * 0.02 * x as f32 }
                })
                .collect()
        };
        let all = |_: usize, _: usize| true;
        let gentle = plane(0.5, &all);
        let (lo, hi) = surface_window(&gentle, w, h, 3 * w + 3, fx).expect("inside a gently tilted plane");
        // The pixel's own points lie between its neighbours' centres, and within the window.
        for x in [2.5f64, 3.0, 3.5, 4.0, 4.5] {
            let depth = 2.0 + 0.5 * 0.02 * (x - 0.5);
            assert!(lo < depth && depth < hi, "{depth} outside {lo}..{hi}");
        }
        assert!(hi - lo < 0.1, "a window, not the whole ray: {lo}..{hi}");
        // A corner pixel has fewer neighbours and still gets one.
        assert!(surface_window(&gentle, w, h, 0, fx).is_some());
        // Grazing: the depths differ by more than WINDOW_SLOPE pixels across the neighbourhood.
        assert!(surface_window(&plane(2.0, &all), w, h, 3 * w + 3, fx).is_none());
        // A silhouette: a neighbour not wholly covered.
        assert!(surface_window(&plane(0.5, &|x, _| x < 4), w, h, 3 * w + 3, fx).is_none());
        assert!(surface_window(&plane(0.5, &|x, _| x < 4), w, h, 3 * w + 1, fx).is_some());
        // A step in depth (an arm in front of the body) next to the pixel.
        let mut step = plane(0.0, &all);
        step[3 * w + 4].depth -= 0.2;
        assert!(surface_window(&step, w, h, 3 * w + 3, fx).is_none());
    }

    #[test]
    fn only_edges_and_silhouettes_are_rendered_over_their_area() {
        // A steep linear ramp (ten 8-bit steps a pixel) on a covered image: nothing, since a
        // box's mean of a linear image is its centre.
        let ramp = |x: usize, y: usize| [0.1 + 0.04 * x as f32, 0.3 + 0.02 * y as f32, 0.5];
        assert!(picked(ramp, |_, _| 1.0).is_empty());
        // A checker edge between columns 3 and 4: the two columns beside it.
        let edge = |x: usize, _: usize| if x < 4 { [0.2; 3] } else { [0.8; 3] };
        let cols: std::collections::BTreeSet<usize> = picked(edge, |_, _| 1.0).into_iter().map(|p| p.0).collect();
        assert_eq!(cols, [3, 4].into_iter().collect());
        // A silhouette (coverage 1 above row 5, 0 below) on a flat colour: rows 4 and 5.
        let rows: std::collections::BTreeSet<usize> = picked(|_, _| [0.5; 3], |_, y| if y < 5 { 1.0 } else { 0.0 }).into_iter().map(|p| p.1).collect();
        assert_eq!(rows, [4, 5].into_iter().collect());
        // A gentle curve along x (a quadratic of 0.5 steps over the neighbourhood) is left
        // alone; a strong one is not, except in the first and last columns, which have no
        // neighbours on one side to tell a curve from a ramp.
        let curve = |k: f32| move |x: usize, _: usize| [0.5 + k * (x as f32 - 3.5).powi(2), 0.5, 0.5];
        assert!(picked(curve(0.5 / 255.0), |_, _| 1.0).is_empty());
        let strong = picked(curve(20.0 / 255.0), |_, _| 1.0);
        assert!(strong.len() == 48 && strong.iter().all(|p| p.0 > 0 && p.0 < 7), "{strong:?}");
    }

    #[test]
    fn strata_take_the_centres_depth_coverage_and_shading_bilinearly() {
        // Centres whose depth, coverage and shading (colour over albedo) are bilinear in the
        // pixel's position: every stratum gets the value at its own position exactly.
        let (w, h) = (5, 5);
        let value =
            |x: f64, y: f64| (2.0 + 0.01 * x - 0.02 * y + 0.003 * x * y, 0.9 + 0.01 * x + 0.005 * y, [0.3 + 0.02 * x, 0.5 - 0.01 * y, 0.2 + 0.01 * x * y]);
        let pixels: Vec<Traced> = (0..w * h)
            .map(|p| {
                let (depth, coverage, shading) = value((p % w) as f64, (p / w) as f64);
                let raw = [0.4f32, 0.6, 0.2];
                Traced {
                    colours: [[0, 1, 2].map(|c| raw[c] * shading[c] as f32); LIGHTS_PER_TRACE],
                    albedo: raw,
                    raw,
                    coverage: coverage as f32,
                    depth: depth as f32,
                }
            })
            .collect();
        let p = 2 * w + 2;
        for offset in crate::scene::footprint::subpixel_offsets(VIEW_PIXEL_RAYS, None) {
            let (depth, coverage, shading) = stratum_from_centres(&pixels, w, p, offset);
            let (d, c, s) = value(2.0 + offset[0] - 0.5, 2.0 + offset[1] - 0.5);
            assert!((depth as f64 - d).abs() < 1e-5 && (coverage as f64 - c).abs() < 1e-5, "{offset:?}: {depth} {d}, {coverage} {c}");
            for k in 0..3 {
                assert!((shading[0][k] as f64 - s[k]).abs() < 1e-5, "{offset:?}: {shading:?} {s:?}");
            }
        }
        // Its shading is read off its neighbours only where each has some albedo in every
        // channel, and never at the image's border.
        assert!(albedo_above_floor(&pixels, w, h, p));
        assert!(!albedo_above_floor(&pixels, w, h, 2));
        let mut dark = pixels.clone();
        dark[3 * w + 3].raw[1] = 0.0;
        assert!(!albedo_above_floor(&dark, w, h, p));
        assert!(albedo_above_floor(&dark, w, h, w + 1));
        // Stratum by stratum: a quadrant is read off where its centres are wholly covered and
        // within a quarter of a pixel's width of depth of each other (here 2 mm apart, a pixel 2
        // cm wide at 2 m with a focal length of 100 pixels); the dark centre at (3, 3) spoils
        // only the quadrant towards it, as does a centre the body leaves partly uncovered.
        let fx = 100.0;
        let pixels: Vec<Traced> = pixels.iter().enumerate().map(|(q, t)| Traced { coverage: 1.0, depth: 2.0 + 0.002 * (q % w) as f32, ..*t }).collect();
        let mut dark = pixels.clone();
        dark[3 * w + 3].raw[1] = 0.0;
        let [top_left, top_right, bottom_left, bottom_right] = [[1.0 / 6.0, 1.0 / 6.0], [5.0 / 6.0, 1.0 / 6.0], [1.0 / 6.0, 5.0 / 6.0], [5.0 / 6.0, 5.0 / 6.0]];
        for offset in [top_left, top_right, bottom_left, bottom_right] {
            assert!(quadrant_interpolates(&pixels, w, h, p, offset, fx), "{offset:?}");
            assert_eq!(quadrant_interpolates(&dark, w, h, p, offset, fx), offset != bottom_right, "{offset:?}");
        }
        let mut edge = pixels.clone();
        edge[w + 1].coverage = 0.5;
        assert!(!quadrant_interpolates(&edge, w, h, p, top_left, fx));
        assert!(quadrant_interpolates(&edge, w, h, p, bottom_right, fx));
        // A side's stratum weighs two centres only: the other two may lie outside the image.
        assert!(!quadrant_interpolates(&pixels, w, h, 2 * w, [1.0 / 6.0, 0.5], fx));
        assert!(quadrant_interpolates(&pixels, w, h, 2 * w, [5.0 / 6.0, 0.5], fx));
        // A step in depth between the centres (a limb before the body) spoils the quadrants
        // across it.
        let mut step = pixels.clone();
        step[3 * w + 3].depth += 0.1;
        assert!(!quadrant_interpolates(&step, w, h, p, bottom_right, fx));
        assert!(quadrant_interpolates(&step, w, h, p, top_left, fx));
    }
}
