//! Image quality metrics on 8-bit sRGB, as an evaluation reads them: PSNR over the whole image,
//! PSNR over the foreground only (a black background otherwise dominates the score of a small
//! figure), and SSIM exactly as scikit-image computes it with `gaussian_weights=True,
//! sigma=1.5, use_sample_covariance=False, data_range=255` (11-tap window, K1 = 0.01,
//! K2 = 0.03, channel SSIMs averaged, the mean taken over pixels whose window lies inside).

use crate::imageio::{linear_to_srgb8, Mask, RgbImage};

/// The three scores of one rendered image against its ground truth.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ImageScores {
    pub psnr: f64,
    pub foreground_psnr: f64,
    pub ssim: f64,
}

/// All three scores; `mask` is the ground-truth foreground when the scene has one.
pub fn score(rendered: &RgbImage, truth: &RgbImage, mask: Option<&Mask>) -> ImageScores {
    let foreground = foreground(rendered, truth, mask);
    ImageScores { psnr: psnr_srgb8(rendered, truth), foreground_psnr: psnr_srgb8_where(rendered, truth, &foreground), ssim: ssim_srgb8(rendered, truth) }
}

/// The per-channel factor that best maps `rendered` onto `truth` over the foreground, in the
/// least-squares sense on linear values: what a relit image or an albedo is off by when the
/// fit cannot know the light's or the albedo's absolute scale.
pub fn least_squares_scale(rendered: &RgbImage, truth: &RgbImage, mask: Option<&Mask>) -> [f64; 3] {
    let foreground = foreground(rendered, truth, mask);
    let (mut cross, mut square) = ([0.0f64; 3], [0.0f64; 3]);
    for ((r, t), &f) in rendered.pixels.iter().zip(&truth.pixels).zip(&foreground) {
        if f {
            for c in 0..3 {
                cross[c] += r[c] as f64 * t[c] as f64;
                square[c] += r[c] as f64 * r[c] as f64;
            }
        }
    }
    [0, 1, 2].map(|c| if square[c] > 0.0 { cross[c] / square[c] } else { 1.0 })
}

/// The scores of `rendered` after its per-channel least-squares scale, and that scale.
pub fn score_scaled(rendered: &RgbImage, truth: &RgbImage, mask: Option<&Mask>) -> (ImageScores, [f64; 3]) {
    let scale = least_squares_scale(rendered, truth, mask);
    let mut scaled = rendered.clone();
    for p in &mut scaled.pixels {
        *p = [0, 1, 2].map(|c| (p[c] as f64 * scale[c]) as f32);
    }
    (score(&scaled, truth, mask), scale)
}

fn srgb8(image: &RgbImage) -> Vec<[f64; 3]> {
    image.pixels.iter().map(|p| [0, 1, 2].map(|c| linear_to_srgb8(p[c]) as f64)).collect()
}

/// Where an image's error lies: the squared error (8-bit sRGB, summed over pixels and
/// channels) outside the ground-truth mask (the render draws body where the truth has none,
/// or a halo), along the silhouette (mask pixels with a background pixel beside them, the
/// four neighbours; a pixel on the image's border does not count as beside background), and
/// inside. A fit whose error is mostly outside and along the silhouette has the wrong shape;
/// one whose error is inside has the wrong colours or shading.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct ErrorRegions {
    pub outside: f64,
    pub silhouette: f64,
    pub inside: f64,
}

impl ErrorRegions {
    /// The three as shares of their sum (zeros for a perfect render).
    pub fn shares(&self) -> ErrorRegions {
        let total = self.outside + self.silhouette + self.inside;
        match total > 0.0 {
            true => ErrorRegions { outside: self.outside / total, silhouette: self.silhouette / total, inside: self.inside / total },
            false => ErrorRegions::default(),
        }
    }

    /// Shares as whole percentages: outside the mask, along the silhouette, inside.
    pub fn percentages(&self) -> [String; 3] {
        [self.outside, self.silhouette, self.inside].map(|v| format!("{:.0}%", 100.0 * v))
    }

