//! Planning a grid lookup on the CPU: each point's nearest bones and their skinning, the
//! trilinear corners of every level in each, with the coefficients' exact derivatives along the
//! world axes when asked (`lookup`; for a lookup carrying a shift, each cell's fractions,
//! `lookup_carried`); where nothing is differentiated, `host_lookup` sums the features
//! as the corners are found (`features_on_host`).

use super::layout::{GridConfig, Level, MAX_TOP_BONES};
use crate::skeleton::BoneFrame;
use rayon::prelude::*;

/// How the skinning and the capsule prior are shaped (shared with the MLP field).
#[derive(Clone, Copy, Debug)]
pub struct Skinning {
    /// The factor on squared distance in the softmax's logits.
    pub sharpness: f32,
    pub prior_radius: f32,
    /// The root bone and the distance (m) beyond which the skinning sees it no farther
    /// (`RootSkinning::cap`).
    pub root: Option<(usize, f32)>,
    /// The most the capsule prior gives (m), when capped (`RootSkinning::prior_capped`).
    pub prior_cap: Option<f32>,
}

impl Skinning {
    /// The squared distance the skinning weighs for bone `bone` at true squared distance `d2`,
    /// and whether it is the true one (so its gradient applies).
    fn distance_squared(&self, bone: usize, d2: f32) -> (f32, bool) {
        match self.root {
            Some((root, cap)) if root == bone && d2 > cap * cap => (cap * cap, false),
            _ => (d2, true),
        }
    }
}

/// The plan of a lookup of `N` points in their `K` chosen bones. Table rows and their
/// trilinear coefficients, `N x K x levels x 8` (point, then bone, then level, then corner),
/// with the coefficients' derivatives along the world axes (`[.., 3]`) when asked. Per point
/// and chosen bone, the skinning's logit from distance (shifted so the largest is 0), its
/// gradient and whether the bone is the root; per point, the root's preference grid's 8
/// rows and coefficients (zero unless the root is chosen) with their gradients; the capsule
/// prior and its gradient. The skinning weights are a softmax of the logits plus, for the
/// root, its learned preference, taken on the tensor side so the preference trains.
#[derive(Clone, Debug, Default)]
pub struct Lookup {
    pub rows: Vec<u32>,
    pub coefficients: Vec<f32>,
    pub coefficient_tangents: Vec<f32>,
    pub logits: Vec<f32>,
    pub logit_tangents: Vec<f32>,
    pub root_slot: Vec<f32>,
    pub root_rows: Vec<u32>,
    pub root_coefficients: Vec<f32>,
    pub root_coefficient_tangents: Vec<f32>,
    pub prior: Vec<f32>,
    pub prior_tangents: Vec<f32>,
    /// Per point and chosen bone, the capsule prior's world gradient through that bone's
    /// distance alone (`[N * K, 3]`; they sum to `prior_tangents`), when tangents are planned:
    /// what a bone's own motion moves the prior by.
    pub prior_slot_tangents: Vec<f32>,
    /// Per point and chosen bone, the bone (`[N * K]`), when tangents are planned: what a
    /// motion increment moves the point's lookup with.
    pub bones: Vec<u32>,
    /// Per cell (point, chosen bone, level) its fractions (`[.., 3]`, `Cell::fraction`), when
    /// planned for a carried shift (`lookup_carried`) instead of per-corner derivatives.
    pub cell_fractions: Vec<f32>,
}

/// What the plan says about one point besides its feature rows.
#[derive(Clone, Copy, Default)]
pub(super) struct PointSkin {
    pub(super) logits: [f32; MAX_TOP_BONES],
    logit_tangents: [[f32; 3]; MAX_TOP_BONES],
    pub(super) root_slot: Option<usize>,
    pub(super) root_rows: [u32; 8],
    pub(super) root_coefficients: [f32; 8],
    root_coefficient_tangents: [[f32; 3]; 8],
    pub(super) prior: f32,
    prior_tangent: [f32; 3],
    prior_slot_tangents: [[f32; 3]; MAX_TOP_BONES],
    bones: [u32; MAX_TOP_BONES],
}

/// Plans the lookup of `points` (`[N * 3]`, world) in the bones `frames`.
pub fn lookup(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: &[f32], tangents: bool) -> Lookup {
    plan(config, levels, frames, skinning, points, if tangents { Derivatives::PerCorner } else { Derivatives::None })
}

