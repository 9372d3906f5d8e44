//! Fingerprints: which scene a run was fitted on (its skeleton; its training data) and whether a
//! checkpoint file is the one that was written. FNV-1a 64 over a canonical byte stream: a
//! guard against mistakes (another scene, a corrupted file), not against an adversary.

use super::{Scene, Split};

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
    /// resumes only on the data it started on.
    pub fn training_identity(&self) -> String {
        let mut f = self.skeleton_fingerprint();
        for view in self.views.iter().filter(|v| v.split == Split::Train) {
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
            f = f.text(&view.light);
            for p in view.colour.pixels() {
                for c in p {
                    f = f.bytes(&c.to_bits().to_le_bytes());
                }
            }
        }
        f.hex()
    }

    fn skeleton_fingerprint(&self) -> Fingerprint {
        let mut f = Fingerprint::default();
        for bone in &self.skeleton.bones {
            f = f.text(&bone.name).number(bone.parent.map_or(-1.0, |p| p as f64)).number(bone.length);
        }
        f
    }
}
