//! Multiresolution feature grids in bone-local coordinates, the capacity of the `grid` field.
//!
//! Every bone owns a box around its segment (its reach follows the body's size), and every
//! level a grid over each box, from a coarse cell of a tenth of the body's extent down to a
//! fine one of 1/160. A level whose grids fit its table is stored densely; a finer one is
//! hashed (instant-NGP's spatial hash, the bone index hashed in). A point is looked up only in
//! the `top_bones` bones nearest to it (their softmax skinning weights over distance to the
//! segment, renormalised over those bones), trilinearly in each level, and the weighted
//! corners summed into `levels x features` values that a small MLP decodes.
//!
//! The lookup is planned on the CPU (`lookup`): which table rows, with which coefficient
//! (skinning weight x trilinear weight) and, when asked, the coefficient's exact derivative
//! along the three world axes, so the features' spatial tangents are closed form and the SDF
//! gradient stays exact. The tensor side is then one `select` of rows, a product and a sum, so
//! the gradient to the features is burn's scatter-add, on any backend. The sample points are
//! constants of the plan: gradients reach the table, not the points.

use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor, TensorData};
use rayon::prelude::*;

/// The grid's shape: levels, features per level, table size and lengths derived from the body.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct GridConfig {
    pub levels: usize,
    /// Features stored per table entry (per level).
    pub features: usize,
    /// log2 of the entries per level.
    pub table_log2: u32,
    /// Cell (m) of the coarsest and the finest level; levels in between are geometric.
    pub coarsest_cell: f32,
    pub finest_cell: f32,
    /// How far (m) a bone's box reaches beyond its segment on every side.
    pub reach: f32,
    /// How many of the nearest bones a point is looked up in.
    pub top_bones: usize,
    /// Bone lengths (m), for the boxes' sizes.
    pub bone_lengths: Vec<f32>,
}

/// Cells per body extent at the coarsest and finest level, and the boxes' reach as a fraction
/// of the extent: at 1/160 a 1.8 m human gets 11 mm cells, finer than a pixel of a 128x128
/// view of it; a reach of 1/8 (22 cm) holds clothing well off the bones.
const COARSEST_PER_EXTENT: f32 = 10.0;
const FINEST_PER_EXTENT: f32 = 160.0;
pub const REACH_PER_EXTENT: f32 = 0.125;

impl GridConfig {
    /// The default grid for a skeleton with these bone lengths whose posed bounds have a
    /// diagonal of `extent` metres.
    pub fn for_body(bone_lengths: Vec<f32>, extent: f32) -> Self {
        Self {
            levels: 8,
            features: 2,
            table_log2: 16,
            coarsest_cell: extent / COARSEST_PER_EXTENT,
            finest_cell: extent / FINEST_PER_EXTENT,
            reach: extent * REACH_PER_EXTENT,
            top_bones: 3,
            bone_lengths,
        }
    }

    /// Features per point after the lookup.
    pub fn width(&self) -> usize {
        self.levels * self.features
    }

    pub fn table_size(&self) -> usize {
        1 << self.table_log2
    }

    fn top(&self) -> usize {
        self.top_bones.min(self.bone_lengths.len()).max(1)
    }

    /// Table rows a point touches: levels x bones x 8 corners.
    pub fn corners(&self) -> usize {
        self.levels * self.top() * 8
    }

    /// Every level's cell and its per-bone grids.
    pub fn layout(&self) -> Vec<Level> {
        let table = self.table_size();
        (0..self.levels)
            .map(|l| {
                let t = if self.levels > 1 { l as f32 / (self.levels - 1) as f32 } else { 1.0 };
                let cell = self.coarsest_cell * (self.finest_cell / self.coarsest_cell).powf(t);
                let across = ((2.0 * self.reach) / cell).ceil() as usize + 1;
                let dims: Vec<[usize; 3]> =
                    self.bone_lengths.iter().map(|&len| [across, ((len + 2.0 * self.reach) / cell).ceil() as usize + 1, across]).collect();
                let mut offsets = Vec::with_capacity(dims.len());
                let mut total = 0usize;
                for d in &dims {
                    offsets.push(total);
                    total += d[0] * d[1] * d[2];
                }
                Level { cell, dims, offsets, dense: total <= table, table_offset: l * table, table_mask: table - 1 }
            })
            .collect()
    }

