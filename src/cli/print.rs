//! What the command line prints of a result: lights as a person reads them, an evaluation's
//! scores, an exported avatar.

use std::path::Path;

/// What `export-avatar` wrote, and its skinning check.
pub fn print_avatar(out: &Path, e: &crate::export::AvatarExported) {
    println!("wrote {}: {} vertices, {} triangles, {} joints, {} animation frames", out.display(), e.vertices, e.triangles, e.bones, e.frames);
    if let Some((frame, s)) = e.skin_check {
        println!(
            "skinning check in frame {frame}: the skinned mesh lies {:.1} mm (mean) from the surface meshed in that frame, which lies {:.1} mm from it",
            s.accuracy * 1e3,
            s.completeness * 1e3
        );
    }
}

/// A fitted light (`fit.json`'s `light`) as a person reads it: a sun's direction as azimuth
/// (degrees from +Z toward +X, about the up axis +Y) and elevation, a point light's position in
/// metres, colours to 3 digits.
pub fn describe_light(light: &serde_json::Value) -> String {
    let triple = |key: &str| -> Option<[f64; 3]> {
        let v = light[key].as_array()?;
        Some([v.first()?.as_f64()?, v.get(1)?.as_f64()?, v.get(2)?.as_f64()?])
    };
    let rgb = |key: &str| triple(key).map(|c| format!("{:.3} {:.3} {:.3}", c[0], c[1], c[2])).unwrap_or_else(|| "-".into());
    match light["type"].as_str() {
        Some("directional") => {
            let Some([x, y, z]) = triple("direction") else { return "a sun of unknown direction".into() };
            let length = (x * x + y * y + z * z).sqrt().max(1e-12);
            let elevation = (y / length).clamp(-1.0, 1.0).asin().to_degrees();
            let azimuth = x.atan2(z).to_degrees();
            format!("sun at azimuth {azimuth:.1} degrees, elevation {elevation:.1} degrees; irradiance {}, ambient {}", rgb("irradiance"), rgb("ambient"))
        }
        Some("point") => {
            let position = triple("position").map(|p| format!("({:.3}, {:.3}, {:.3}) m", p[0], p[1], p[2])).unwrap_or_else(|| "unknown".into());
            format!("point light at {position}; intensity {}, ambient {}", rgb("intensity"), rgb("ambient"))
        }
        Some("uniform") => "uniform light (no direction to fit)".into(),
        _ => light.to_string(),
    }
}

pub fn print_evaluation(evaluation: &serde_json::Value) {
    for (key, what) in [("novel_pose", "novel pose"), ("novel_view", "novel view"), ("relit", "relit"), ("albedo", "albedo")] {
        if let Some(p) = evaluation[format!("{key}_psnr")].as_f64() {
            let foreground = evaluation[format!("{key}_foreground_psnr")].as_f64().unwrap_or(f64::NAN);
            let ssim = evaluation[format!("{key}_ssim")].as_f64().unwrap_or(f64::NAN);
            println!("{what}: PSNR {p:.2} dB, foreground {foreground:.2} dB, SSIM {ssim:.4}");
        }
    }
    // The fitted surface against the scene's ground-truth meshes, averaged over the frames meshed.
    let frames = evaluation["geometry"].as_array().cloned().unwrap_or_default();
    let mean = |key: &str| {
        let values: Vec<f64> = frames.iter().filter_map(|f| f[key].as_f64()).collect();
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    if let (Some(accuracy), Some(completeness), Some(chamfer)) = (mean("accuracy"), mean("completeness"), mean("chamfer")) {
        let closed = frames.iter().filter(|f| f["closed"].as_bool() == Some(true)).count();
        println!(
            "surface against the scene's meshes ({} frames): accuracy {:.1} mm, completeness {:.1} mm, Chamfer {:.1} mm, {:.1}% within 2 cm ({:.1}% of what the training images saw), {closed} of {} closed",
            frames.len(),
            accuracy * 1e3,
            completeness * 1e3,
            chamfer * 1e3,
            mean("within_2cm").unwrap_or(f64::NAN) * 100.0,
            mean("seen_within_2cm").unwrap_or(f64::NAN) * 100.0,
            frames.len()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::describe_light;
    use serde_json::json;

    #[test]
    fn a_light_is_described_in_degrees_and_three_digit_colours() {
        let sun = |d: [f64; 3]| json!({"type": "directional", "direction": d, "irradiance": [0.30000007152557373, 1, 2], "ambient": [0.25, 0.25, 0.25]});
        assert_eq!(
            describe_light(&sun([0.0, 0.0, 1.0])),
            "sun at azimuth 0.0 degrees, elevation 0.0 degrees; irradiance 0.300 1.000 2.000, ambient 0.250 0.250 0.250"
        );
        assert!(describe_light(&sun([1.0, 0.0, 0.0])).contains("azimuth 90.0 degrees, elevation 0.0"));
        assert!(describe_light(&sun([0.0, 2.0, 0.0])).contains("elevation 90.0"));
        assert!(describe_light(&sun([-1.0, 1.0, -1.0])).contains("azimuth -135.0 degrees, elevation 35.3"));
        let lamp = json!({"type": "point", "position": [1, 2.5, -0.25], "intensity": [8, 8, 8], "ambient": [0, 0, 0]});
        assert!(describe_light(&lamp).starts_with("point light at (1.000, 2.500, -0.250) m; intensity 8.000"));
    }
}
