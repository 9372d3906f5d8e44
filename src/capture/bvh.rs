//! BVH motion: reading any BVH (any joint names, any channel order, root translation, End Sites,
//! position channels on any joint), forward kinematics, and writing a skeleton's frames as a BVH.
//!
//! A joint's frame in its parent's: translated by its `OFFSET` (or, when it has position
//! channels, by their values instead, as Blender and most tools read them), then rotated by its
//! rotation channels in the order the file lists them (`Zrotation Xrotation Yrotation` is
//! `Rz * Rx * Ry`), in degrees.

use glam::{DMat3, DMat4, DVec3};
use std::path::{Path, PathBuf};

/// One degree of freedom a joint's frame line carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channel {
    Xposition,
    Yposition,
    Zposition,
    Xrotation,
    Yrotation,
    Zrotation,
}

impl Channel {
    fn parse(word: &str) -> Option<Channel> {
        Some(match word.to_ascii_lowercase().as_str() {
            "xposition" => Channel::Xposition,
            "yposition" => Channel::Yposition,
            "zposition" => Channel::Zposition,
            "xrotation" => Channel::Xrotation,
            "yrotation" => Channel::Yrotation,
            "zrotation" => Channel::Zrotation,
            _ => return None,
        })
    }

    fn is_position(self) -> bool {
        matches!(self, Channel::Xposition | Channel::Yposition | Channel::Zposition)
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Joint {
    pub name: String,
    /// An earlier joint (the file lists parents before children).
    pub parent: Option<usize>,
    /// Where the joint sits in its parent's frame at rest (file units).
    pub offset: DVec3,
    pub channels: Vec<Channel>,
    /// A leaf's End Site, in the joint's frame.
    pub end_site: Option<DVec3>,
}

/// A BVH clip: the joints and, per frame, every channel's value in the joints' order.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    pub joints: Vec<Joint>,
    /// Seconds between frames.
    pub frame_time: f64,
    pub frames: Vec<Vec<f64>>,
}

#[derive(Debug, thiserror::Error)]
#[error("{}: line {line}: {message}", file.display())]
pub struct BvhError {
    pub file: PathBuf,
    pub line: usize,
    pub message: String,
}

/// Reads the BVH at `path` (bounded like every text umbra reads).
pub fn read(path: &Path) -> Result<Motion, BvhError> {
    let text = crate::files::read_text(path, crate::files::SCENE_BYTES).map_err(|e| BvhError { file: path.to_path_buf(), line: 0, message: e.to_string() })?;
    parse(&text, path)
}

/// The words of a BVH with their line numbers.
struct Words<'a> {
    words: Vec<(usize, &'a str)>,
    at: usize,
    file: &'a Path,
}

impl<'a> Words<'a> {
    fn new(text: &'a str, file: &'a Path) -> Self {
        let words = text.lines().enumerate().flat_map(|(n, line)| line.split_whitespace().map(move |w| (n + 1, w))).collect();
        Self { words, at: 0, file }
    }

    fn line(&self) -> usize {
        self.words.get(self.at).or(self.words.last()).map(|w| w.0).unwrap_or(0)
    }

    fn error(&self, message: impl Into<String>) -> BvhError {
        BvhError { file: self.file.to_path_buf(), line: self.line(), message: message.into() }
    }

    fn next(&mut self, what: &str) -> Result<&'a str, BvhError> {
        let word = self.words.get(self.at).map(|w| w.1).ok_or_else(|| self.error(format!("the file ends where {what} was expected")))?;
        self.at += 1;
        Ok(word)
    }

    fn peek(&self) -> Option<&'a str> {
        self.words.get(self.at).map(|w| w.1)
    }

    fn keyword(&mut self, word: &str) -> Result<(), BvhError> {
        let found = self.next(word)?;
        if !found.eq_ignore_ascii_case(word) {
            self.at -= 1;
            return Err(self.error(format!("expected {word}, found {found:?}")));
        }
        Ok(())
    }

    fn number(&mut self, what: &str) -> Result<f64, BvhError> {
        let word = self.next(what)?;
        match word.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => {
                self.at -= 1;
                Err(self.error(format!("{what}: expected a finite number, found {word:?}")))
            }
        }
    }

    fn vector(&mut self, what: &str) -> Result<DVec3, BvhError> {
        Ok(DVec3::new(self.number(what)?, self.number(what)?, self.number(what)?))
    }
}