    /// A grid with features uniform in +-1e-4 (instant-NGP's start) from our own seeded stream.
    pub fn init(&self, device: &Device, seed: u64) -> FeatureGrid {
        let mut stream = crate::synth::trace::Stream::new(seed, 0x6121D, 0);
        let n = self.levels * self.table_size();
        let values: Vec<f32> = (0..n * self.features).map(|_| ((stream.uniform() * 2.0 - 1.0) * 1e-4) as f32).collect();
        FeatureGrid {
            table: Param::from_tensor(Tensor::from_data(TensorData::new(values, [n, self.features]), device)),
            config: self.clone(),
            active_levels: self.levels as f32,
            composite: false,
        }
    }
}

/// One level: its cell (m), each bone's grid size in vertices and, for a dense level, where
/// each bone's grid starts in the level's table.
#[derive(Clone, Debug)]
pub struct Level {
    pub cell: f32,
    pub dims: Vec<[usize; 3]>,
    pub offsets: Vec<usize>,
    pub dense: bool,
    table_offset: usize,
    table_mask: usize,
}

impl Level {
    /// The table row of vertex `v` of bone `bone`'s grid.
    fn row(&self, bone: usize, v: [usize; 3]) -> usize {
        let within = if self.dense {
            let d = self.dims[bone];
            self.offsets[bone] + v[0] + d[0] * (v[1] + d[1] * v[2])
        } else {
            let h =
                (v[0] as u32) ^ (v[1] as u32).wrapping_mul(2_654_435_761) ^ (v[2] as u32).wrapping_mul(805_459_861) ^ (bone as u32).wrapping_mul(3_674_653_429);
            h as usize & self.table_mask
        };
        self.table_offset + within
    }
}

/// A posed bone on the CPU: its local axes in world space, its head and its length.
#[derive(Clone, Copy, Debug)]
pub struct BoneFrame {
    pub axes: [[f32; 3]; 3],
    pub origin: [f32; 3],
    pub length: f32,
}

impl BoneFrame {
    fn to_local(&self, p: [f32; 3]) -> [f32; 3] {
        let r = [p[0] - self.origin[0], p[1] - self.origin[1], p[2] - self.origin[2]];
        self.axes.map(|a| a[0] * r[0] + a[1] * r[1] + a[2] * r[2])
    }
}

/// The learnable table: `levels x 2^table_log2` rows of `features`.
#[derive(Module, Debug)]
pub struct FeatureGrid {
    pub table: Param<Tensor<2>>,
    #[module(skip)]
    pub config: GridConfig,
    /// How many levels, coarsest first, contribute (fractional: the next one fades in); the
    /// trainer sets it for a coarse-to-fine schedule, all of them otherwise.
    #[module(skip)]
    pub active_levels: f32,
    /// How the lookup runs: the fused op (default) or, for comparison, the composite of tensor
    /// ops it replaced.
    #[module(skip)]
    pub composite: bool,
}

/// How the skinning and the capsule prior are shaped (shared with the MLP field).
#[derive(Clone, Copy, Debug)]
pub struct Skinning {
    /// The factor on squared distance in the softmax's logits.
    pub sharpness: f32,
    pub prior_radius: f32,
}

/// The plan of a lookup of `N` points: `N x corners` table rows and their coefficients
/// (point-major), with their derivatives along the world axes (`[N x corners, 3]`) when asked;
/// the capsule prior and its gradient (`[N, 3]`).
#[derive(Clone, Debug, Default)]
pub struct Lookup {
    pub rows: Vec<u32>,
    pub coefficients: Vec<f32>,
    pub coefficient_tangents: Vec<f32>,
    pub prior: Vec<f32>,
    pub prior_tangents: Vec<f32>,
}

