//! COLMAP's text model: `cameras.txt` (`CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`; SIMPLE_PINHOLE,
//! PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV) and `images.txt` (per image `IMAGE_ID QW QX QY QZ TX
//! TY TZ CAMERA_ID NAME`, then a line of 2D points). A pose maps the world into the camera (OpenCV
//! axes, as scene/1's); pixel centres sit at +0.5 in both. An image's frame is the number in its
//! name; its file is `NAME` in the images folder.

use super::{input, CaptureImage, Distortion, ImportError, Intrinsics};
use crate::scene::Split;
use glam::{DMat3, DMat4, DQuat, DVec3};
use std::collections::BTreeMap;
use std::path::Path;

/// The numbers of a line, or an error naming the file and line.
fn numbers(words: &[&str], file: &Path, line: usize) -> Result<Vec<f64>, ImportError> {
    words
        .iter()
        .map(|w| w.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| input(file, format!("line {line}: expected a finite number, found {w:?}"))))
        .collect()
}

/// Each camera of `cameras.txt` by its id.
fn cameras(file: &Path) -> Result<BTreeMap<u64, (Intrinsics, Distortion)>, ImportError> {
    let text = crate::files::read_text(file, crate::files::SCENE_BYTES).map_err(|e| input(file, e.to_string()))?;
    let mut out = BTreeMap::new();
    for (n, line) in text.lines().enumerate().map(|(n, l)| (n + 1, l.trim())) {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        let [id, model, width, height, params @ ..] = words.as_slice() else {
            return Err(input(file, format!("line {n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")));
        };
        let id: u64 = id.parse().map_err(|_| input(file, format!("line {n}: camera id {id:?} is not a number")))?;
        let size =
            |w: &str| w.parse::<usize>().ok().filter(|v| *v > 0).ok_or_else(|| input(file, format!("line {n}: size {w:?} is not a positive whole number")));
        let (width, height) = (size(width)?, size(height)?);
        let p = numbers(params, file, n)?;
        let expected = match *model {
            "SIMPLE_PINHOLE" => 3,
            "PINHOLE" | "SIMPLE_RADIAL" => 4,
            "RADIAL" => 5,
            "OPENCV" => 8,
            other => {
                return Err(input(
                    file,
                    format!("line {n}: camera model {other:?} is not supported (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV)"),
                ))
            }
        };
        if p.len() != expected {
            return Err(input(file, format!("line {n}: {model} has {expected} parameters, found {}", p.len())));
        }
        let (fx, fy, cx, cy, k) = match *model {
            "PINHOLE" | "OPENCV" => (p[0], p[1], p[2], p[3], &p[4..]),
            _ => (p[0], p[0], p[1], p[2], &p[3..]),
        };
        if fx <= 0.0 || fy <= 0.0 {
            return Err(input(file, format!("line {n}: focal lengths must be positive, found {fx} and {fy}")));
        }
        let coefficient = |i: usize| k.get(i).copied().unwrap_or(0.0);
        let distortion = match *model {
            "OPENCV" => Distortion { model: model.to_string(), k1: k[0], k2: k[1], p1: k[2], p2: k[3], k3: 0.0 },
            _ => Distortion { model: model.to_string(), k1: coefficient(0), k2: coefficient(1), ..Distortion::default() },
        };
        let intrinsics = Intrinsics { fx, fy, cx, cy, width, height };
        if let Some(problem) = intrinsics.problem(&distortion) {
            return Err(input(file, format!("line {n}: camera {id}: {problem}")));
        }
        if out.insert(id, (intrinsics, distortion)).is_some() {
            return Err(input(file, format!("line {n}: a second camera {id}: each CAMERA_ID names one camera")));
        }
    }
    Ok(out)
}