    /// The `error_share` an evaluation wrote (`metrics.json`, `fit.json`), if it has one.
    pub fn from_json(value: &serde_json::Value) -> Option<ErrorRegions> {
        Some(ErrorRegions { outside: value["outside"].as_f64()?, silhouette: value["silhouette"].as_f64()?, inside: value["inside"].as_f64()? })
    }

    pub fn add(&self, other: &ErrorRegions) -> ErrorRegions {
        ErrorRegions { outside: self.outside + other.outside, silhouette: self.silhouette + other.silhouette, inside: self.inside + other.inside }
    }
}

/// `ErrorRegions` of `rendered` against `truth` with its ground-truth `mask`.
pub fn error_regions(rendered: &RgbImage, truth: &RgbImage, mask: &Mask) -> ErrorRegions {
    let (a, b) = (srgb8(rendered), srgb8(truth));
    let (w, h) = (mask.width, mask.height);
    let background = |x: isize, y: isize| x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && !mask.foreground[y as usize * w + x as usize];
    let mut regions = ErrorRegions::default();
    for k in 0..a.len().min(b.len()).min(w * h) {
        let error: f64 = (0..3).map(|c| (a[k][c] - b[k][c]).powi(2)).sum();
        let (x, y) = ((k % w) as isize, (k / w) as isize);
        if !mask.foreground[k] {
            regions.outside += error;
        } else if background(x - 1, y) || background(x + 1, y) || background(x, y - 1) || background(x, y + 1) {
            regions.silhouette += error;
        } else {
            regions.inside += error;
        }
    }
    regions
}

/// The pixels that count as foreground: the ground-truth mask (or, without one, every pixel the
/// truth does not leave black) together with every pixel the render does not leave black, so
/// that a render is penalised both for missing the figure and for drawing outside it.
pub fn foreground(rendered: &RgbImage, truth: &RgbImage, mask: Option<&Mask>) -> Vec<bool> {
    let drawn = |image: &RgbImage, k: usize| image.pixels[k].iter().any(|&v| linear_to_srgb8(v) > 0);
    (0..truth.pixels.len()).map(|k| mask.map(|m| m.foreground[k]).unwrap_or_else(|| drawn(truth, k)) || drawn(rendered, k)).collect()
}

/// PSNR (dB) after 8-bit sRGB encoding over every pixel and channel.
pub fn psnr_srgb8(a: &RgbImage, b: &RgbImage) -> f64 {
    psnr_srgb8_where(a, b, &vec![true; a.pixels.len()])
}

/// PSNR (dB) after 8-bit sRGB encoding over the pixels where `selected` holds; infinite for
/// identical pixels (or none selected).
pub fn psnr_srgb8_where(a: &RgbImage, b: &RgbImage, selected: &[bool]) -> f64 {
    let (a, b) = (srgb8(a), srgb8(b));
    let mut sum = 0.0;
    let mut count = 0usize;
    for k in (0..a.len()).filter(|&k| selected[k]) {
        for c in 0..3 {
            let d = a[k][c] - b[k][c];
            sum += d * d;
        }
        count += 3;
    }
    if sum == 0.0 || count == 0 {
        return f64::INFINITY;
    }
    10.0 * (255.0f64 * 255.0 / (sum / count as f64)).log10()
}

/// Radius of the Gaussian window: scikit-image's `int(truncate * sigma + 0.5)` with truncate 3.5.
const SSIM_RADIUS: usize = 5;
const SSIM_SIGMA: f64 = 1.5;