/// Plans the lookup of `points` (`[N * 3]`, world) in the bones `frames`.
pub fn lookup(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: &[f32], tangents: bool) -> Lookup {
    let n = points.len() / 3;
    let c = config.corners();
    let mut plan = Lookup {
        rows: vec![0; n * c],
        coefficients: vec![0.0; n * c],
        coefficient_tangents: if tangents { vec![0.0; n * c * 3] } else { Vec::new() },
        prior: vec![0.0; n],
        prior_tangents: if tangents { vec![0.0; n * 3] } else { Vec::new() },
    };
    // Points in chunks across threads; each chunk writes its own slices of the plan.
    const CHUNK: usize = 64;
    let tangent_chunks: Vec<&mut [f32]> =
        if tangents { plan.coefficient_tangents.chunks_mut(CHUNK * c * 3).collect() } else { (0..n.div_ceil(CHUNK)).map(|_| &mut [][..]).collect() };
    let prior_tangent_chunks: Vec<&mut [f32]> =
        if tangents { plan.prior_tangents.chunks_mut(CHUNK * 3).collect() } else { (0..n.div_ceil(CHUNK)).map(|_| &mut [][..]).collect() };
    plan.rows
        .par_chunks_mut(CHUNK * c)
        .zip(plan.coefficients.par_chunks_mut(CHUNK * c))
        .zip(plan.prior.par_chunks_mut(CHUNK))
        .zip(tangent_chunks.into_par_iter().zip(prior_tangent_chunks))
        .enumerate()
        .for_each(|(chunk, (((rows, coefficients), prior), (d_coefficients, d_prior)))| {
            let mut scratch = Scratch::default();
            for k in 0..prior.len() {
                let i = chunk * CHUNK + k;
                let point = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
                let span = k * c..(k + 1) * c;
                let d_coefficients = if tangents { Some(&mut d_coefficients[k * c * 3..(k + 1) * c * 3]) } else { None };
                let d_prior = if tangents { Some(&mut d_prior[k * 3..k * 3 + 3]) } else { None };
                prior[k] = plan_point(
                    config,
                    levels,
                    frames,
                    skinning,
                    point,
                    &mut scratch,
                    &mut rows[span.clone()],
                    &mut coefficients[span],
                    d_coefficients,
                    d_prior,
                );
            }
        });
    plan
}

/// One bone near a point: its index, skinning weight and the weight's gradient, the point in
/// its frame.
struct Near {
    bone: usize,
    weight: f32,
    d_weight: [f32; 3],
    local: [f32; 3],
}

/// Buffers one thread reuses from point to point (a point's plan allocates nothing).
#[derive(Default)]
struct Scratch {
    /// Per bone: squared distance to its segment, index, the distance's world gradient, the
    /// point in its frame.
    all: Vec<(f32, usize, [f32; 3], [f32; 3])>,
    near: Vec<Near>,
}