/// Every image of the model in `dir` (`cameras.txt`, `images.txt`), its file in `images`.
/// A pose line is recognised by its fields, not by its place: a model written without the
/// lines of 2D points, or with some missing, reads whole; a line of points is taken as one only
/// right after a pose line.
pub fn read(dir: &Path, images: &Path) -> Result<Vec<CaptureImage>, ImportError> {
    let cameras = cameras(&dir.join("cameras.txt"))?;
    let file = dir.join("images.txt");
    let text = crate::files::read_text(&file, crate::files::SCENE_BYTES).map_err(|e| input(&file, e.to_string()))?;
    let mut out = Vec::new();
    let mut ids = std::collections::BTreeSet::new();
    // A line of 2D points may follow a pose line, and nothing else may be one.
    let mut after_pose = false;
    for (n, line) in text.lines().enumerate().map(|(n, l)| (n + 1, l.trim())) {
        let words: Vec<&str> = line.split_whitespace().collect();
        if words.is_empty() || line.starts_with('#') || (after_pose && is_points_line(&words)) {
            after_pose = false;
            continue;
        }
        after_pose = true;
        let (id, image) = pose_line(&words, &cameras, images, &file, n)?;
        if !ids.insert(id) {
            return Err(input(&file, format!("line {n}: a second image {id}: each IMAGE_ID names one image")));
        }
        out.push(image);
    }
    if out.is_empty() {
        return Err(input(&file, "lists no images"));
    }
    Ok(out)
}

/// Whether `words` are a line of 2D points: `X Y POINT3D_ID` triples, numbers all.
fn is_points_line(words: &[&str]) -> bool {
    words.len() % 3 == 0 && words.iter().all(|w| w.parse::<f64>().is_ok())
}

/// One image's pose line, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`: its id and image.
fn pose_line(
    words: &[&str],
    cameras: &BTreeMap<u64, (Intrinsics, Distortion)>,
    images: &Path,
    file: &Path,
    n: usize,
) -> Result<(u64, CaptureImage), ImportError> {
    if words.len() < 10 {
        return Err(input(file, format!("line {n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, or a line of 2D points (X Y POINT3D_ID ...)")));
    }
    let id: u64 = words[0].parse().map_err(|_| input(file, format!("line {n}: image id {:?} is not a whole number", words[0])))?;
    let v = numbers(&words[1..8], file, n)?;
    let camera: u64 = words[8].parse().map_err(|_| input(file, format!("line {n}: camera id {:?} is not a number", words[8])))?;
    let (intrinsics, distortion) = cameras.get(&camera).cloned().ok_or_else(|| input(file, format!("line {n}: camera {camera} is not in cameras.txt")))?;
    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]);
    if (q.length() - 1.0).abs() > 1e-3 {
        return Err(input(file, format!("line {n}: the rotation quaternion has length {:.4}, not 1", q.length())));
    }
    let rotation = DMat3::from_quat(q.normalize());
    let world_to_camera = DMat4::from_mat3_translation(rotation, DVec3::new(v[4], v[5], v[6]));
    let name = words[9..].join(" ");
    let relative = super::inside(&name).map_err(|e| input(file, format!("line {n}: NAME {e}")))?;
    let image = CaptureImage {
        path: images.join(&relative),
        key: super::image_key(&relative),
        json_path: format!("line {n} ({name})"),
        mask: None,
        intrinsics,
        distortion,
        camera_to_world: world_to_camera.inverse(),
        time: None,
        split: Split::Train,
    };
    Ok((id, image))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_camera_model_reads_its_parameters_in_colmaps_order() {
        let dir = std::env::temp_dir().join(format!("umbra-colmap-cameras-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("cameras.txt");
        let text = "# comment\n1 SIMPLE_PINHOLE 640 480 500 320 240\n2 PINHOLE 640 480 500 510 321 241\n3 SIMPLE_RADIAL 640 480 500 320 240 -0.1\n\
                    4 RADIAL 640 480 500 320 240 -0.1 0.02\n5 OPENCV 640 480 500 510 320 240 -0.1 0.02 0.001 -0.002\n";
        std::fs::write(&file, text).unwrap();
        let read = cameras(&file).unwrap();
        let (k, d) = &read[&2];
        assert_eq!((k.fx, k.fy, k.cx, k.cy, k.width, k.height), (500.0, 510.0, 321.0, 241.0, 640, 480));
        assert!(d.is_none());
        assert_eq!(read[&1].0.fy, 500.0);
        assert_eq!((read[&3].1.k1, read[&3].1.k2), (-0.1, 0.0));
        assert_eq!((read[&4].1.k1, read[&4].1.k2), (-0.1, 0.02));
        let opencv = &read[&5].1;
        assert_eq!((opencv.k1, opencv.k2, opencv.p1, opencv.p2, opencv.k3), (-0.1, 0.02, 0.001, -0.002, 0.0));
        std::fs::write(&file, "1 PINHOLE 640 480 500 320 240\n").unwrap();
        let err = cameras(&file).unwrap_err().to_string();
        assert!(err.contains("line 1: PINHOLE has 4 parameters, found 3"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