/// The most joints and frames a clip may hold (a hostile header cannot allocate without bound).
const MAX_JOINTS: usize = 1024;
const MAX_CHANNELS: usize = 6;

/// Parses BVH text; errors name `file` and the line.
pub fn parse(text: &str, file: &Path) -> Result<Motion, BvhError> {
    let mut words = Words::new(text, file);
    words.keyword("HIERARCHY")?;
    words.keyword("ROOT")?;
    let mut joints = Vec::new();
    joint(&mut words, None, &mut joints)?;
    if words.peek().is_some_and(|w| w.eq_ignore_ascii_case("ROOT")) {
        return Err(words.error("a second ROOT: umbra reads clips of one skeleton"));
    }
    words.keyword("MOTION")?;
    words.keyword("Frames:")?;
    let count = words.number("the frame count")?;
    if count < 1.0 || count.fract() != 0.0 {
        return Err(words.error(format!("Frames: expected a positive whole number, found {count}")));
    }
    words.keyword("Frame")?;
    words.keyword("Time:")?;
    let frame_time = words.number("the frame time")?;
    if frame_time <= 0.0 {
        return Err(words.error(format!("Frame Time: expected seconds > 0, found {frame_time}")));
    }
    let per_frame: usize = joints.iter().map(|j| j.channels.len()).sum();
    if per_frame == 0 {
        return Err(words.error("no joint has a channel: the clip holds no motion"));
    }
    let remaining = words.words.len() - words.at;
    // Checked before anything is allocated for the frames: a header may claim any count.
    if (count as usize).checked_mul(per_frame) != Some(remaining) {
        return Err(
            words.error(format!("the MOTION section holds {remaining} values; {count} frames of {per_frame} channels need {}", count * per_frame as f64))
        );
    }
    let mut frames = Vec::with_capacity(count as usize);
    for k in 0..count as usize {
        frames.push((0..per_frame).map(|_| words.number(&format!("frame {k}'s channel value"))).collect::<Result<Vec<f64>, _>>()?);
    }
    Ok(Motion { joints, frame_time, frames })
}

/// Reads one joint's block (its name is next) and its children's.
fn joint(words: &mut Words, parent: Option<usize>, joints: &mut Vec<Joint>) -> Result<(), BvhError> {
    if joints.len() >= MAX_JOINTS {
        return Err(words.error(format!("more than {MAX_JOINTS} joints")));
    }
    let name = words.next("a joint's name")?.to_string();
    if joints.iter().any(|j: &Joint| j.name == name) {
        return Err(words.error(format!("a second joint named {name:?}")));
    }
    words.keyword("{")?;
    words.keyword("OFFSET")?;
    let offset = words.vector("OFFSET")?;
    words.keyword("CHANNELS")?;
    let count = words.number("the channel count")?;
    if !(0.0..=MAX_CHANNELS as f64).contains(&count) || count.fract() != 0.0 {
        return Err(words.error(format!("CHANNELS: expected 0 to {MAX_CHANNELS}, found {count}")));
    }
    let mut channels = Vec::new();
    for _ in 0..count as usize {
        let word = words.next("a channel")?;
        let channel = Channel::parse(word).ok_or_else(|| words.error(format!("unknown channel {word:?} (expected X/Y/Z position or rotation)")))?;
        if channels.contains(&channel) {
            return Err(words.error(format!("channel {word} twice")));
        }
        channels.push(channel);
    }
    let index = joints.len();
    joints.push(Joint { name, parent, offset, channels, end_site: None });
    loop {
        match words.next("JOINT, End Site or }")? {
            "}" => return Ok(()),
            w if w.eq_ignore_ascii_case("JOINT") => joint(words, Some(index), joints)?,
            w if w.eq_ignore_ascii_case("End") => {
                words.keyword("Site")?;
                words.keyword("{")?;
                words.keyword("OFFSET")?;
                joints[index].end_site = Some(words.vector("End Site OFFSET")?);
                words.keyword("}")?;
            }
            other => {
                words.at -= 1;
                return Err(words.error(format!("expected JOINT, End Site or }}, found {other:?}")));
            }
        }
    }
}