/// The normalised 11-tap Gaussian window (separable).
fn ssim_window() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut w = [0.0; 2 * SSIM_RADIUS + 1];
    for (k, v) in w.iter_mut().enumerate() {
        let x = k as f64 - SSIM_RADIUS as f64;
        *v = (-0.5 * x * x / (SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Gaussian-weighted means over the window centred on every interior pixel (the pixels whose
/// window lies inside the image): `[rows][cols]` of the interior, row-major.
fn filtered(values: &[f64], width: usize, height: usize) -> Vec<f64> {
    let w = ssim_window();
    let r = SSIM_RADIUS;
    let (iw, ih) = (width - 2 * r, height - 2 * r);
    // Horizontal pass over every row, then vertical over the interior.
    let mut rows = vec![0.0; height * iw];
    for y in 0..height {
        for x in 0..iw {
            rows[y * iw + x] = (0..w.len()).map(|k| w[k] * values[y * width + x + k]).sum();
        }
    }
    let mut out = vec![0.0; ih * iw];
    for y in 0..ih {
        for x in 0..iw {
            out[y * iw + x] = (0..w.len()).map(|k| w[k] * rows[(y + k) * iw + x]).sum();
        }
    }
    out
}

/// SSIM of two images in 8-bit sRGB: the mean over channels of each channel's mean SSIM over
/// the interior pixels. Images smaller than the 11-pixel window score NaN, as scikit-image
/// refuses them.
pub fn ssim_srgb8(a: &RgbImage, b: &RgbImage) -> f64 {
    let (width, height) = (a.width, a.height);
    if width < 2 * SSIM_RADIUS + 1 || height < 2 * SSIM_RADIUS + 1 {
        return f64::NAN;
    }
    let (a, b) = (srgb8(a), srgb8(b));
    let c1 = (0.01f64 * 255.0).powi(2);
    let c2 = (0.03f64 * 255.0).powi(2);
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = a.iter().map(|p| p[c]).collect();
        let y: Vec<f64> = b.iter().map(|p| p[c]).collect();
        let product = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(u, v)| u * v).collect::<Vec<f64>>();
        let (ux, uy) = (filtered(&x, width, height), filtered(&y, width, height));
        let (uxx, uyy, uxy) = (filtered(&product(&x, &x), width, height), filtered(&product(&y, &y), width, height), filtered(&product(&x, &y), width, height));
        let mut sum = 0.0;
        for k in 0..ux.len() {
            let (vx, vy, vxy) = (uxx[k] - ux[k] * ux[k], uyy[k] - uy[k] * uy[k], uxy[k] - ux[k] * uy[k]);
            let numerator = (2.0 * ux[k] * uy[k] + c1) * (2.0 * vxy + c2);
            let denominator = (ux[k] * ux[k] + uy[k] * uy[k] + c1) * (vx + vy + c2);
            sum += numerator / denominator;
        }
        total += sum / ux.len() as f64;
    }
    total / 3.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_per_channel_scale_is_undone_and_reported() {
        let mut truth = RgbImage::new(16, 16);
        for (k, p) in truth.pixels.iter_mut().enumerate() {
            if (k % 16) > 3 && (k / 16) > 3 {
                *p = [0.1 + (k % 7) as f32 * 0.05, 0.2, 0.05 + (k % 5) as f32 * 0.04];
            }
        }
        let mut rendered = truth.clone();
        for p in &mut rendered.pixels {
            *p = [p[0] * 2.0, p[1] * 0.5, p[2]];
        }
        let (scores, scale) = score_scaled(&rendered, &truth, None);
        assert!((scale[0] - 0.5).abs() < 1e-6 && (scale[1] - 2.0).abs() < 1e-6 && (scale[2] - 1.0).abs() < 1e-6, "{scale:?}");
        assert!(scores.psnr.is_infinite() || scores.psnr > 60.0, "{scores:?}");
        assert!(score(&rendered, &truth, None).psnr < 30.0, "the unscaled render is off");
    }
    use crate::imageio::srgb_to_linear;

    /// An image from 8-bit sRGB values.
    fn image(width: usize, height: usize, value: impl Fn(usize, usize, usize) -> u8) -> RgbImage {
        let mut im = RgbImage::new(width, height);
        for y in 0..height {
            for x in 0..width {
                im.set(x, y, [0, 1, 2].map(|c| srgb_to_linear(value(x, y, c) as f32 / 255.0)));
            }
        }
        im
    }

    #[test]
    fn the_srgb_round_trip_is_exact_for_every_8_bit_value() {
        for v in 0..=255u8 {
            assert_eq!(linear_to_srgb8(srgb_to_linear(v as f32 / 255.0)), v);
        }
    }

    #[test]
    fn psnr_by_hand() {
        // One channel of one pixel off by 10 in a 2x2 image: MSE = 100 / 12.
        let a = image(2, 2, |_, _, _| 100);
        let b = image(2, 2, |x, y, c| if x == 0 && y == 0 && c == 0 { 110 } else { 100 });
        let expected = 10.0 * (255.0f64 * 255.0 / (100.0 / 12.0)).log10();
        assert!((psnr_srgb8(&a, &b) - expected).abs() < 1e-9);
        // Over the foreground pixel only: MSE = 100 / 3.
        let only = [true, false, false, false];
        let expected = 10.0 * (255.0f64 * 255.0 / (100.0 / 3.0)).log10();
        assert!((psnr_srgb8_where(&a, &b, &only) - expected).abs() < 1e-9);
        assert_eq!(psnr_srgb8(&a, &a), f64::INFINITY);
    }

    #[test]
    fn error_regions_by_hand() {
        // A 4x3 mask with a 2x2 body whose top row touches the image's border:
        //   . X X .
        //   . X X .      X = foreground
        //   . . . .
        // Each foreground pixel has background to its left or right, so all four lie along the
        // silhouette (the border above the top row does not count). Errors: pixel (0, 0)
        // (outside) 10 in one channel, pixel (1, 0) (silhouette) 3 in two channels.
        let mask = Mask { width: 4, height: 3, foreground: (0..12).map(|k| matches!(k, 1 | 2 | 5 | 6)).collect() };
        let truth = image(4, 3, |_, _, _| 100);
        let rendered = image(4, 3, |x, y, c| match (x, y, c) {
            (0, 0, 0) => 110,
            (1, 0, 0) | (1, 0, 2) => 103,
            _ => 100,
        });
        let regions = error_regions(&rendered, &truth, &mask);
        assert_eq!(regions, ErrorRegions { outside: 100.0, silhouette: 18.0, inside: 0.0 });
        let shares = regions.shares();
        assert!((shares.outside - 100.0 / 118.0).abs() < 1e-12 && (shares.silhouette - 18.0 / 118.0).abs() < 1e-12);
        assert_eq!(shares.percentages(), ["85%", "15%", "0%"]);
        // As an evaluation writes it and the report and the CLI read it back.
        assert_eq!(ErrorRegions::from_json(&serde_json::to_value(shares).unwrap()), Some(shares));
        assert_eq!(ErrorRegions::from_json(&serde_json::json!(null)), None);
        // A body away from every edge has an inside: a 5x5 mask with a 3x3 body, the centre
        // pixel off by 4 in every channel.
        let mask = Mask { width: 5, height: 5, foreground: (0..25).map(|k| (1..4).contains(&(k % 5)) && (1..4).contains(&(k / 5))).collect() };
        let truth = image(5, 5, |_, _, _| 60);
        let rendered = image(5, 5, |x, y, _| if (x, y) == (2, 2) { 64 } else { 60 });
        assert_eq!(error_regions(&rendered, &truth, &mask), ErrorRegions { outside: 0.0, silhouette: 0.0, inside: 48.0 });
        assert_eq!(error_regions(&truth, &truth, &mask).shares(), ErrorRegions::default());
    }

    #[test]
    fn foreground_is_the_mask_or_anything_drawn() {
        let truth = image(3, 1, |x, _, _| if x == 0 { 50 } else { 0 });
        let rendered = image(3, 1, |x, _, _| if x == 2 { 9 } else { 0 });
        let mask = Mask { width: 3, height: 1, foreground: vec![false, true, false].into() };
        assert_eq!(foreground(&rendered, &truth, Some(&mask)), vec![false, true, true]);
        assert_eq!(foreground(&rendered, &truth, None), vec![true, false, true]);
    }

    #[test]
    fn ssim_of_constant_images_is_the_luminance_term() {
        // Constant images: no variance, so SSIM = (2ab + C1) / (a^2 + b^2 + C1).
        let (a, b) = (120.0f64, 80.0f64);
        let c1 = (0.01f64 * 255.0).powi(2);
        let expected = (2.0 * a * b + c1) / (a * a + b * b + c1);
        let got = ssim_srgb8(&image(13, 12, |_, _, _| 120), &image(13, 12, |_, _, _| 80));
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
        assert!((ssim_srgb8(&image(12, 12, |x, y, _| (x * 20 + y) as u8), &image(12, 12, |x, y, _| (x * 20 + y) as u8)) - 1.0).abs() < 1e-12);
        assert!(ssim_srgb8(&image(10, 12, |_, _, _| 1), &image(10, 12, |_, _, _| 1)).is_nan(), "smaller than the window");
    }

    #[test]
    fn ssim_of_an_offset_copy_is_the_luminance_term_of_the_local_means() {
        // y = x + d: variances and covariance are equal, so the structure term is exactly 1 and
        // SSIM = mean of (2 ux (ux + d) + C1) / (ux^2 + (ux + d)^2 + C1). An 11x11 image has one
        // interior pixel, whose weighted mean is computed here term by term.
        let value = |x: usize, y: usize| ((x * 7 + y * 13) % 50) as u8 + 60;
        let d = 30.0;
        let a = image(11, 11, |x, y, _| value(x, y));
        let b = image(11, 11, |x, y, _| value(x, y) + 30);
        let g = |k: usize| (-0.5 * (k as f64 - 5.0).powi(2) / 2.25).exp();
        let norm: f64 = (0..11).map(g).sum::<f64>().powi(2);
        let ux: f64 = (0..11).flat_map(|y| (0..11).map(move |x| (x, y))).map(|(x, y)| g(x) * g(y) * value(x, y) as f64).sum::<f64>() / norm;
        let c1 = (0.01f64 * 255.0).powi(2);
        let expected = (2.0 * ux * (ux + d) + c1) / (ux * ux + (ux + d) * (ux + d) + c1);
        let got = ssim_srgb8(&a, &b);
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
    }

    #[test]
    fn ssim_matches_scikit_image() {
        // Pseudo-random 16x14 images from an LCG; reference values from scikit-image 0.26.0:
        // structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
        // use_sample_covariance=False, data_range=255, channel_axis=2).
        let lcg = |seed: u64| {
            let mut s = seed;
            move || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 56) as u8
            }
        };
        let fill = |seed: u64, smooth: bool| {
            let mut next = lcg(seed);
            let raw: Vec<u8> = (0..16 * 14 * 3).map(|_| next()).collect();
            image(
                16,
                14,
                move |x, y, c| if smooth { ((x * 9 + y * 5 + c * 40) as u8).wrapping_add(raw[(y * 16 + x) * 3 + c] / 8) } else { raw[(y * 16 + x) * 3 + c] },
            )
        };
        for (seed_a, seed_b, smooth, expected) in SKIMAGE_REFERENCE {
            let got = ssim_srgb8(&fill(seed_a, smooth), &fill(seed_b, smooth));
            assert!((got - expected).abs() < 1e-9, "seeds {seed_a}, {seed_b}: {got} vs scikit-image {expected}");
        }
    }

    /// (seed of a, seed of b, smooth, scikit-image's SSIM); see `ssim_matches_scikit_image`.
    const SKIMAGE_REFERENCE: [(u64, u64, bool, f64); 3] = [(1, 2, false, -0.06925288517787796), (3, 3, false, 1.0), (5, 6, true, 0.6844799119473582)];
}