/// `lookup` with tangents for a lookup that carries a shift of its points
/// (`plan::Carried`): the skinning's and the prior's tangents, and per cell its
/// fractions instead of each corner's derivative (3 floats a cell instead of 24).
pub fn lookup_carried(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: &[f32]) -> Lookup {
    plan(config, levels, frames, skinning, points, Derivatives::Cells)
}

/// Which spatial derivatives a plan holds.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Derivatives {
    None,
    /// Each corner coefficient's world derivative.
    PerCorner,
    /// Each cell's fractions (the coefficients' derivatives follow from them and the bone's axes).
    Cells,
}

fn plan(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: &[f32], derivatives: Derivatives) -> Lookup {
    let tangents = derivatives != Derivatives::None;
    let n = points.len() / 3;
    let c = config.corners();
    let mut rows = vec![0u32; n * c];
    let mut coefficients = vec![0.0f32; n * c];
    // Per point: 3 floats per corner, or 3 per cell of 8 corners.
    let per_point = match derivatives {
        Derivatives::None => 0,
        Derivatives::PerCorner => c * 3,
        Derivatives::Cells => c / 8 * 3,
    };
    let mut coefficient_tangents = vec![0.0f32; n * per_point];
    let mut skins = vec![PointSkin::default(); n];
    // Points in chunks across threads; each chunk writes its own slices of the plan.
    const CHUNK: usize = 64;
    let tangent_chunks: Vec<&mut [f32]> =
        if tangents { coefficient_tangents.chunks_mut(CHUNK * per_point).collect() } else { (0..n.div_ceil(CHUNK)).map(|_| &mut [][..]).collect() };
    rows.par_chunks_mut(CHUNK * c)
        .zip(coefficients.par_chunks_mut(CHUNK * c))
        .zip(skins.par_chunks_mut(CHUNK))
        .zip(tangent_chunks.into_par_iter())
        .enumerate()
        .for_each(|(chunk, (((rows, coefficients), skins), d_coefficients))| {
            let mut scratch = Scratch::default();
            for (k, skin) in skins.iter_mut().enumerate() {
                let i = chunk * CHUNK + k;
                let point = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
                let span = k * c..(k + 1) * c;
                let d_coefficients = if tangents { Some(&mut d_coefficients[k * per_point..(k + 1) * per_point]) } else { None };
                *skin = plan_point(
                    config,
                    levels,
                    frames,
                    skinning,
                    point,
                    &mut scratch,
                    &mut rows[span.clone()],
                    &mut coefficients[span],
                    d_coefficients,
                    derivatives,
                );
            }
        });
    let top = config.top();
    let (coefficient_tangents, cell_fractions) = match derivatives {
        Derivatives::Cells => (Vec::new(), coefficient_tangents),
        _ => (coefficient_tangents, Vec::new()),
    };
    let mut plan = Lookup { rows, coefficients, coefficient_tangents, cell_fractions, ..Lookup::default() };
    for skin in &skins {
        plan.logits.extend_from_slice(&skin.logits[..top]);
        plan.root_slot.extend((0..top).map(|j| if skin.root_slot == Some(j) { 1.0 } else { 0.0 }));
        plan.root_rows.extend_from_slice(&skin.root_rows);
        plan.root_coefficients.extend_from_slice(&skin.root_coefficients);
        plan.prior.push(skin.prior);
        if tangents {
            plan.logit_tangents.extend(skin.logit_tangents[..top].iter().flatten());
            plan.root_coefficient_tangents.extend(skin.root_coefficient_tangents.iter().flatten());
            plan.prior_tangents.extend_from_slice(&skin.prior_tangent);
            plan.prior_slot_tangents.extend(skin.prior_slot_tangents[..top].iter().flatten());
            plan.bones.extend_from_slice(&skin.bones[..top]);
        }
    }
    plan
}

/// A bone's squared distance to a point: the true one (the capsule prior's) and the one the
/// skinning weighs (`Skinning::distance_squared`), each with its world gradient.
pub(super) struct BoneDistance {
    bone: usize,
    d2: f32,
    gradient: [f32; 3],
    skinning_d2: f32,
    skinning_gradient: [f32; 3],
    /// The point in the bone's frame.
    local: [f32; 3],
}

/// Buffers one thread reuses from point to point (a point's plan allocates nothing).
#[derive(Default)]
pub(super) struct Scratch {
    /// The chosen bones' distances to the point, ascending by bone.
    pub(super) all: Vec<BoneDistance>,
    /// Every bone's skinning's squared distance while choosing: (distance, bone).
    nearest: Vec<(f32, usize)>,
    /// A softmax's weights.
    weights: Vec<f32>,
}