fn rotation(channel: Channel, degrees: f64) -> DMat3 {
    let angle = degrees.to_radians();
    match channel {
        Channel::Xrotation => DMat3::from_rotation_x(angle),
        Channel::Yrotation => DMat3::from_rotation_y(angle),
        Channel::Zrotation => DMat3::from_rotation_z(angle),
        _ => DMat3::IDENTITY,
    }
}

impl Motion {
    /// Every joint's frame in the world (file units) in frame `k`.
    pub fn joint_to_world(&self, k: usize) -> Vec<DMat4> {
        let values = &self.frames[k];
        let mut at = 0;
        let mut world: Vec<DMat4> = Vec::with_capacity(self.joints.len());
        for joint in &self.joints {
            let mut position = joint.offset;
            let positioned = joint.channels.iter().any(|c| c.is_position());
            if positioned {
                position = DVec3::ZERO;
            }
            let mut turn = DMat3::IDENTITY;
            for (&channel, &value) in joint.channels.iter().zip(&values[at..]) {
                match channel {
                    Channel::Xposition => position.x = value,
                    Channel::Yposition => position.y = value,
                    Channel::Zposition => position.z = value,
                    _ => turn *= rotation(channel, value),
                }
            }
            at += joint.channels.len();
            // A joint with only some position channels keeps its offset in the others.
            if positioned {
                for (axis, channel) in [Channel::Xposition, Channel::Yposition, Channel::Zposition].into_iter().enumerate() {
                    if !joint.channels.contains(&channel) {
                        position[axis] = joint.offset[axis];
                    }
                }
            }
            let local = DMat4::from_translation(position) * DMat4::from_mat3(turn);
            world.push(match joint.parent {
                Some(p) => world[p] * local,
                None => local,
            });
        }
        world
    }

    /// Frame `k`'s time in seconds from the clip's start.
    pub fn time(&self, k: usize) -> f64 {
        k as f64 * self.frame_time
    }

