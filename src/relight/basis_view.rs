//! Relighting one view through a visibility basis built for it, timed, and the table of those
//! timings (`basis.md`).

use crate::imageio::RgbImage;
use crate::light::Light;
use crate::scene::Scene;

/// The most a view's basis may hold (bytes, every pixel drawn): 2 GiB, the memory budget of
/// a fit on this project's 2-core machines.
pub(super) const BASIS_BYTES_LIMIT: f64 = 2.0 * (1u64 << 30) as f64;

/// What relighting one view through its basis cost, and how far it is from the direct estimator.
pub struct BasisTiming {
    pub camera: usize,
    pub frame: usize,
    pub pixels: usize,
    pub precompute_seconds: f64,
    /// The fastest of `RELIGHT_REPEATS` relights (the light's binning included).
    pub relight_seconds: f64,
    pub against_direct: Option<crate::metrics::ImageScores>,
}

/// Relights timed per view, the fastest kept (the first pays for cold caches).
const RELIGHT_REPEATS: usize = 5;

/// One view relit through a visibility basis of `directions` directions built for it.
pub(super) fn relight_by_basis(
    model: &crate::avatar::Avatar,
    scene: &Scene,
    camera: usize,
    frame: usize,
    light: &Light,
    directions: usize,
    device: &burn::tensor::Device,
) -> (RgbImage, BasisTiming) {
    let started = std::time::Instant::now();
    let basis = crate::basis::TransferBasis::of_view(model, scene, camera, frame, directions, device);
    let (w, h) = (basis.width, basis.height);
    let precompute_seconds = started.elapsed().as_secs_f64();
    let mut relight_seconds = f64::INFINITY;
    let mut image = RgbImage::new(w, h);
    for _ in 0..RELIGHT_REPEATS {
        let started = std::time::Instant::now();
        image = basis.relight(light);
        relight_seconds = relight_seconds.min(started.elapsed().as_secs_f64());
    }
    (image, BasisTiming { camera, frame, pixels: basis.len(), precompute_seconds, relight_seconds, against_direct: None })
}

/// `basis.md`: per view the precompute and relight times, and the first view's scores against
/// the direct estimator.
pub fn basis_table(label: &str, directions: usize, timings: &[BasisTiming]) -> String {
    let mut table = format!(
        "# Relit through a visibility basis: {label}\n\n{directions} directions per view. Relight time: the fastest of {RELIGHT_REPEATS}.\n\n\
         | view | covered pixels | precompute (s) | relight (ms) | against the direct estimator (PSNR / foreground / SSIM) |\n|---|---|---|---|---|\n"
    );
    for t in timings {
        let against = t.against_direct.map_or("".to_string(), |s| format!("{:.2} / {:.2} dB / {:.4}", s.psnr, s.foreground_psnr, s.ssim));
        table.push_str(&format!(
            "| c{:02} f{:04} | {} | {:.2} | {:.1} | {} |\n",
            t.camera,
            t.frame,
            t.pixels,
            t.precompute_seconds,
            t.relight_seconds * 1e3,
            against
        ));
    }
    table
}
