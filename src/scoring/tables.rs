//! The tables of an evaluation: each image's scores, the groups' means, `metrics.csv`,
//! `metrics.md` (with the geometry's section) and the figures `metrics.json` and `fit.json` hold.

use crate::metrics::{ErrorRegions, ImageScores};
use serde_json::{json, Value};

/// The score of one rendered test image (and of its albedo, when the scene has one).
#[derive(serde::Serialize)]
pub(super) struct ImageScore {
    pub(super) image: String,
    pub(super) light: String,
    pub(super) group: &'static str,
    #[serde(flatten)]
    pub(super) scores: ImageScores,
    pub(super) albedo: Option<ImageScores>,
    /// A relit image's scores after its per-channel least-squares scale.
    pub(super) relit_scaled: Option<ImageScores>,
    /// The albedo's scores after its per-channel least-squares scale.
    pub(super) albedo_scaled: Option<ImageScores>,
    /// Where the image's error lies, as shares (`metrics::ErrorRegions`; with a mask only).
    pub(super) error_share: Option<ErrorRegions>,
    /// The same as squared-error sums, for the group's shares.
    #[serde(skip)]
    pub(super) error_sums: Option<ErrorRegions>,
    pub(super) novel_pose: bool,
    pub(super) novel_view: bool,
    pub(super) relit: bool,
}

/// The mean scores of one group of test images (novel pose, novel view, relit, albedo).
#[derive(serde::Serialize)]
pub(super) struct GroupScores {
    pub(super) group: &'static str,
    pub(super) images: usize,
    #[serde(flatten)]
    pub(super) scores: ImageScores,
    /// Where the group's error lies: its images' squared errors summed by region, as shares.
    pub(super) error_share: Option<ErrorRegions>,
}

/// Mean scores per group, in a fixed order; albedo renders form a group of their own.
pub(super) fn group_means(rows: &[ImageScore]) -> Vec<GroupScores> {
    let mean = |group: &'static str, scores: Vec<ImageScores>, errors: Option<ErrorRegions>| {
        let n = scores.len() as f64;
        let avg = |pick: fn(&ImageScores) -> f64| scores.iter().map(pick).sum::<f64>() / n;
        GroupScores {
            group,
            images: scores.len(),
            scores: ImageScores { psnr: avg(|s| s.psnr), foreground_psnr: avg(|s| s.foreground_psnr), ssim: avg(|s| s.ssim) },
            error_share: errors.map(|e| e.shares()),
        }
    };
    let mut out = Vec::new();
    for group in ["novel pose", "novel view", "relit", "training pose and view"] {
        let members: Vec<&ImageScore> = rows.iter().filter(|r| r.group == group).collect();
        if !members.is_empty() {
            // Summed over the group's images when every one has a mask.
            let errors = members.iter().try_fold(ErrorRegions::default(), |sum, r| r.error_sums.map(|e| sum.add(&e)));
            out.push(mean(group, members.iter().map(|r| r.scores).collect(), errors));
        }
    }
    for (group, pick) in [
        ("albedo", (|r: &ImageScore| r.albedo) as fn(&ImageScore) -> Option<ImageScores>),
        ("relit, per-channel scaled", |r: &ImageScore| r.relit_scaled),
        ("albedo, per-channel scaled", |r: &ImageScore| r.albedo_scaled),
    ] {
        let scores: Vec<ImageScores> = rows.iter().filter_map(pick).collect();
        if !scores.is_empty() {
            out.push(mean(group, scores, None));
        }
    }
    out
}

pub(super) fn cells(s: &ImageScores, digits: usize) -> [String; 3] {
    [format!("{:.digits$}", s.psnr), format!("{:.digits$}", s.foreground_psnr), format!("{:.4}", s.ssim)]
}

/// The columns of `metrics.csv`.
pub const METRICS_COLUMNS: [&str; 12] = [
    "image",
    "light",
    "group",
    "psnr",
    "foreground_psnr",
    "ssim",
    "albedo_psnr",
    "albedo_foreground_psnr",
    "albedo_ssim",
    "error_outside_mask",
    "error_along_silhouette",
    "error_inside",
];

pub(super) fn metrics_csv(rows: &[ImageScore]) -> String {
    let rows = rows.iter().map(|r| {
        let albedo = r.albedo.map(|a| cells(&a, 3)).unwrap_or_else(|| [String::new(), String::new(), String::new()]);
        let shares = r.error_share.map(|e| share_cells(&e, 4)).unwrap_or_else(|| [String::new(), String::new(), String::new()]);
        let mut row = vec![r.image.clone(), r.light.clone(), r.group.to_string()];
        row.extend(cells(&r.scores, 3));
        row.extend(albedo);
        row.extend(shares);
        row
    });
    crate::table::to_csv(&METRICS_COLUMNS, rows)
}