/// Plans one point's corners; returns its capsule prior SDF.
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
    mut d_coefficients: Option<&mut [f32]>,
    d_prior: Option<&mut [f32]>,
) -> f32 {
    // Squared distance to every bone segment and its world gradient 2 R offset.
    let all = &mut scratch.all;
    all.clear();
    all.extend(frames.iter().enumerate().map(|(b, f)| {
        let local = f.to_local(point);
        let offset = [local[0], local[1] - local[1].clamp(0.0, f.length), local[2]];
        let d2 = offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2];
        let g = [0, 1, 2].map(|a| 2.0 * (f.axes[0][a] * offset[0] + f.axes[1][a] * offset[1] + f.axes[2][a] * offset[2]));
        (d2, b, g, local)
    }));
    let top = config.top_bones.min(all.len()).max(1);
    if top < all.len() {
        all.select_nth_unstable_by(top - 1, |a, b| a.0.total_cmp(&b.0));
    }
    let chosen = &mut all[..top];
    chosen.sort_unstable_by_key(|a| a.1);
    // Softmax over the chosen bones (shifted by the largest logit) and its gradient.
    let max = chosen.iter().map(|a| a.0 * skinning.sharpness).fold(f32::NEG_INFINITY, f32::max);
    let near = &mut scratch.near;
    near.clear();
    near.extend(chosen.iter().map(|a| Near {
        bone: a.1,
        weight: (a.0 * skinning.sharpness - max).exp(),
        d_weight: a.2.map(|g| g * skinning.sharpness),
        local: a.3,
    }));
    let sum: f32 = near.iter().map(|nb| nb.weight).sum();
    for nb in near.iter_mut() {
        nb.weight /= sum;
    }
    // d w_j = w_j (d logit_j - sum_k w_k d logit_k); `d_weight` holds d logit_j until here.
    let mean_d_logit = [0, 1, 2].map(|x| near.iter().map(|nb| nb.weight * nb.d_weight[x]).sum::<f32>());
    for nb in near.iter_mut() {
        nb.d_weight = [0, 1, 2].map(|x| nb.weight * (nb.d_weight[x] - mean_d_logit[x]));
    }
    let near = &scratch.near;
    let chosen = &scratch.all[..top];
    // The capsule prior: skinning-weighted distance to the segments, minus the radius.
    let mut prior = -skinning.prior_radius;
    let mut gradient = [0.0f32; 3];
    for (j, nb) in near.iter().enumerate() {
        let distance = (chosen[j].0 + 1e-8).sqrt();
        prior += nb.weight * distance;
        for x in 0..3 {
            gradient[x] += nb.d_weight[x] * distance + nb.weight * chosen[j].2[x] / (2.0 * distance);
        }
    }
    if let Some(d) = d_prior {
        d.copy_from_slice(&gradient);
    }
    let mut k = 0;
    for level in levels {
        for nb in near {
            let frame = &frames[nb.bone];
            let dims = level.dims[nb.bone];
            // Grid coordinates, clamped to the box (a clamped axis has no spatial derivative).
            let mut base = [0usize; 3];
            let mut fraction = [0.0f32; 3];
            let mut inside = [true; 3];
            for m in 0..3 {
                let top_vertex = (dims[m] - 1) as f32;
                let mut u = (nb.local[m] + config.reach) / level.cell;
                if !(u > 0.0) {
                    u = 0.0;
                    inside[m] = false;
                } else if u >= top_vertex {
                    u = top_vertex;
                    inside[m] = false;
                }
                let cell = (u.floor() as usize).min(dims[m] - 2);
                base[m] = cell;
                fraction[m] = u - cell as f32;
            }
            // d u_m / d x = (local axis m) / cell on axes inside the box.
            let du: [[f32; 3]; 3] = [0, 1, 2].map(|m| if inside[m] { frame.axes[m].map(|a| a / level.cell) } else { [0.0; 3] });
            for corner in 0..8 {
                let bit = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
                let factor = [0, 1, 2].map(|m| if bit[m] == 1 { fraction[m] } else { 1.0 - fraction[m] });
                let trilinear = factor[0] * factor[1] * factor[2];
                rows[k] = level.row(nb.bone, [base[0] + bit[0], base[1] + bit[1], base[2] + bit[2]]) as u32;
                coefficients[k] = nb.weight * trilinear;
                if let Some(d) = d_coefficients.as_deref_mut() {
                    // d trilinear / d u_m: the other two factors, signed by the corner's side.
                    let d_tri = [0, 1, 2].map(|m| {
                        let sign = if bit[m] == 1 { 1.0 } else { -1.0 };
                        sign * factor[(m + 1) % 3] * factor[(m + 2) % 3]
                    });
                    for x in 0..3 {
                        let spatial = d_tri[0] * du[0][x] + d_tri[1] * du[1][x] + d_tri[2] * du[2][x];
                        d[k * 3 + x] = nb.d_weight[x] * trilinear + nb.weight * spatial;
                    }
                }
                k += 1;
            }
        }
    }
    prior
}

/// What the grid gives a batch of points: features `[N, W]` and the prior `[N]`, with their
/// derivatives along the world axes (`[3N, W]` axis-major, `[3, N]`) when asked.
pub struct GridFeatures {
    pub features: Tensor<2>,
    pub prior: Tensor<1>,
    pub tangents: Option<(Tensor<2>, Tensor<2>)>,
}