/// The weights the grid field blends its bones' features with at `point` (the root's learned
/// preference aside): a softmax of the skinning's logits over the `top` nearest bones, as
/// `(bone, weight)` ascending by bone.
pub fn skinning_weights(config: &GridConfig, frames: &[BoneFrame], skinning: Skinning, point: [f32; 3]) -> Vec<(usize, f32)> {
    let mut scratch = Scratch::default();
    let skin = skin_point(config, frames, skinning, point, &mut scratch, false);
    let chosen = &scratch.all;
    let sum: f32 = (0..chosen.len()).map(|j| skin.logits[j].exp()).sum();
    chosen.iter().enumerate().map(|(j, a)| (a.bone, skin.logits[j].exp() / sum)).collect()
}

/// Softmax weights of logits `sharpness d2`, into `out`.
#[inline(always)]
fn softmax(out: &mut Vec<f32>, d2: impl Iterator<Item = f32>, sharpness: f32) {
    out.clear();
    out.extend(d2.map(|d2| d2 * sharpness));
    // Shifted by the largest logit, so the exponentials stay finite.
    let max = out.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    for w in out.iter_mut() {
        *w = (*w - max).exp();
    }
    let sum: f32 = out.iter().sum();
    for w in out.iter_mut() {
        *w /= sum;
    }
}

/// The trilinear cell around a point: its lowest vertex, and per corner (bit 0 the x side,
/// bit 1 y, bit 2 z) its weight and the weight's world gradient (zero unless asked for).
pub(super) struct Cell {
    base: [usize; 3],
    pub(super) weights: [f32; 8],
    gradients: [[f32; 3]; 8],
    /// The point's place in the cell along the bone's local axes, as `Carried` keeps it.
    fraction: [f32; 3],
}

/// The trilinear cell around `local` in a grid of `dims` vertices spaced `cell` apart from
/// `-reach` on each local axis, with the weights' world gradients (through the bone's `axes`)
/// when `TANGENTS`; a point outside the grid is clamped to its border (a clamped axis has no
/// spatial derivative).
// This and the other helpers of a point's lookup are inlined into each lookup's loop (the
// compiler left them as calls): a cell then stays in registers instead of passing its weights
// and gradients through memory, and a plan with tangents takes a third of the time
// (`cargo run --release --example grid_profile`), to the same bits.
#[inline(always)]
fn trilinear<const TANGENTS: bool>(local: [f32; 3], reach: f32, cell: f32, dims: [usize; 3], axes: &[[f32; 3]; 3]) -> Cell {
    let mut base = [0usize; 3];
    let mut fraction = [0.0f32; 3];
    let mut inside = [true; 3];
    // One division for the three axes (a cell's corners cost little more than this).
    let per_cell = 1.0 / cell;
    for m in 0..3 {
        let top_vertex = (dims[m] - 1) as f32;
        let mut u = (local[m] + reach) * per_cell;
        if !(u > 0.0) {
            u = 0.0;
            inside[m] = false;
        } else if u >= top_vertex {
            u = top_vertex;
            inside[m] = false;
        }
        // u is in [0, top] here, so truncation is floor (and, unlike `floor`, needs no call
        // into libm on the baseline instruction set).
        let at = (u as usize).min(dims[m] - 2);
        base[m] = at;
        fraction[m] = u - at as f32;
    }
    // Each axis's two factors, the low side's and the high side's.
    let factors = [0, 1, 2].map(|m| [1.0 - fraction[m], fraction[m]]);
    let mut weights = [0.0f32; 8];
    for (k, w) in weights.iter_mut().enumerate() {
        *w = factors[0][k & 1] * factors[1][(k >> 1) & 1] * factors[2][k >> 2];
    }
    let mut gradients = [[0.0f32; 3]; 8];
    if TANGENTS {
        // d u_m / d x = (local axis m) / cell on axes inside the grid.
        let du: [[f32; 3]; 3] = [0, 1, 2].map(|m| if inside[m] { axes[m].map(|a| a * per_cell) } else { [0.0; 3] });
        for (k, gradient) in gradients.iter_mut().enumerate() {
            let bit = [k & 1, (k >> 1) & 1, k >> 2];
            let factor = [0, 1, 2].map(|m| factors[m][bit[m]]);
            // d weight / d u_m: the other two factors, signed by the corner's side.
            let d_tri = [0, 1, 2].map(|m| {
                let sign = if bit[m] == 1 { 1.0 } else { -1.0 };
                sign * factor[(m + 1) % 3] * factor[(m + 2) % 3]
            });
            *gradient = [0, 1, 2].map(|x| d_tri[0] * du[0][x] + d_tri[1] * du[1][x] + d_tri[2] * du[2][x]);
        }
    }
    // An axis outside the grid has no derivative: kept as its fraction plus 2.
    let fraction = [0, 1, 2].map(|m| if inside[m] { fraction[m] } else { fraction[m] + 2.0 });
    Cell { base, weights, gradients, fraction }
}