/// An `ErrorRegions` of shares as three cells: outside the mask, along the silhouette, inside.
pub(super) fn share_cells(e: &ErrorRegions, digits: usize) -> [String; 3] {
    [e.outside, e.silhouette, e.inside].map(|v| format!("{v:.digits$}"))
}

pub(super) fn metrics_markdown(rows: &[ImageScore], groups: &[GroupScores]) -> String {
    let mut md = String::from(
        "## Test images (sRGB 8-bit; foreground = ground-truth mask or any rendered pixel)\n\n| group | images | PSNR (dB) | foreground PSNR (dB) | SSIM |\n|---|---|---|---|---|\n",
    );
    for g in groups {
        md += &format!("| {} | {} | {} |\n", g.group, g.images, cells(&g.scores, 2).join(" | "));
    }
    if groups.iter().any(|g| g.error_share.is_some()) {
        md += "\n## Where the error lies (share of each group's squared error, sRGB 8-bit)\n\nOutside the mask: the render draws body (or a halo) where the truth has none; along the silhouette: mask pixels beside the background; inside: the rest of the body. Most of it outside and along the silhouette is a shape error, most of it inside a colour or shading error.\n\n| group | outside the mask | along the silhouette | inside |\n|---|---|---|---|\n";
        for g in groups {
            if let Some(e) = &g.error_share {
                md += &format!("| {} | {} |\n", g.group, e.percentages().join(" | "));
            }
        }
    }
    md += "\n| image | light | group | PSNR (dB) | foreground PSNR (dB) | SSIM | albedo PSNR (dB) | albedo foreground PSNR (dB) | albedo SSIM |\n|---|---|---|---|---|---|---|---|---|\n";
    for r in rows {
        let albedo = r.albedo.map(|a| cells(&a, 2)).unwrap_or_else(|| ["-".into(), "-".into(), "-".into()]);
        md += &format!("| {} | {} | {} | {} | {} |\n", r.image, r.light, r.group, cells(&r.scores, 2).join(" | "), albedo.join(" | "));
    }
    md
}

/// The evaluation's figures: each group's PSNR, foreground PSNR and SSIM under flat keys
/// (`novel_pose_psnr`, ...), the groups, the albedo's scale and every image's scores.
pub(super) fn evaluation_json(rows: &[ImageScore], groups: &[GroupScores], albedo_scale: glam::DVec3) -> serde_json::Map<String, Value> {
    let group = |g: &str| groups.iter().find(|m| m.group == g);
    let field = |g: &str, pick: fn(&ImageScores) -> f64| group(g).map(|m| json!(pick(&m.scores))).unwrap_or(json!(null));
    let mut evaluation = serde_json::Map::new();
    for (key, g) in [
        ("novel_pose", "novel pose"),
        ("novel_view", "novel view"),
        ("relit", "relit"),
        ("albedo", "albedo"),
        ("relit_scaled", "relit, per-channel scaled"),
        ("albedo_scaled", "albedo, per-channel scaled"),
    ] {
        evaluation.insert(format!("{key}_psnr"), field(g, |s| s.psnr));
        evaluation.insert(format!("{key}_foreground_psnr"), field(g, |s| s.foreground_psnr));
        evaluation.insert(format!("{key}_ssim"), field(g, |s| s.ssim));
    }
    evaluation.insert("groups".into(), json!(groups));
    evaluation.insert("albedo_scale".into(), json!(albedo_scale.to_array()));
    evaluation.insert("images".into(), json!(rows));
    evaluation
}

/// `metrics.md`'s section of the surface against the scene's meshes (empty without meshes).
pub(super) fn geometry_markdown(frames: &[Value]) -> String {
    if frames.is_empty() {
        return String::new();
    }
    let mut markdown = "\n## Geometry against the scene's meshes\n\n| frame | accuracy (mm) | completeness (mm) | Chamfer (mm) | normal angle (deg) | within 2 cm | seen | seen within 2 cm | closed |\n|---|---|---|---|---|---|---|---|---|\n".to_string();
    for f in frames {
        let mm = |key: &str| f[key].as_f64().map(|v| format!("{:.2}", v * 1e3)).unwrap_or_else(|| "-".into());
        let percent = |key: &str| f[key].as_f64().map(|v| format!("{:.1}%", v * 100.0)).unwrap_or_else(|| "-".into());
        markdown += &format!(
            "| {} | {} | {} | {} | {:.2} | {:.1}% | {} | {} | {} |\n",
            f["frame"],
            mm("accuracy"),
            mm("completeness"),
            mm("chamfer"),
            f["normal_angle"].as_f64().unwrap_or(f64::NAN),
            f["within_2cm"].as_f64().unwrap_or(f64::NAN) * 100.0,
            percent("seen"),
            percent("seen_within_2cm"),
            if f["closed"].as_bool() == Some(true) { "yes" } else { "no" }
        );
    }
    markdown
}