impl FeatureGrid {
    /// Plans the lookup of `points` (a tensor) in the posed bones `frames`.
    fn plan(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> (Lookup, usize) {
        let [n, _] = points.dims();
        let values = points.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_else(|_| vec![f32::NAN; n * 3]);
        let levels = self.config.layout();
        (lookup(&self.config, &levels, frames, skinning, &values, tangents), n)
    }

    /// Each level's weight: levels beyond `active_levels` are faded out (coarse to fine).
    fn fade(&self) -> Vec<f32> {
        (0..self.config.levels).map(|l| (self.active_levels - l as f32).clamp(0.0, 1.0)).collect()
    }

    /// Looks `points` up in the posed bones `frames`.
    pub fn encode(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> GridFeatures {
        if self.composite {
            self.encode_composite(points, frames, skinning, tangents)
        } else {
            self.encode_fused(points, frames, skinning, tangents)
        }
    }

    /// The lookup as one fused op (`interpolate`).
    fn encode_fused(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> GridFeatures {
        let device = points.device();
        let config = &self.config;
        let (plan, n) = self.plan(points, frames, skinning, tangents);
        let width = config.levels * config.features;
        let fused = super::interpolate::Plan {
            points: n,
            levels: config.levels,
            corners: config.corners() / config.levels,
            features: config.features,
            rows: plan.rows,
            coefficients: plan.coefficients,
            tangents: tangents.then_some(plan.coefficient_tangents),
            fade: self.fade(),
        };
        let out = super::interpolate::interpolate(self.table.val(), fused);
        let features = out.clone().slice([0..n, 0..width]);
        let prior = Tensor::from_data(TensorData::new(plan.prior, [n]), &device);
        let tangents = tangents.then(|| {
            let prior_tangents: Tensor<2> = Tensor::from_data(TensorData::new(plan.prior_tangents, [n, 3]), &device);
            (out.slice([n..4 * n, 0..width]), prior_tangents.transpose())
        });
        GridFeatures { features, prior, tangents }
    }

    /// The same lookup as a composite of tensor ops (`select` of every corner's row, a product
    /// and a sum): the reference the fused op is tested against, and the step benchmark's
    /// "before".
    fn encode_composite(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> GridFeatures {
        let device = points.device();
        let config = &self.config;
        let (plan, n) = self.plan(points, frames, skinning, tangents);
        let corners = config.corners() / config.levels;
        let m = plan.rows.len();
        let rows_index: Tensor<1, Int> = Tensor::from_data(TensorData::new(plan.rows.iter().map(|&r| r as i64).collect::<Vec<_>>(), [m]), &device);
        let rows = self.table.val().select(0, rows_index); // [M, F]
        let f = config.features;
        let coefficients: Tensor<2> = Tensor::from_data(TensorData::new(plan.coefficients, [m, 1]), &device);
        let features = (rows.clone() * coefficients).reshape([n, config.levels, corners, f]).sum_dim(2).reshape([n, config.levels * f]);
        let prior = Tensor::from_data(TensorData::new(plan.prior, [n]), &device);
        let fade: Vec<f32> = self.fade().into_iter().flat_map(|w| std::iter::repeat_n(w, f)).collect();
        let fade: Tensor<2> = Tensor::from_data(TensorData::new(fade, [1, config.levels * f]), &device);
        let features = features * fade.clone();
        let tangents = tangents.then(|| {
            let d: Tensor<2> = Tensor::from_data(TensorData::new(plan.coefficient_tangents, [m, 3]), &device);
            let d = d.transpose().reshape([3, m, 1]);
            let feature_tangents = (rows.unsqueeze_dim::<3>(0) * d).reshape([3 * n, config.levels, corners, f]).sum_dim(2).reshape([3 * n, config.levels * f]);
            let prior_tangents: Tensor<2> = Tensor::from_data(TensorData::new(plan.prior_tangents, [n, 3]), &device);
            (feature_tangents * fade, prior_tangents.transpose())
        });
        GridFeatures { features, prior, tangents }
    }
}