/// Plans one point's corners and returns the rest of its plan.
#[allow(clippy::too_many_arguments)]
fn plan_point(
    config: &GridConfig,
    levels: &[Level],
    frames: &[BoneFrame],
    skinning: Skinning,
    point: [f32; 3],
    scratch: &mut Scratch,
    rows: &mut [u32],
    coefficients: &mut [f32],
    d_coefficients: Option<&mut [f32]>,
    derivatives: Derivatives,
) -> PointSkin {
    let tangents = d_coefficients.is_some();
    let skin = skin_point(config, frames, skinning, point, scratch, tangents);
    let chosen = &scratch.all[..config.top().min(scratch.all.len())];
    match (d_coefficients, derivatives) {
        (Some(d), Derivatives::PerCorner) => visit_cells::<true>(config, levels, frames, chosen, |k, _, cell_rows, cell| {
            rows[k..k + 8].copy_from_slice(&cell_rows);
            coefficients[k..k + 8].copy_from_slice(&cell.weights);
            d[k * 3..(k + 8) * 3].copy_from_slice(cell.gradients.as_flattened());
        }),
        (Some(d), _) => visit_cells::<false>(config, levels, frames, chosen, |k, _, cell_rows, cell| {
            rows[k..k + 8].copy_from_slice(&cell_rows);
            coefficients[k..k + 8].copy_from_slice(&cell.weights);
            d[k / 8 * 3..k / 8 * 3 + 3].copy_from_slice(&cell.fraction);
        }),
        (None, _) => visit_cells::<false>(config, levels, frames, chosen, |k, _, cell_rows, cell| {
            rows[k..k + 8].copy_from_slice(&cell_rows);
            coefficients[k..k + 8].copy_from_slice(&cell.weights);
        }),
    }
    skin
}

