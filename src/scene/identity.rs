//! Fingerprints: which scene a run was fitted on (its skeleton; its training data) and whether a
//! checkpoint file is the one that was written. FNV-1a 64 over a canonical byte stream: a
//! guard against mistakes (another scene, a corrupted file), not against an adversary.

use super::{Scene, Split};

/// The version `Scene::training_identity` writes before its hex.
pub const TRAINING_IDENTITY_VERSION: &str = "v2";

/// FNV-1a, 64 bits.
#[derive(Clone, Copy, Debug)]
pub struct Fingerprint(u64);

impl Default for Fingerprint {
    fn default() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
}

impl Fingerprint {
    pub fn bytes(mut self, bytes: &[u8]) -> Self {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
        self
    }

    pub fn number(self, v: f64) -> Self {
        self.bytes(&v.to_bits().to_le_bytes())
    }

    pub fn text(self, s: &str) -> Self {
        // The length first, so ("ab", "c") and ("a", "bc") differ.
        self.bytes(&(s.len() as u64).to_le_bytes()).bytes(s.as_bytes())
    }

    pub fn hex(self) -> String {
        format!("{:016x}", self.0)
    }
}

/// The fingerprint of a file's bytes.
pub fn file_checksum(path: &std::path::Path) -> std::io::Result<String> {
    Ok(Fingerprint::default().bytes(&std::fs::read(path)?).hex())
}

impl Scene {
    /// The skeleton's bones (names, parents, lengths): a fitted avatar renders in any scene
    /// with this skeleton.
    pub fn skeleton_identity(&self) -> String {
        self.skeleton_fingerprint().hex()
    }

    /// The skeleton and every training image (its camera, pose, light and pixels): a fit
    /// resumes only on the data it started on. Each image is hashed on its own thread (its
    /// pixels that are not black, `lit_fingerprint`) and the images' fingerprints are hashed in
    /// order after the skeleton's; the text says its version
    /// (`TRAINING_IDENTITY_VERSION`), so a checkpoint of an earlier one is checked by that one.
    pub fn training_identity(&self) -> String {
        use rayon::prelude::*;
        let training: Vec<&super::View> = self.views.iter().filter(|v| v.split == Split::Train).collect();
        // Each plate hashed once, however many images share it.
        let mut plates: Vec<&std::sync::Arc<crate::silhouette::Plate>> = Vec::new();
        for plate in training.iter().filter_map(|v| v.plate.as_ref()) {
            if !plates.iter().any(|p| std::sync::Arc::ptr_eq(p, plate)) {
                plates.push(plate);
            }
        }
        let plate_hashes: Vec<u64> = plates.par_iter().map(|plate| pixels_fingerprint(Fingerprint::default(), plate_pixels(plate)).0).collect();
        let plate_hash = |view: &super::View| {
            let plate = view.plate.as_ref()?;
            plates.iter().position(|p| std::sync::Arc::ptr_eq(p, plate)).map(|k| plate_hashes[k])
        };
        let views: Vec<u64> = training.par_iter().map(|view| self.lit_fingerprint(view, plate_hash(view))).collect();
        let f = views.iter().fold(self.skeleton_fingerprint(), |f, v| f.bytes(&v.to_le_bytes()));
        format!("{TRAINING_IDENTITY_VERSION}:{}", f.hex())
    }

    /// Whether `recorded` (a checkpoint's `training_data`) is this scene's training data:
    /// `current` is `training_identity`'s; a recorded identity without a version is the
    /// first one (every image hashed one after another in a single stream).
    pub fn is_training_identity(&self, recorded: &str, current: &str) -> bool {
        match recorded.split_once(':') {
            Some(_) => recorded == current,
            None => recorded == self.serial_training_identity(),
        }
    }

    /// The first training identity: the skeleton and every training image in one stream.
    fn serial_training_identity(&self) -> String {
        let training = self.views.iter().filter(|v| v.split == Split::Train);
        training.fold(self.skeleton_fingerprint(), |f, view| self.view_fingerprint(view, f)).hex()
    }

    /// One training image's fingerprint: its camera, pose and light as `view_fingerprint`
    /// hashes them, then each pixel that is not black, its index and its value (the black
    /// background says nothing a mask does not).
    fn lit_fingerprint(&self, view: &super::View, plate: Option<u64>) -> u64 {
        let f = pixels_fingerprint(self.view_header(view, Fingerprint::default()), view.colour.lit_pixels());
        // What lies behind the body when the image has a plate (its fingerprint): a scene
        // without plates keeps the identity it had.
        match plate {
            Some(hash) => f.text("plate").bytes(&hash.to_le_bytes()).0,
            None => f.0,
        }
    }

    /// `f` continued over a training image's camera, its frame's pose and its light.
    fn view_header(&self, view: &super::View, mut f: Fingerprint) -> Fingerprint {
        let camera = &self.cameras[view.camera];
        f = f.text(&camera.name).number(camera.fx).number(camera.fy).number(camera.cx).number(camera.cy);
        for v in camera.camera_to_world.to_cols_array() {
            f = f.number(v);
        }
        for m in &self.frames[view.frame].pose.bone_to_world {
            for v in m.to_cols_array() {
                f = f.number(v);
            }
        }
        f.text(&view.light)
    }

    /// `f` continued over one training image: its camera, its frame's pose, its light, its pixels.
    fn view_fingerprint(&self, view: &super::View, f: Fingerprint) -> Fingerprint {
        let mut f = self.view_header(view, f);
        for p in view.colour.pixels() {
            for c in p {
                f = f.bytes(&c.to_bits().to_le_bytes());
            }
        }
        f
    }

    fn skeleton_fingerprint(&self) -> Fingerprint {
        let mut f = Fingerprint::default();
        for bone in &self.skeleton.bones {
            f = f.text(&bone.name).number(bone.parent.map_or(-1.0, |p| p as f64)).number(bone.length);
        }
        f
    }
}

/// `f` continued over pixels given as (index, linear RGB).
fn pixels_fingerprint(mut f: Fingerprint, pixels: impl Iterator<Item = (usize, [f32; 3])>) -> Fingerprint {
    for (p, c) in pixels {
        f = f.bytes(&(p as u64).to_le_bytes());
        for v in c {
            f = f.bytes(&v.to_bits().to_le_bytes());
        }
    }
    f
}

/// A plate's known pixels as (index, linear RGB).
fn plate_pixels(plate: &crate::silhouette::Plate) -> impl Iterator<Item = (usize, [f32; 3])> + '_ {
    plate.colour.pixels.iter().copied().enumerate().filter(|(p, _)| plate.known.foreground[*p])
}
