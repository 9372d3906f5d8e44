//! The errors a real capture pipeline leaves, put into a synthetic capture at stated sizes
//! (`umbra synth --export nerfstudio --errors SPEC`), so that what they cost a fit, and what a
//! fit forgives, can be measured against the truth kept beside them. A tracker's: each training
//! frame's bone rotations off by a few degrees per Euler channel and its root by about a
//! centimetre. A segmenter's: each training mask a pixel too wide or too narrow, with blobs
//! added or cut on its edge. A calibration's: each camera turned and moved a little. A rig's:
//! each camera with its own gain and white balance. A codec's: JPEG. Test images, their frames
//! and their cameras stay exact.

use crate::imageio::{Mask, RgbImage};
use crate::random::Stream;
use glam::{DMat3, DMat4, DVec3};

/// The sizes of the errors (standard deviations of normal draws, pixels, counts); zero: none.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CaptureErrors {
    /// Each training frame's bone rotation, per Euler channel (degrees).
    #[serde(default)]
    pub joints: f64,
    /// Each training frame's root position, per axis (cm).
    #[serde(default)]
    pub root: f64,
    /// Each training mask grown or shrunk (the sign drawn per image) by this many pixels.
    #[serde(default)]
    pub masks: usize,
    /// Blobs of 2 pixels' radius added to or cut from each training mask's edge.
    #[serde(default)]
    pub blobs: usize,
    /// Each camera turned about each axis (degrees) ...
    #[serde(default)]
    pub camera_turn: f64,
    /// ... and moved along each (mm), for its training images.
    #[serde(default)]
    pub camera_move: f64,
    /// Each camera's gain (relative) ...
    #[serde(default)]
    pub gain: f64,
    /// ... times a white balance per channel (relative).
    #[serde(default)]
    pub white_balance: f64,
    /// Training plates as JPEG of this quality (1-100; 0: PNG).
    #[serde(default)]
    pub jpeg: u8,
}

/// The sizes a real pipeline leaves (`--errors real`): a tracker's 2.5 degrees and 1 cm, a
/// segmenter's pixel and two blobs, a calibration's 0.1 degrees and 3 mm, a rig's 6% gain and
/// 3% white balance, JPEG at quality 88.
pub const REAL: CaptureErrors =
    CaptureErrors { joints: 2.5, root: 1.0, masks: 1, blobs: 2, camera_turn: 0.1, camera_move: 3.0, gain: 0.06, white_balance: 0.03, jpeg: 88 };

/// The radius of a blob (pixels).
const BLOB_RADIUS: i64 = 2;

impl CaptureErrors {
    /// Reads `real`, or `real,` followed by changes, or `key=value,...` from none
    /// (`joints=2.5,root=1,masks=1,blobs=2,camera_turn=0.1,camera_move=3,gain=0.06,white_balance=0.03,jpeg=88`).
    pub fn parse(text: &str) -> Result<CaptureErrors, String> {
        let mut errors = CaptureErrors::default();
        for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            if part == "real" {
                errors = REAL;
                continue;
            }
            let (key, value) = part.split_once('=').ok_or_else(|| format!("{part:?}: expected `real` or KEY=VALUE"))?;
            let number = value.trim().parse::<f64>().ok().filter(|v| v.is_finite() && *v >= 0.0).ok_or_else(|| format!("{key}={value}: a number >= 0"))?;
            let whole = || (number.fract() == 0.0 && number <= 1000.0).then_some(number as usize).ok_or_else(|| format!("{key}={value}: a whole number"));
            match key.trim() {
                "joints" => errors.joints = number,
                "root" => errors.root = number,
                "masks" => errors.masks = whole()?,
                "blobs" => errors.blobs = whole()?,
                "camera_turn" => errors.camera_turn = number,
                "camera_move" => errors.camera_move = number,
                "gain" => errors.gain = number,
                "white_balance" => errors.white_balance = number,
                "jpeg" => {
                    errors.jpeg = whole()
                        .and_then(|q| u8::try_from(q).ok().filter(|q| *q <= 100).ok_or_else(|| format!("jpeg={value}: a quality from 1 to 100, 0 for PNG")))?
                }
                other => {
                    return Err(format!(
                        "{other:?}: not an error of a capture (joints, root, masks, blobs, camera_turn, camera_move, gain, white_balance, jpeg)"
                    ))
                }
            }
        }
        if text.trim().is_empty() {
            return Err("an empty spec: give `real` or KEY=VALUE,...".into());
        }
        let within = [
            (errors.joints, 45.0),
            (errors.camera_turn, 45.0),
            (errors.root, 100.0),
            (errors.camera_move, 1000.0),
            (errors.gain, 1.0),
            (errors.white_balance, 1.0),
            (errors.masks as f64, 16.0),
            (errors.blobs as f64, 100.0),
        ];
        if within.iter().any(|(v, most)| v > most) {
            return Err(format!(
                "{text:?}: no capture's errors are that large (at most 45 degrees, 100 cm at the root, 1000 mm for a camera, 1 in gain or white balance, 16 pixels of mask, 100 blobs)"
            ));
        }
        Ok(errors)
    }

    pub fn is_none(&self) -> bool {
        *self == CaptureErrors::default()
    }
}