    /// The skeleton's size at rest (file units): the span of its joints and End Sites placed by
    /// their offsets alone.
    pub fn rest_span(&self) -> f64 {
        let mut heads: Vec<DVec3> = Vec::with_capacity(self.joints.len());
        let mut points = Vec::with_capacity(2 * self.joints.len());
        for joint in &self.joints {
            let head = joint.parent.map_or(DVec3::ZERO, |p| heads[p]) + joint.offset;
            heads.push(head);
            points.push(head);
            points.extend(joint.end_site.map(|e| head + e));
        }
        let (lo, hi) = points.iter().fold((DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        (hi - lo).length()
    }

    /// What makes the clip impossible to pose a body with, if anything: frames further apart
    /// than `MAX_FRAME_TIME`, a skeleton of no size (every offset 0: no bone has a direction or
    /// a length), or a frame that puts a joint further from the start than `MAX_TRAVEL` times
    /// the skeleton's size (a body 1.7 m tall 17 km away: past what f32 renders) or nowhere.
    /// Every reader of clips refuses these (`capture::read_clip`).
    pub fn problem(&self) -> Option<String> {
        if !(self.frame_time <= MAX_FRAME_TIME) {
            let time = super::readable(self.frame_time);
            return Some(format!(
                "Frame Time {time} s: frames more than {MAX_FRAME_TIME} s apart are no motion clip (is it in milliseconds or frames per second?)"
            ));
        }
        let span = self.rest_span();
        if !(span > 0.0) || !span.is_finite() {
            return Some("the skeleton has no size: every joint's OFFSET (and End Site) is 0, so its bones have neither length nor direction".into());
        }
        let reach = MAX_TRAVEL * span;
        for k in 0..self.frames.len() {
            let far =
                self.joint_to_world(k).iter().map(|m| m.w_axis.truncate().length()).fold(0.0f64, |a, d| if d.is_nan() { f64::INFINITY } else { a.max(d) });
            if !(far <= reach) {
                return Some(format!(
                    "frame {k}: a joint lies {far:e} file units from the origin, more than {MAX_TRAVEL} times the skeleton's size ({span:.4}): no body can be posed there"
                ));
            }
        }
        None
    }
}

/// The most seconds between a clip's frames (a clip at 0.1 frames per second is a slideshow).
pub const MAX_FRAME_TIME: f64 = 10.0;

/// How far from the origin, in skeleton sizes, a clip may carry a joint.
pub const MAX_TRAVEL: f64 = 1e4;

/// The angles (degrees) `a, b, c` with `Rz(a) Rx(b) Ry(c) = r` (a BVH's `Zrotation Xrotation
/// Yrotation`).
pub(crate) fn zxy_degrees(r: DMat3) -> [f64; 3] {
    // Rz Rx Ry has row 2 = (-cos b sin c, sin b, cos b cos c) and column 1 = (-sin a cos b,
    // cos a cos b, sin b).
    let sin_b = r.y_axis.z.clamp(-1.0, 1.0);
    let b = sin_b.asin();
    if sin_b.abs() < 1.0 - 1e-12 {
        let c = (-r.x_axis.z).atan2(r.z_axis.z);
        let a = (-r.y_axis.x).atan2(r.y_axis.y);
        [a.to_degrees(), b.to_degrees(), c.to_degrees()]
    } else {
        // Gimbal lock: only a + c (or a - c) is determined; c = 0.
        let a = r.x_axis.y.atan2(r.x_axis.x);
        [a.to_degrees(), b.to_degrees(), 0.0]
    }
}

/// A skeleton's frames as BVH text in `units` per metre (100 for centimetres): one joint per
/// bone at the bone's head, each joint's frame the bone's frame, the root translated, the
/// others rotated (`Zrotation Xrotation Yrotation`), a leaf's End Site at its bone's tail.
/// Refused when a child's head moves on its parent between frames (a BVH joint's offset is
/// fixed).
pub fn write(skeleton: &crate::skeleton::Skeleton, frames: &[Vec<DMat4>], frame_time: f64, units: f64) -> Result<String, String> {
    let first = frames.first().ok_or("no frames")?;
    let offsets: Vec<DVec3> = (0..skeleton.len())
        .map(|b| match skeleton.bones[b].parent {
            Some(p) => first[p].inverse().transform_point3(first[b].w_axis.truncate()),
            None => DVec3::ZERO,
        })
        .collect();
    for (k, frame) in frames.iter().enumerate() {
        for (b, bone) in skeleton.bones.iter().enumerate() {
            let Some(p) = bone.parent else { continue };
            let offset = frame[p].inverse().transform_point3(frame[b].w_axis.truncate());
            if offset.distance(offsets[b]) > 1e-6 {
                return Err(format!(
                    "bone {:?} moves on its parent {:?} in frame {k}: a BVH holds each joint's offset fixed",
                    bone.name, skeleton.bones[p].name
                ));
            }
        }
    }
    let mut text = String::from("HIERARCHY\n");
    let roots: Vec<usize> = (0..skeleton.len()).filter(|&b| skeleton.bones[b].parent.is_none()).collect();
    if roots.len() != 1 {
        return Err(format!("a BVH holds one root; the skeleton has {}", roots.len()));
    }
    write_joint(&mut text, skeleton, roots[0], &offsets, units, 0);
    text.push_str(&format!("MOTION\nFrames: {}\nFrame Time: {frame_time:.9}\n", frames.len()));
    // The joints are written depth first; each frame's values follow that order.
    let order = depth_first(skeleton, roots[0]);
    for frame in frames {
        let mut line = Vec::new();
        for &b in &order {
            let local = match skeleton.bones[b].parent {
                Some(p) => frame[p].inverse() * frame[b],
                None => frame[b],
            };
            if skeleton.bones[b].parent.is_none() {
                line.extend((local.w_axis.truncate() * units).to_array());
            }
            line.extend(zxy_degrees(DMat3::from_mat4(local)));
        }
        let line: Vec<String> = line.iter().map(|v| format!("{v:.9}")).collect();
        text.push_str(&line.join(" "));
        text.push('\n');
    }
    Ok(text)
}

/// The bones below `root`, depth first, children in the skeleton's order.
fn depth_first(skeleton: &crate::skeleton::Skeleton, root: usize) -> Vec<usize> {
    let mut order = vec![root];
    for child in (0..skeleton.len()).filter(|&c| skeleton.bones[c].parent == Some(root)) {
        order.extend(depth_first(skeleton, child));
    }
    order
}

fn write_joint(text: &mut String, skeleton: &crate::skeleton::Skeleton, b: usize, offsets: &[DVec3], units: f64, depth: usize) {
    let pad = "  ".repeat(depth);
    let bone = &skeleton.bones[b];
    let keyword = if depth == 0 { "ROOT" } else { "JOINT" };
    let o = offsets[b] * units;
    text.push_str(&format!("{pad}{keyword} {}\n{pad}{{\n{pad}  OFFSET {:.9} {:.9} {:.9}\n", bone.name, o.x, o.y, o.z));
    let channels =
        if depth == 0 { "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" } else { "CHANNELS 3 Zrotation Xrotation Yrotation" };
    text.push_str(&format!("{pad}  {channels}\n"));
    let children: Vec<usize> = (0..skeleton.len()).filter(|&c| skeleton.bones[c].parent == Some(b)).collect();
    for &child in &children {
        write_joint(text, skeleton, child, offsets, units, depth + 1);
    }
    if children.is_empty() {
        text.push_str(&format!("{pad}  End Site\n{pad}  {{\n{pad}    OFFSET 0 {:.9} 0\n{pad}  }}\n", bone.length * units));
    }
    text.push_str(&format!("{pad}}}\n"));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A header claiming absurd counts is refused before anything is allocated for it.
    #[test]
    fn hostile_headers_are_refused_without_allocating() {
        let file = Path::new("hostile.bvh");
        let joint = "HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n End Site\n {\n  OFFSET 0 1 0\n }\n}\n";
        for frames in ["1e30", "18446744073709551615", "99999999999999"] {
            let text = format!("{joint}MOTION\nFrames: {frames}\nFrame Time: 0.1\n0 0 0\n");
            let err = parse(&text, file).unwrap_err().to_string();
            assert!(err.contains("MOTION section holds 3 values"), "{frames}: {err}");
        }
        let still = joint.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 0");
        let err = parse(&format!("{still}MOTION\nFrames: 1e15\nFrame Time: 0.1\n"), file).unwrap_err().to_string();
        assert!(err.contains("no joint has a channel"), "{err}");
        // More joints than allowed, and a truncated file, are errors too.
        let many = "HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 0\n".to_string()
            + &(0..2000).map(|k| format!("JOINT j{k}\n{{\n OFFSET 0 0 0\n CHANNELS 0\n")).collect::<String>();
        let err = parse(&many, file).unwrap_err().to_string();
        assert!(err.contains("more than 1024 joints"), "{err}");
        assert!(parse("HIERARCHY\nROOT a\n{\n OFFSET 0 0", file).unwrap_err().to_string().contains("the file ends"));
    }

    #[test]
    fn zxy_angles_rebuild_the_rotation() {
        for (a, b, c) in [(10.0, 20.0, 30.0), (-170.0, 80.0, 5.0), (45.0, -60.0, 120.0), (0.0, 90.0, 0.0)] {
            let r = rotation(Channel::Zrotation, a) * rotation(Channel::Xrotation, b) * rotation(Channel::Yrotation, c);
            let [x, y, z] = zxy_degrees(r);
            let back = rotation(Channel::Zrotation, x) * rotation(Channel::Xrotation, y) * rotation(Channel::Yrotation, z);
            assert!((back - r).to_cols_array().iter().all(|d| d.abs() < 1e-9), "{a} {b} {c}");
        }
    }
}
