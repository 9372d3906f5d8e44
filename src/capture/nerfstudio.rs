//! nerfstudio's `transforms.json`: reading a capture's cameras (OpenGL camera axes, intrinsics
//! shared or per frame, PINHOLE / SIMPLE_PINHOLE / OPENCV) and writing one from a scene.
//!
//! A frame's `transform_matrix` maps OpenGL camera axes (+X right, +Y up, looking down -Z) to the
//! world; scene/1 cameras use OpenCV axes (+Y down, looking down +Z): the two differ by a half
//! turn about the camera's X axis. Pixel coordinates are continuous with the top-left pixel's
//! centre at (0.5, 0.5) in both.

use super::{CaptureImage, Distortion, Intrinsics};
use crate::scene::json::At;
use crate::scene::{Camera, Scene, SceneError, Split};
use glam::{DMat4, DVec4};
use serde_json::{json, Value};
use std::path::Path;

/// OpenGL camera axes to OpenCV's (and back: its own inverse).
pub fn flip_yz() -> DMat4 {
    DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0))
}

/// Every image `transforms.json` lists, in order, with its intrinsics, its camera-to-world in
/// OpenCV axes (capture units), its time, its mask and its split.
pub fn read(file: &Path) -> Result<Vec<CaptureImage>, SceneError> {
    let value = crate::scene::json::parse(&crate::scene::read_capped(file)?, file)?;
    let root = At::root(&value, file);
    let dir = file.parent().unwrap_or(Path::new("."));
    let model = match root.opt_field("camera_model")? {
        Some(m) => m.str()?.to_string(),
        None => "OPENCV".to_string(),
    };
    let shared = intrinsics(&root, None, &model)?;
    let mut lists = SplitLists::read(&root)?;
    let mut images = Vec::new();
    for frame in root.field("frames")?.non_empty_array()? {
        let path_node = frame.field("file_path")?;
        let relative = path_node.str()?;
        let within = |node: &At| -> Result<std::path::PathBuf, SceneError> { super::inside(node.str()?).map_err(|e| node.error(e)) };
        let file_path = within(&path_node)?;
        let own = intrinsics(&frame, shared.as_ref(), &model)?;
        let (intrinsics, distortion) =
            own.or(shared.clone()).ok_or_else(|| frame.error("no intrinsics: fl_x, fl_y, cx, cy, w and h on the frame or the file"))?;
        let opengl = frame.field("transform_matrix")?.rigid_mat4()?;
        let split = lists.split_of(relative).map_err(|e| path_node.error(e))?;
        // The key: the path below `images/` (nerfstudio's folder for them), else below the file.
        let below = file_path.strip_prefix("images").ok().filter(|p| !p.as_os_str().is_empty()).unwrap_or(&file_path);
        images.push(CaptureImage {
            path: dir.join(&file_path),
            key: super::image_key(below),
            json_path: path_node.path.clone(),
            mask: frame.opt_field("mask_path")?.map(|m| within(&m).map(|p| dir.join(p))).transpose()?,
            intrinsics,
            distortion,
            camera_to_world: opengl * flip_yz(),
            time: frame.opt_field("time")?.map(|t| t.f64()).transpose()?,
            split,
        });
    }
    lists.each_names_a_frame()?;
    Ok(images)
}

/// The capture's `train_filenames`, `val_filenames` and `test_filenames`: which split each
/// frame's image is in. An entry and a frame's `file_path` name the same image when one is the
/// other's last parts (`c03/0001.png` names `images/c03/0001.png`, and so does an absolute
/// `/data/capture/images/c03/0001.png`, but `c00/0001.png` does not): multi-camera captures
/// often keep each camera's images in a folder of its own under the same file names.
struct SplitLists<'a> {
    /// Each list's split and entries, as their JSON nodes.
    lists: Vec<(Split, &'static str, Vec<At<'a>>)>,
    /// The entries by their last part, as path components with their list and place in it.
    by_name: std::collections::HashMap<String, Vec<(usize, usize, Vec<String>)>>,
    /// Which entries named a frame, per list (`each_names_a_frame`).
    used: Vec<Vec<bool>>,
}

const SPLIT_KEYS: [(&str, Split); 3] = [("train_filenames", Split::Train), ("val_filenames", Split::Val), ("test_filenames", Split::Test)];

/// A path's parts, without `.` and empty ones, with either separator.
fn parts(path: &str) -> Vec<String> {
    path.split(['/', '\\']).filter(|p| !p.is_empty() && *p != ".").map(str::to_string).collect()
}

