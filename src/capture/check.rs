//! The capture check: do the cameras and the motion agree? Points along every bone, posed in each
//! training image's frame and projected by its camera, should fall inside the image's mask (the
//! bones run inside the body). A wrong up axis, a centimetre/metre mix-up, OpenGL axes read as
//! OpenCV's or a time offset put them outside, and the share inside collapses. The contact sheet
//! shows each camera's first image with its mask and the bones drawn over it.

use crate::plot::Canvas;
use crate::scene::{Scene, Split};

/// Points per bone, from its head to its tail.
const POINTS_PER_BONE: usize = 9;

/// Below this share of the bones' points inside the masks, an import is refused; below `WARN`
/// it is kept with a warning. A capture whose cameras and motion agree scores above 0.9 (the
/// synthetic round trips: 1.0); a swapped up axis or wrong units below 0.1.
pub const REFUSE: f64 = 0.5;
pub const WARN: f64 = 0.85;

/// The body sizes umbra fits (m, the diagonal of its joints' box): a cat's to an elephant's.
/// Units or an up that turn and scale the cameras and the motion together leave the capture
/// check's projections unchanged; a body's size and the cameras' level rows do not.
pub const SMALLEST_BODY: f64 = 0.25;
pub const LARGEST_BODY: f64 = 10.0;

/// The most the up the cameras show (`scene::world_up`) may lean from the scene's +Y (degrees).
pub const MOST_UP_LEAN: f64 = 30.0;

/// What is wrong with a body `metres` across, if anything (`SMALLEST_BODY`..`LARGEST_BODY`).
pub fn size_problem(metres: f64) -> Option<String> {
    match (SMALLEST_BODY..=LARGEST_BODY).contains(&metres) {
        true => None,
        false => Some(format!("a body {metres:.3} m across, where umbra fits bodies {SMALLEST_BODY} to {LARGEST_BODY} m across")),
    }
}

/// What is wrong with the way `scene` stands, if anything: its cameras' image rows are level
/// about an up far from +Y (the capture's up is another axis), or most cameras stand below the
/// body's lowest joint in every frame (up is upside down).
pub fn orientation_problem(scene: &Scene) -> Option<String> {
    let up = crate::scene::world_up(&scene.cameras);
    let lean = up.angle_between(glam::DVec3::Y).to_degrees();
    if !(lean <= MOST_UP_LEAN) {
        return Some(format!(
            "the cameras' image rows are level about an up of ({:.2}, {:.2}, {:.2}) in the scene, {lean:.0} degrees from its +Y",
            up.x, up.y, up.z
        ));
    }
    let lowest = scene.frames.iter().map(|f| f.pose.bounds(&scene.skeleton).0.y).fold(f64::INFINITY, f64::min);
    let below = scene.cameras.iter().filter(|c| c.centre().y < lowest).count();
    if 2 * below > scene.cameras.len() {
        return Some(format!("{below} of {} cameras stand below the body's lowest joint ({lowest:.3} m): the body is upside down", scene.cameras.len()));
    }
    None
}

/// The share of the bones' points inside the masks: over all training images, per camera and
/// per bone.
#[derive(Clone, Debug)]
pub struct CaptureCheck {
    pub score: f64,
    pub per_camera: Vec<(String, f64)>,
    pub per_bone: Vec<(String, f64)>,
}

impl CaptureCheck {
    /// The worst bones, as a sentence.
    pub fn worst_bones(&self, count: usize) -> String {
        let mut bones = self.per_bone.clone();
        bones.sort_by(|a, b| a.1.total_cmp(&b.1));
        bones.iter().take(count).map(|(name, s)| format!("{name} {:.0}%", 100.0 * s)).collect::<Vec<_>>().join(", ")
    }
}

/// Whether bone `b`'s point `k` (of `POINTS_PER_BONE`) in view `v` projects inside its mask.
fn inside(scene: &Scene, v: usize, b: usize, k: usize) -> bool {
    let view = &scene.views[v];
    let (Some(mask), camera) = (&view.mask, &scene.cameras[view.camera]) else { return false };
    let pose = &scene.frames[view.frame].pose;
    let (head, tail) = pose.segment(&scene.skeleton, b);
    let t = k as f64 / (POINTS_PER_BONE - 1) as f64;
    camera.project(head.lerp(tail, t)).is_some_and(|px| {
        let (x, y) = (px.x.floor(), px.y.floor());
        x >= 0.0 && y >= 0.0 && (x as usize) < mask.width && (y as usize) < mask.height && mask.foreground[y as usize * mask.width + x as usize]
    })
}