/// One normal draw (Box-Muller) of standard deviation `sd`.
fn normal(stream: &mut Stream, sd: f64) -> f64 {
    if sd == 0.0 {
        return 0.0;
    }
    let (u, v) = (stream.uniform().max(1e-300), stream.uniform());
    sd * (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
}

/// A rotation by three normal draws of `degrees`, one per axis (X, then Y, then Z).
fn turn(stream: &mut Stream, degrees: f64) -> DMat3 {
    let [x, y, z] = [(); 3].map(|_| normal(stream, degrees).to_radians());
    DMat3::from_rotation_z(z) * DMat3::from_rotation_y(y) * DMat3::from_rotation_x(x)
}

/// A pose as a tracker leaves it: each bone's rotation in its parent's frame turned by
/// `errors.joints` per channel, the root moved by `errors.root` (cm) per axis; each bone's head
/// stays where its parent's frame holds it (the skeleton's offsets are kept).
pub fn tracked_pose(skeleton: &crate::skeleton::Skeleton, bone_to_world: &[DMat4], errors: &CaptureErrors, stream: &mut Stream) -> Vec<DMat4> {
    let mut out: Vec<DMat4> = Vec::with_capacity(bone_to_world.len());
    for (b, bone) in skeleton.bones.iter().enumerate() {
        let wrong = DMat4::from_mat3(turn(stream, errors.joints));
        out.push(match bone.parent {
            Some(p) => out[p] * (bone_to_world[p].inverse() * bone_to_world[b]) * wrong,
            None => {
                let moved = DVec3::new(normal(stream, errors.root), normal(stream, errors.root), normal(stream, errors.root)) / 100.0;
                DMat4::from_translation(moved) * bone_to_world[b] * wrong
            }
        });
    }
    out
}

/// A camera as a calibration leaves it: turned about its centre and moved (`camera_turn`
/// degrees, `camera_move` mm per axis).
pub fn calibrated_camera(camera_to_world: DMat4, errors: &CaptureErrors, stream: &mut Stream) -> DMat4 {
    let moved = DVec3::new(normal(stream, errors.camera_move), normal(stream, errors.camera_move), normal(stream, errors.camera_move)) / 1000.0;
    let mut out = camera_to_world * DMat4::from_mat3(turn(stream, errors.camera_turn));
    out.w_axis += moved.extend(0.0);
    out
}

/// A camera's colour as a rig leaves it: per channel, a gain times a white balance.
pub fn camera_colour(errors: &CaptureErrors, stream: &mut Stream) -> [f32; 3] {
    let gain = 1.0 + normal(stream, errors.gain);
    [(); 3].map(|_| ((gain * (1.0 + normal(stream, errors.white_balance))).max(0.05)) as f32)
}

/// A plate in a camera's colour.
pub fn coloured(plate: &RgbImage, colour: [f32; 3]) -> RgbImage {
    RgbImage { width: plate.width, height: plate.height, pixels: plate.pixels.iter().map(|p| [0, 1, 2].map(|c| p[c] * colour[c])).collect() }
}

/// A mask as a segmenter leaves it: grown or shrunk (the sign drawn) by `errors.masks`
/// pixels, then `errors.blobs` disks of 2 pixels' radius, each centred on a pixel of the edge,
/// added or cut (drawn).
pub fn segmented_mask(mask: &Mask, errors: &CaptureErrors, stream: &mut Stream) -> Mask {
    let grow = stream.uniform() < 0.5;
    let mut out = mask.clone();
    for _ in 0..errors.masks {
        out = step(&out, grow);
    }
    let edge: Vec<usize> = (0..out.foreground.len()).filter(|&p| out.foreground[p] && neighbours(&out, p).any(|q| !out.foreground[q])).collect();
    let mut pixels: Vec<bool> = out.foreground.iter().copied().collect();
    for _ in 0..errors.blobs {
        if edge.is_empty() {
            break;
        }
        let centre = edge[stream.below(edge.len())];
        let add = stream.uniform() < 0.5;
        let (cx, cy) = ((centre % out.width) as i64, (centre / out.width) as i64);
        for dy in -BLOB_RADIUS..=BLOB_RADIUS {
            for dx in -BLOB_RADIUS..=BLOB_RADIUS {
                let (x, y) = (cx + dx, cy + dy);
                if dx * dx + dy * dy <= BLOB_RADIUS * BLOB_RADIUS && (0..out.width as i64).contains(&x) && (0..out.height as i64).contains(&y) {
                    pixels[y as usize * out.width + x as usize] = add;
                }
            }
        }
    }
    Mask { foreground: pixels.into(), ..out }
}

/// The four neighbours of pixel `p` inside the mask's image.
fn neighbours(mask: &Mask, p: usize) -> impl Iterator<Item = usize> + '_ {
    let (x, y, w, h) = (p % mask.width, p / mask.width, mask.width, mask.height);
    [(x > 0).then(|| p - 1), (x + 1 < w).then(|| p + 1), (y > 0).then(|| p - w), (y + 1 < h).then(|| p + w)].into_iter().flatten()
}