impl<'a> SplitLists<'a> {
    fn read(root: &At<'a>) -> Result<SplitLists<'a>, SceneError> {
        let mut lists = Vec::new();
        let mut by_name: std::collections::HashMap<String, Vec<_>> = std::collections::HashMap::new();
        for (k, (key, split)) in SPLIT_KEYS.into_iter().enumerate() {
            let entries = match root.opt_field(key)? {
                Some(list) => list.array()?,
                None => Vec::new(),
            };
            for (e, entry) in entries.iter().enumerate() {
                let entry_parts = parts(entry.str()?);
                if let Some(last) = entry_parts.last() {
                    by_name.entry(last.clone()).or_default().push((k, e, entry_parts));
                }
            }
            lists.push((split, key, entries));
        }
        let used = lists.iter().map(|(_, _, e)| vec![false; e.len()]).collect();
        Ok(SplitLists { lists, by_name, used })
    }

    /// The split of the frame whose `file_path` is `path`: every image trains when no list is
    /// given; refused when the lists are given and none, or more than one, names it.
    fn split_of(&mut self, path: &str) -> Result<Split, String> {
        if self.lists.iter().all(|(_, _, entries)| entries.is_empty()) {
            return Ok(Split::Train);
        }
        let frame = parts(path);
        let mut naming: Vec<usize> = Vec::new();
        for (k, e, entry) in frame.last().and_then(|last| self.by_name.get(last)).into_iter().flatten() {
            if frame.ends_with(entry) || entry.ends_with(&frame) {
                self.used[*k][*e] = true;
                if !naming.contains(k) {
                    naming.push(*k);
                }
            }
        }
        naming.sort_unstable();
        match naming.as_slice() {
            [k] => Ok(self.lists[*k].0),
            [] => Err("listed in none of train_filenames, val_filenames and test_filenames".into()),
            _ => Err(format!(
                "listed in {}: each image is in one split (a test image that also trains scores the fit on what it has seen)",
                naming.iter().map(|&k| self.lists[k].1).collect::<Vec<_>>().join(" and ")
            )),
        }
    }

    /// Refuses an entry of a list that named no frame, naming it: a list that names an image the
    /// file does not hold has lost it, or names another capture's.
    fn each_names_a_frame(&self) -> Result<(), SceneError> {
        for ((_, _, entries), used) in self.lists.iter().zip(&self.used) {
            if let Some(entry) = entries.iter().zip(used).find(|(_, u)| !**u).map(|(entry, _)| entry) {
                return Err(entry.error(format!("{:?} names none of the frames' file_path", entry.str()?)));
            }
        }
        Ok(())
    }
}

/// The intrinsics `node` states (`None` when it states none of them), each missing one taken
/// from `shared`; the camera model `node`'s or else `model`.
fn intrinsics(node: &At, shared: Option<&(Intrinsics, Distortion)>, model: &str) -> Result<Option<(Intrinsics, Distortion)>, SceneError> {
    let keys = ["fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "p1", "p2"];
    let states_any = keys.iter().map(|k| node.opt_field(k)).collect::<Result<Vec<_>, _>>()?.iter().any(Option::is_some);
    if !states_any {
        return Ok(None);
    }
    let base = shared.map(|s| s.0.clone());
    let number = |key: &str, fallback: Option<f64>| -> Result<f64, SceneError> {
        match node.opt_field(key)? {
            Some(v) => v.f64(),
            None => fallback.ok_or_else(|| node.error(format!("{key}: missing"))),
        }
    };
    // An image's size in pixels: a whole number (128.5 is no size), and no more than an image
    // umbra reads may have.
    let whole = |key: &str, v: f64| -> Result<usize, SceneError> {
        match v.fract() == 0.0 && (1.0..=crate::imageio::MAX_PIXELS as f64).contains(&v) {
            true => Ok(v as usize),
            false => Err(node.error(format!("{key} {v}: an image's size is a whole number of pixels"))),
        }
    };
    let model = match node.opt_field("camera_model")? {
        Some(m) => m.str()?.to_string(),
        None => model.to_string(),
    };
    let fl_x = number("fl_x", base.as_ref().map(|b| b.fx))?;
    let fl_y = match model.as_str() {
        "SIMPLE_PINHOLE" => number("fl_y", Some(fl_x))?,
        _ => number("fl_y", base.as_ref().map(|b| b.fy))?,
    };
    let intrinsics = Intrinsics {
        fx: fl_x,
        fy: fl_y,
        cx: number("cx", base.as_ref().map(|b| b.cx))?,
        cy: number("cy", base.as_ref().map(|b| b.cy))?,
        width: whole("w", number("w", base.as_ref().map(|b| b.width as f64))?)?,
        height: whole("h", number("h", base.as_ref().map(|b| b.height as f64))?)?,
    };
    if intrinsics.fx <= 0.0 || intrinsics.fy <= 0.0 || intrinsics.width == 0 || intrinsics.height == 0 {
        return Err(node.error(format!("fl_x, fl_y, w and h must be positive, found {intrinsics:?}")));
    }
    let coefficient =
        |key: &str, shared_value: f64| -> Result<f64, SceneError> { Ok(node.opt_field(key)?.map(|v| v.f64()).transpose()?.unwrap_or(shared_value)) };
    let previous = shared.map(|s| s.1.clone()).unwrap_or_default();
    let distortion = match model.as_str() {
        "PINHOLE" | "SIMPLE_PINHOLE" => Distortion { model, ..Distortion::default() },
        "OPENCV" => Distortion {
            k1: coefficient("k1", previous.k1)?,
            k2: coefficient("k2", previous.k2)?,
            k3: coefficient("k3", previous.k3)?,
            p1: coefficient("p1", previous.p1)?,
            p2: coefficient("p2", previous.p2)?,
            model,
        },
        other => {
            return Err(node
                .error(format!("camera_model {other:?} is not supported (PINHOLE, SIMPLE_PINHOLE or OPENCV; fisheye and equirectangular captures are not)")))
        }
    };
    if let Some(problem) = intrinsics.problem(&distortion) {
        return Err(node.error(problem));
    }
    Ok(Some((intrinsics, distortion)))
}

/// `scene`'s images `chosen` as nerfstudio's `transforms.json`, seen through `cameras` (one per
/// scene camera): cameras in OpenGL axes, positions in `units` per metre, each image's `time`
/// its frame's position times `frame_time`, `file_path` and `mask_path` as `name` gives them for
/// image `k`.
pub fn write(scene: &Scene, cameras: &[Camera], chosen: &[usize], units: f64, frame_time: f64, name: impl Fn(usize) -> (String, Option<String>)) -> Value {
    let frames: Vec<Value> = chosen
        .iter()
        .filter_map(|&k| {
            let view = &scene.views[k];
            let camera = cameras.get(view.camera)?;
            let mut opengl = camera.camera_to_world * flip_yz();
            opengl.w_axis = (opengl.w_axis.truncate() * units).extend(1.0);
            let rows: Vec<Vec<f64>> = (0..4).map(|r| opengl.row(r).to_array().to_vec()).collect();
            let (file_path, mask_path) = name(k);
            let mut frame = json!({
                "file_path": file_path,
                "transform_matrix": rows,
                "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
                "w": camera.width, "h": camera.height,
                "time": view.frame as f64 * frame_time,
            });
            if let Some(mask) = mask_path {
                frame["mask_path"] = json!(mask);
            }
            Some(frame)
        })
        .collect();
    let split_names = |split: Split| -> Vec<String> { chosen.iter().filter(|&&k| scene.views[k].split == split).map(|&k| name(k).0).collect() };
    json!({
        "camera_model": "PINHOLE",
        "frames": frames,
        "train_filenames": split_names(Split::Train),
        "val_filenames": split_names(Split::Val),
        "test_filenames": split_names(Split::Test),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lists(value: &Value) -> SplitLists<'_> {
        SplitLists::read(&At::root(value, Path::new("transforms.json"))).unwrap()
    }

    #[test]
    fn a_list_names_a_frame_by_its_whole_path_or_its_last_parts_never_by_a_shared_file_name() {
        // Each camera's images in a folder of its own, under the same file names.
        let value = json!({"train_filenames": ["images/c00/0001.png", "./images/c01/0001.png"], "test_filenames": ["c02/0001.png"]});
        let mut lists = lists(&value);
        assert_eq!(lists.split_of("images/c00/0001.png"), Ok(Split::Train));
        assert_eq!(lists.split_of("images/c01/0001.png"), Ok(Split::Train));
        assert_eq!(lists.split_of("images/c02/0001.png"), Ok(Split::Test), "c00's entry shares only the file name");
        // An entry written from elsewhere, whole, names the frame its last parts are.
        let written_whole = json!({"train_filenames": ["/data/capture/images/c00/0001.png"], "test_filenames": ["/data/capture/images/c01/0001.png"]});
        let mut absolute = self::lists(&written_whole);
        assert_eq!(absolute.split_of("images/c01/0001.png"), Ok(Split::Test));
        assert_eq!(absolute.split_of("c00/0001.png"), Ok(Split::Train));
        // A part of a name is no name.
        let bare_names = json!({"train_filenames": ["1.png"]});
        let mut bare = self::lists(&bare_names);
        assert!(bare.split_of("images/c00/0001.png").is_err());
        assert_eq!(bare.split_of("images/1.png"), Ok(Split::Train));
        // No lists: everything trains.
        assert_eq!(self::lists(&json!({})).split_of("images/a.png"), Ok(Split::Train));
    }

    #[test]
    fn an_image_in_two_lists_or_in_none_and_an_entry_naming_no_frame_are_refused() {
        let value = json!({"train_filenames": ["a.png", "b.png"], "test_filenames": ["images/b.png", "images/c.png"]});
        let root = At::root(&value, Path::new("transforms.json"));
        let mut lists = SplitLists::read(&root).unwrap();
        let both = lists.split_of("images/b.png").unwrap_err();
        assert!(both.contains("train_filenames and test_filenames"), "{both}");
        assert!(lists.split_of("images/d.png").unwrap_err().contains("listed in none"));
        assert_eq!(lists.split_of("images/a.png"), Ok(Split::Train));
        // images/c.png was never read: its entry names nothing.
        let unused = lists.each_names_a_frame().unwrap_err().to_string();
        assert!(unused.contains("test_filenames[1]") && unused.contains("images/c.png"), "{unused}");
        assert_eq!(lists.split_of("images/c.png"), Ok(Split::Test));
        assert!(lists.each_names_a_frame().is_ok());
    }
}