/// A point's skinning: the `top` nearest bones chosen (left, ascending by bone, at the head of
/// `scratch.all`), their logits, the capsule prior and the root's preference corners, with
/// their world gradients when `tangents` says.
#[inline(always)]
pub(super) fn skin_point(config: &GridConfig, frames: &[BoneFrame], skinning: Skinning, point: [f32; 3], scratch: &mut Scratch, tangents: bool) -> PointSkin {
    // The skinning's squared distance to every bone segment first, and only then, for the `top`
    // nearest (a point is looked up in 3 of a human's 20 bones), the offset, its true distance and
    // their world gradients: the full record for every bone was a quarter of a render's lookups.
    // The selection compares the same distances in the same order as when every record was
    // built first, so a bone tied for the last place is the one it was and a fit is the same
    // to the bit.
    let top = config.top().min(frames.len());
    let nearest = &mut scratch.nearest;
    nearest.clear();
    nearest.extend(frames.iter().enumerate().map(|(b, f)| (skinning.distance_squared(b, f.distance_squared(point)).0, b)));
    if top < nearest.len() {
        nearest.select_nth_unstable_by(top - 1, |a, b| a.0.total_cmp(&b.0));
        nearest.truncate(top);
    }
    nearest.sort_unstable_by_key(|&(_, b)| b);
    let all = &mut scratch.all;
    all.clear();
    all.extend(nearest.iter().map(|&(_, b)| {
        let f = &frames[b];
        let local = f.to_local(point);
        let offset = [local[0], local[1] - local[1].clamp(0.0, f.length), local[2]];
        let d2 = offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2];
        let gradient = [0, 1, 2].map(|a| 2.0 * (f.axes[0][a] * offset[0] + f.axes[1][a] * offset[1] + f.axes[2][a] * offset[2]));
        let (skinning_d2, moves) = skinning.distance_squared(b, d2);
        BoneDistance { bone: b, d2, gradient, skinning_d2, skinning_gradient: if moves { gradient } else { [0.0; 3] }, local }
    }));
    let chosen = &mut all[..];
    let mut skin = PointSkin::default();
    // The skinning's logits from distance, shifted so the largest is 0 (a softmax's weights
    // do not change), with their gradients. Each gradient is its own bone's distance's alone
    // (the shift's gradient, common to all, moves no weight): a bone's motion moves its logit
    // and no other.
    let lead = (0..chosen.len()).min_by(|&a, &b| chosen[a].skinning_d2.total_cmp(&chosen[b].skinning_d2)).unwrap_or(0);
    let max = chosen[lead].skinning_d2 * skinning.sharpness;
    for (j, a) in chosen.iter().enumerate() {
        skin.bones[j] = a.bone as u32;
        skin.logits[j] = a.skinning_d2 * skinning.sharpness - max;
        skin.logit_tangents[j] = a.skinning_gradient.map(|g| g * skinning.sharpness);
    }
    // The capsule prior: the distance to the segments, weighted by a softmax of the true
    // distances (the root's cap would mix distances that differ by the whole cap where the
    // weights turn, a gradient far steeper than a distance's), minus the radius.
    // Its gradient is split by bone: through bone j's distance alone, sharpness w_j (d_j - mean)
    // (the softmax's weights) plus w_j / (2 d_j), times the squared distance's gradient.
    softmax(&mut scratch.weights, chosen.iter().map(|a| a.d2), skinning.sharpness);
    let mut distances = [0.0f32; MAX_TOP_BONES];
    for (d, a) in distances.iter_mut().zip(chosen.iter()) {
        *d = (a.d2 + 1e-8).sqrt();
    }
    let mean: f32 = scratch.weights.iter().zip(&distances).map(|(w, d)| w * d).sum();
    skin.prior = mean - skinning.prior_radius;
    let slope = match skinning.prior_cap {
        Some(cap) => {
            let (value, slope) = saturate(skin.prior, cap);
            skin.prior = value;
            slope
        }
        None => 1.0,
    };
    // (A lookup without gradients, the surface search's and a render's, needs none of it.)
    if tangents {
        for (j, ((a, &weight), distance)) in chosen.iter().zip(&scratch.weights).zip(&distances).enumerate() {
            let through = slope * (skinning.sharpness * weight * (distance - mean) + weight / (2.0 * distance));
            skin.prior_slot_tangents[j] = a.gradient.map(|g| through * g);
            for (tangent, part) in skin.prior_tangent.iter_mut().zip(skin.prior_slot_tangents[j]) {
                *tangent += part;
            }
        }
    }
    // The root's preference grid, when the root is chosen.
    if let (Some(root), Some(j)) = (config.root, chosen.iter().position(|a| Some(a.bone) == config.root.map(|r| r.bone))) {
        skin.root_slot = Some(j);
        let dims = root.dims(frames[root.bone].length);
        let (local, axes) = (chosen[j].local, &frames[root.bone].axes);
        let cell =
            if tangents { trilinear::<true>(local, root.reach, root.cell, dims, axes) } else { trilinear::<false>(local, root.reach, root.cell, dims, axes) };
        for k in 0..8 {
            let v = [cell.base[0] + (k & 1), cell.base[1] + ((k >> 1) & 1), cell.base[2] + (k >> 2)];
            skin.root_rows[k] = (v[0] + dims[0] * (v[1] + dims[1] * v[2])) as u32;
        }
        skin.root_coefficients = cell.weights;
        skin.root_coefficient_tangents = cell.gradients;
    }
    skin
}

/// The capsule prior `x` capped at `cap`, and its slope: a corner at the cap.
pub fn saturate(x: f32, cap: f32) -> (f32, f32) {
    if x > cap {
        (cap, 0.0)
    } else {
        (x, 1.0)
    }
}

/// Every cell of a point's lookup in its `chosen` bones, level by level: `cell(k, level, rows,
/// cell)` with `k` the place of its first corner in the plan (bone, then level, then corner;
/// an inactive level's 8 places are skipped, left at row 0 and weight 0), the weights' world
/// gradients computed only when `TANGENTS`.
#[inline(always)]
pub(super) fn visit_cells<const TANGENTS: bool>(
    config: &GridConfig,
    levels: &[Level],
    frames: &[BoneFrame],
    chosen: &[BoneDistance],
    mut visit: impl FnMut(usize, usize, [u32; 8], &Cell),
) {
    let mut k = 0;
    for a in chosen {
        let frame = &frames[a.bone];
        let reach = config.bone_reach(a.bone);
        for (l, level) in levels.iter().enumerate() {
            if level.active {
                let cell = trilinear::<TANGENTS>(a.local, reach, level.cell, level.dims[a.bone], &frame.axes);
                visit(k, l, level.corner_rows(a.bone, cell.base).map(|r| r as u32), &cell);
            }
            k += 8;
        }
    }
}