/// Scores `scene`'s training images (those with masks).
pub fn check(scene: &Scene) -> CaptureCheck {
    let views: Vec<usize> = (0..scene.views.len()).filter(|&v| scene.views[v].split == Split::Train && scene.views[v].mask.is_some()).collect();
    let bones = scene.skeleton.len();
    // hits[v][b]: how many of bone b's points fall inside view v's mask.
    let hits: Vec<Vec<usize>> = views.iter().map(|&v| (0..bones).map(|b| (0..POINTS_PER_BONE).filter(|&k| inside(scene, v, b, k)).count()).collect()).collect();
    let share = |counts: &mut dyn Iterator<Item = usize>, of: usize| counts.sum::<usize>() as f64 / (of * POINTS_PER_BONE).max(1) as f64;
    let score = share(&mut hits.iter().flatten().copied(), views.len() * bones);
    let per_bone = (0..bones).map(|b| (scene.skeleton.bones[b].name.clone(), share(&mut hits.iter().map(|h| h[b]), views.len()))).collect();
    let per_camera = (0..scene.cameras.len())
        .filter_map(|c| {
            let of_camera: Vec<usize> = (0..views.len()).filter(|&i| scene.views[views[i]].camera == c).collect();
            (!of_camera.is_empty())
                .then(|| (scene.cameras[c].name.clone(), share(&mut of_camera.iter().flat_map(|&i| hits[i].iter().copied()), of_camera.len() * bones)))
        })
        .collect();
    CaptureCheck { score, per_camera, per_bone }
}

/// Each camera's first training image (its mask's outside dimmed, the bones drawn: green where a
/// point is inside the mask, red where not), labelled with the camera's score; six across.
pub fn contact_sheet(scene: &Scene, check: &CaptureCheck) -> Canvas {
    let firsts: Vec<usize> = (0..scene.cameras.len())
        .filter_map(|c| (0..scene.views.len()).find(|&v| scene.views[v].camera == c && scene.views[v].split == Split::Train && scene.views[v].mask.is_some()))
        .collect();
    let largest = firsts.iter().map(|&v| scene.views[v].colour.width().max(scene.views[v].colour.height())).max().unwrap_or(1);
    let zoom = (256 / largest).max(1);
    let tile = largest * zoom;
    let label = crate::plot::TextSize::Small.height() as usize + 6;
    let columns = firsts.len().clamp(1, 6);
    let rows = firsts.len().div_ceil(columns).max(1);
    let mut sheet = Canvas::new(columns * (tile + 4), rows * (tile + label + 4));
    for (n, &v) in firsts.iter().enumerate() {
        let (x0, y0) = ((n % columns) * (tile + 4), (n / columns) * (tile + label + 4));
        draw_view(&mut sheet, scene, v, (x0, y0 + label), zoom);
        let camera = &scene.cameras[scene.views[v].camera];
        let score = check.per_camera.iter().find(|(name, _)| *name == camera.name).map(|(_, s)| *s).unwrap_or(0.0);
        sheet.text(x0 as i64 + 2, y0 as i64 + 2, &format!("{} {:.0}%", camera.name, 100.0 * score), crate::plot::TextSize::Small, [0, 0, 0]);
    }
    sheet
}

fn draw_view(sheet: &mut Canvas, scene: &Scene, v: usize, (x0, y0): (usize, usize), zoom: usize) {
    let view = &scene.views[v];
    let Some(mask) = &view.mask else { return };
    for y in 0..view.colour.height() {
        for x in 0..view.colour.width() {
            let p = y * view.colour.width() + x;
            let srgb = view.colour.pixel(p).map(crate::imageio::linear_to_srgb8);
            // Outside the mask: a dim blue, so the silhouette reads at a glance.
            let c = if mask.foreground[p] { srgb } else { [srgb[0] / 3, srgb[1] / 3, srgb[2] / 3 + 60] };
            sheet.fill((x0 + x * zoom) as i64, (y0 + y * zoom) as i64, (x0 + (x + 1) * zoom) as i64, (y0 + (y + 1) * zoom) as i64, c);
        }
    }
    let camera = &scene.cameras[view.camera];
    let pose = &scene.frames[view.frame].pose;
    let z = zoom as f64;
    for b in 0..scene.skeleton.len() {
        let (head, tail) = pose.segment(&scene.skeleton, b);
        for k in 0..POINTS_PER_BONE - 1 {
            let (t0, t1) = (k as f64 / (POINTS_PER_BONE - 1) as f64, (k + 1) as f64 / (POINTS_PER_BONE - 1) as f64);
            let (Some(a), Some(c)) = (camera.project(head.lerp(tail, t0)), camera.project(head.lerp(tail, t1))) else { continue };
            let colour = if inside(scene, v, b, k) { [40, 220, 60] } else { [240, 40, 40] };
            let at = |p: glam::DVec2| (x0 as f64 + p.x * z, y0 as f64 + p.y * z);
            let (a, c) = (at(a), at(c));
            // Clipped to the tile: a bone far outside the image is not drawn across the sheet.
            let tile = |(x, y): (f64, f64)| {
                x >= x0 as f64 && y >= y0 as f64 && x < (x0 + view.colour.width() * zoom) as f64 && y < (y0 + view.colour.height() * zoom) as f64
            };
            if tile(a) && tile(c) {
                sheet.line(a, c, colour);
            }
        }
    }
}