/// The mask grown (a pixel with a foreground neighbour joins) or shrunk (a pixel with a
/// background neighbour leaves) by one pixel.
fn step(mask: &Mask, grow: bool) -> Mask {
    let foreground = (0..mask.foreground.len())
        .map(|p| match grow {
            true => mask.foreground[p] || neighbours(mask, p).any(|q| mask.foreground[q]),
            false => mask.foreground[p] && neighbours(mask, p).all(|q| mask.foreground[q]),
        })
        .collect();
    Mask { width: mask.width, height: mask.height, foreground }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_read_as_written_and_nonsense_is_refused() {
        assert_eq!(CaptureErrors::parse("real").unwrap(), REAL);
        let changed = CaptureErrors::parse("real, jpeg=0, joints=5").unwrap();
        assert_eq!((changed.jpeg, changed.joints, changed.root), (0, 5.0, 1.0));
        assert_eq!(CaptureErrors::parse("masks=2").unwrap(), CaptureErrors { masks: 2, ..CaptureErrors::default() });
        for bad in [
            "",
            "joints",
            "joints=-1",
            "masks=1.5",
            "jpeg=101",
            "elbows=3",
            "joints=nan",
            "gain=2",
            "root=1e39",
            "camera_move=18446744073709551616",
            "masks=0.5e3",
        ] {
            assert!(CaptureErrors::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn normal_draws_have_the_stated_spread_and_masks_move_by_a_pixel() {
        let mut stream = Stream::new(3, 1, 2);
        let draws: Vec<f64> = (0..20000).map(|_| normal(&mut stream, 2.5)).collect();
        let mean = draws.iter().sum::<f64>() / draws.len() as f64;
        let sd = (draws.iter().map(|d| (d - mean) * (d - mean)).sum::<f64>() / draws.len() as f64).sqrt();
        assert!(mean.abs() < 0.06 && (sd - 2.5).abs() < 0.06, "mean {mean}, sd {sd}");
        // A 10 x 10 square in 20 x 20: grown, 10 x 10 plus its 40-pixel ring; shrunk, 8 x 8.
        let square = Mask { width: 20, height: 20, foreground: (0..400).map(|p| (5..15).contains(&(p % 20)) && (5..15).contains(&(p / 20))).collect() };
        let count = |m: &Mask| m.foreground.iter().filter(|&&f| f).count();
        assert_eq!(count(&step(&square, true)), 140);
        assert_eq!(count(&step(&square, false)), 64);
    }
}
