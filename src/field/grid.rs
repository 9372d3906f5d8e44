//! Multiresolution feature grids in bone-local coordinates, the capacity of the `grid` field.
//!
//! Every bone owns a box around its segment (its reach follows the body's size; the root's, which
//! carries loose clothing, reaches as far as the training masks show the body), and every
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
//! gradient stays exact. The tensor side is then one fused op (`interpolate`) whose backward
//! scatters into the table. The sample points are constants of the plan: gradients reach the
//! table, not the points. Where nothing is differentiated (a ray's search for the body, most of
//! a step's points, and every lookup of a render) the plan is never stored: each point's
//! corners are summed as they are found (`features_on_host`).

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
    /// How points far from every bone follow the root (none: by distance alone, as grids
    /// before it).
    #[serde(default)]
    pub root: Option<RootSkinning>,
}

/// The root bone's part in the skinning. Its distance is capped at `cap` (m), so a point
/// farther than that from every bone (loose clothing: a skirt's hem lies 25-30 cm from the
/// thighs inside it) follows the root rather than the nearest limb, whose swing would drag it;
/// and a learned preference, a dense grid of logits in the root's frame (`cell` m, reaching
/// `reach` m beyond its segment), moves the border between the root and the limbs to where
/// the images say it is. The capsule prior keeps the true distances, up to the cap when the
/// body is loose (`prior_capped`).
#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct RootSkinning {
    pub bone: usize,
    pub cap: f32,
    pub cell: f32,
    /// How far (m) the preference grid, and the root's feature grids, reach beyond its segment.
    pub reach: f32,
    /// Whether the root's feature grids reach as far as its preference grid (`reach`), in a
    /// table of their own, rather than as far as the other bones' (`GridConfig::reach`): what
    /// the root carries, loose clothing, can lie beyond every bone's box (a skirt's hem 0.5 m
    /// from the pelvis's segment), and a grid's features are constant beyond its border.
    /// Runs before it: false.
    #[serde(default)]
    pub features_reach_body: bool,
    /// Whether the capsule prior stops growing at the root's `cap` (less its radius): beyond
    /// it the body is the root's, and so is its shape. The prior is the distance to the
    /// nearest bones, so a skirt's hem, carried rigidly by the root, would otherwise get a
    /// prior that moves with the thighs swinging inside it (lower where a leg comes near) and
    /// the root's residual could not hold it still. Runs before it: false.
    #[serde(default)]
    pub prior_capped: bool,
    /// Whether the capped prior bends into its cap (`saturate`): its slope falling from 1 at the
    /// capsule's surface to 0 at twice the cap, rather than stopping dead at the cap. At a corner
    /// the residual must turn its own slope from 0 to 1 at once wherever the surface crosses the
    /// cap (a skirt below the hips, a backpack's sides), which the Eikonal and curvature terms
    /// resist: on human-dressed the fitted SDF's gradient length there strayed twice as far from
    /// 1 as elsewhere on the skirt (0.26 against 0.11-0.12; 0.15 with the knee). Measured, not
    /// the default (`[field] prior_knee`): it gained on human-dressed and lost on the 128x128
    /// dressed capture, whose skirt it left faceted in a novel view. Runs before it: false.
    #[serde(default)]
    pub prior_knee: bool,
}

/// Cells of the root's preference grid per body extent: 5 cm on a 2 m human, about a
/// pixel of a 64x64 view.
const ROOT_CELLS_PER_EXTENT: f32 = 40.0;

impl RootSkinning {
    /// The root's skinning on a body of `extent` m whose bones' feature grids reach `reach` m
    /// beyond their segments. Its preference grid reaches twice as far; where the body lies
    /// farther than `reach` from every bone (`loose`: how far from the root's segment it then
    /// reaches, e.g. a skirt's hem 0.5 m), it and the root's feature grids reach that far, so
    /// whatever the root carries is inside them (beyond its border a grid is constant), and
    /// the capsule prior stops at the cap, so what the root carries keeps its shape while the
    /// limbs move inside it (`human-dressed` seed 0: foreground novel pose 22.24 -> 23.63 dB,
    /// novel view 17.91 -> 21.34 dB).
    pub fn for_body(bone: usize, cap: f32, reach: f32, loose: Option<f32>, extent: f32) -> Self {
        let cell = extent / ROOT_CELLS_PER_EXTENT;
        match loose {
            Some(far) => Self { bone, cap, cell, reach: far.max(2.0 * reach), features_reach_body: true, prior_capped: true, prior_knee: false },
            None => Self { bone, cap, cell, reach: 2.0 * reach, features_reach_body: false, prior_capped: false, prior_knee: false },
        }
    }

    /// Vertices of the preference grid along the root's local axes.
    fn dims(&self, length: f32) -> [usize; 3] {
        let across = ((2.0 * self.reach) / self.cell).ceil() as usize + 1;
        [across, ((length + 2.0 * self.reach) / self.cell).ceil() as usize + 1, across]
    }
}

/// Cells per body extent at the coarsest and finest level, and the boxes' reach as a fraction
/// of the extent: at 1/160 a 1.8 m human gets 11 mm cells, finer than a pixel of a 128x128
/// view of it; a reach of 1/8 (22 cm) holds clothing well off the bones.
const COARSEST_PER_EXTENT: f32 = 10.0;
pub const FINEST_PER_EXTENT: f32 = 160.0;
pub const REACH_PER_EXTENT: f32 = 0.125;

/// The most entries a grid may allocate (feature rows times features, or a dense preference
/// grid's vertices): 2^28 f32s are 1 GiB, far beyond any fit's (a human's is about 2^21).
const MAX_ENTRIES: f64 = (1u64 << 28) as f64;

/// Checks that a length read from a file is finite and positive (`what` names it).
fn positive(what: &str, value: f32) -> Result<(), String> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(format!("{what}: {value} is not a finite positive length"))
    }
}

/// Vertices of a box reaching `reach` around a segment of `length` at `cell` (f64, so a
/// hostile size cannot overflow).
fn box_vertices(length: f32, reach: f32, cell: f32) -> f64 {
    let across = (2.0 * reach as f64 / cell as f64).ceil() + 1.0;
    across * across * ((length as f64 + 2.0 * reach as f64) / cell as f64).ceil() + 1.0
}

impl GridConfig {
    /// Checks a recorded grid (a checkpoint's `state.json`) before anything is allocated from
    /// it: every length finite and positive, counts in range, and no table or dense grid over
    /// `MAX_ENTRIES`. The error names the key.
    pub fn check(&self, bones: usize) -> Result<(), String> {
        if !(1..=32).contains(&self.levels) || !(1..=64).contains(&self.features) || !(1..=MAX_TOP_BONES).contains(&self.top_bones) {
            return Err(format!(
                "levels, features, top_bones: {}, {}, {} out of range (1-32, 1-64, 1-{MAX_TOP_BONES})",
                self.levels, self.features, self.top_bones
            ));
        }
        if !(1..=26).contains(&self.table_log2) {
            return Err(format!("table_log2: {} out of range (1-26)", self.table_log2));
        }
        positive("coarsest_cell", self.coarsest_cell)?;
        positive("finest_cell", self.finest_cell)?;
        if !(self.reach.is_finite() && self.reach >= 0.0) {
            return Err(format!("reach: {} is not a finite length >= 0", self.reach));
        }
        if self.bone_lengths.len() != bones {
            return Err(format!("bone_lengths: {} lengths for {bones} bones", self.bone_lengths.len()));
        }
        for (k, &length) in self.bone_lengths.iter().enumerate() {
            positive(&format!("bone_lengths[{k}]"), length)?;
        }
        if (self.table_rows() * self.features) as f64 > MAX_ENTRIES {
            return Err(format!("table_log2, levels, features: a table of {} entries is more than {MAX_ENTRIES} allowed", self.table_rows() * self.features));
        }
        if let Some(root) = &self.root {
            if root.bone >= bones {
                return Err(format!("root.bone: {} is not a bone (there are {bones})", root.bone));
            }
            positive("root.cell", root.cell)?;
            if !(root.cap.is_finite() && root.cap >= 0.0 && root.reach.is_finite() && root.reach >= 0.0) {
                return Err(format!("root.cap, root.reach: {}, {} are not finite lengths >= 0", root.cap, root.reach));
            }
            let dense = box_vertices(self.bone_lengths[root.bone], root.reach, root.cell);
            if dense > MAX_ENTRIES {
                return Err(format!("root.reach, root.cell: a preference grid of {dense:e} vertices is more than {MAX_ENTRIES} allowed"));
            }
        }
        // Each level's boxes are counted to decide whether they fit the table: bound them too.
        let finest = self.coarsest_cell.min(self.finest_cell);
        let largest = (0..bones).map(|b| box_vertices(self.bone_lengths[b], self.bone_reach(b), finest)).fold(0.0, f64::max);
        if largest * bones as f64 > 1e15 {
            return Err(format!("coarsest_cell, finest_cell, reach: boxes of {largest:e} vertices at the finest cell cannot be indexed"));
        }
        Ok(())
    }

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
            root: None,
        }
    }

    /// Features per point after the lookup.
    pub fn width(&self) -> usize {
        self.levels * self.features
    }

    pub fn table_size(&self) -> usize {
        1 << self.table_log2
    }

    /// How far (m) a bone's feature grids reach beyond its segment.
    pub fn bone_reach(&self, bone: usize) -> f32 {
        match self.root {
            Some(root) if root.bone == bone && root.features_reach_body => root.reach,
            _ => self.reach,
        }
    }

    /// Bones a point is looked up in: `top_bones`, at most every bone and at most
    /// `MAX_TOP_BONES` (a point's plan holds that many in fixed arrays).
    pub fn top(&self) -> usize {
        self.top_bones.min(self.bone_lengths.len()).clamp(1, MAX_TOP_BONES)
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
                let dims: Vec<[usize; 3]> = self
                    .bone_lengths
                    .iter()
                    .enumerate()
                    .map(|(bone, &len)| {
                        let reach = self.bone_reach(bone);
                        let across = ((2.0 * reach) / cell).ceil() as usize + 1;
                        [across, ((len + 2.0 * reach) / cell).ceil() as usize + 1, across]
                    })
                    .collect();
                // The root's grids, when they reach loose clothing, have a table of their own per
                // level (after the other bones'): in a shared one their entries, touched by nearly
                // every point of the body (the root is one of its bones), collided with every
                // bone's (with them reaching the whole skeleton: `human-sun-128` 0.4 and 0.8 dB
                // lower at seeds 0 and 1, `dog-sun` 3.4 dB).
                let own = self.own_root_table();
                let vertices = |d: &[usize; 3]| d[0] * d[1] * d[2];
                let mut offsets = Vec::with_capacity(dims.len());
                let mut total = 0usize;
                for (bone, d) in dims.iter().enumerate() {
                    offsets.push(if own == Some(bone) { 0 } else { total });
                    if own != Some(bone) {
                        total += vertices(d);
                    }
                }
                let rows = self.table_rows() / self.levels;
                let root = own.map(|bone| RootTable { bone, dense: vertices(&dims[bone]) <= table, offset: l * rows + table });
                Level { cell, dims, offsets, dense: total <= table, table_offset: l * rows, table_mask: table - 1, root, active: true }
            })
            .collect()
    }

    /// The root bone, when its grids have a table of their own (`RootSkinning::features_reach_body`).
    fn own_root_table(&self) -> Option<usize> {
        self.root.filter(|r| r.features_reach_body).map(|r| r.bone)
    }

    /// Rows of the feature table: a table per level, and one more per level for the root's
    /// grids when they have their own.
    pub fn table_rows(&self) -> usize {
        self.levels * self.table_size() * if self.own_root_table().is_some() { 2 } else { 1 }
    }

    /// A grid with features uniform in +-1e-4 (instant-NGP's start) from our own seeded stream.
    pub fn init(&self, device: &Device, seed: u64) -> FeatureGrid {
        let mut stream = crate::random::Stream::new(seed, 0x6121D, 0);
        let n = self.table_rows();
        let values: Vec<f32> = (0..n * self.features).map(|_| ((stream.uniform() * 2.0 - 1.0) * 1e-4) as f32).collect();
        // The root's preference starts at zero: the skinning starts from distances alone.
        let root_preference = self.root.map(|root| {
            let [a, b, c] = root.dims(self.bone_lengths.get(root.bone).copied().unwrap_or(0.0));
            Param::from_tensor(Tensor::zeros([a * b * c, 1], device))
        });
        FeatureGrid {
            table: Param::from_tensor(Tensor::from_data(TensorData::new(values, [n, self.features]), device)),
            root_preference,
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
    /// The root's own table at this level, when it has one.
    pub root: Option<RootTable>,
    /// Whether the level contributes (coarse to fine: not yet faded in). An inactive level's
    /// corners are left out of the plan (row 0, coefficient 0), which is what its zero fade
    /// would make of them anyway.
    pub active: bool,
}

/// Where the root's grids live when they have a table of their own.
#[derive(Clone, Copy, Debug)]
pub struct RootTable {
    pub bone: usize,
    pub dense: bool,
    pub offset: usize,
}

/// instant-NGP's spatial hash's primes for the second and third axes, and one for the bone.
const HASH_PRIMES: [u32; 3] = [2_654_435_761, 805_459_861, 3_674_653_429];

impl Level {
    /// The table rows of the 8 vertices of the cell whose lowest vertex is `base` in bone
    /// `bone`'s grid, in `trilinear`'s corner order (bit 0 the x side, bit 1 y, bit 2 z):
    /// `row` of each, with each axis's part of the index or hash taken once for both of its
    /// sides rather than once per corner.
    pub fn corner_rows(&self, bone: usize, base: [usize; 3]) -> [usize; 8] {
        let (offset, dense) = match self.root {
            Some(root) if root.bone == bone => (root.offset, root.dense),
            _ => (self.table_offset + if self.dense { self.offsets[bone] } else { 0 }, self.dense),
        };
        let mut rows = [0usize; 8];
        if dense {
            let d = self.dims[bone];
            let parts = [0, 1].map(|b| [base[0] + b, d[0] * (base[1] + b), d[0] * d[1] * (base[2] + b)]);
            for (k, row) in rows.iter_mut().enumerate() {
                *row = offset + parts[k & 1][0] + parts[(k >> 1) & 1][1] + parts[(k >> 2) & 1][2];
            }
        } else {
            let salt = (bone as u32).wrapping_mul(HASH_PRIMES[2]);
            let parts = [0, 1].map(|b| {
                [(base[0] + b) as u32 ^ salt, ((base[1] + b) as u32).wrapping_mul(HASH_PRIMES[0]), ((base[2] + b) as u32).wrapping_mul(HASH_PRIMES[1])]
            });
            for (k, row) in rows.iter_mut().enumerate() {
                *row = offset + ((parts[k & 1][0] ^ parts[(k >> 1) & 1][1] ^ parts[(k >> 2) & 1][2]) as usize & self.table_mask);
            }
        }
        rows
    }

    /// The table row of vertex `v` of bone `bone`'s grid.
    pub fn row(&self, bone: usize, v: [usize; 3]) -> usize {
        let d = self.dims[bone];
        let hashed = || {
            let h = (v[0] as u32)
                ^ (v[1] as u32).wrapping_mul(HASH_PRIMES[0])
                ^ (v[2] as u32).wrapping_mul(HASH_PRIMES[1])
                ^ (bone as u32).wrapping_mul(HASH_PRIMES[2]);
            h as usize & self.table_mask
        };
        let within_grid = v[0] + d[0] * (v[1] + d[1] * v[2]);
        match self.root {
            Some(root) if root.bone == bone => root.offset + if root.dense { within_grid } else { hashed() },
            _ => self.table_offset + if self.dense { self.offsets[bone] + within_grid } else { hashed() },
        }
    }
}

pub use crate::skeleton::BoneFrame;

/// The learnable table: `levels x 2^table_log2` rows of `features`.
#[derive(Module, Debug)]
pub struct FeatureGrid {
    pub table: Param<Tensor<2>>,
    /// The root's learned skinning preference (`RootSkinning`): one logit per vertex.
    pub root_preference: Option<Param<Tensor<2>>>,
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
    /// The root bone and the distance (m) beyond which the skinning sees it no farther
    /// (`RootSkinning::cap`).
    pub root: Option<(usize, f32)>,
    /// The most the capsule prior gives (m), when capped (`RootSkinning::prior_capped`).
    pub prior_cap: Option<f32>,
    /// Half the width (m) of the knee over which the capped prior's slope falls from 1 to 0
    /// (`RootSkinning::prior_knee`: the cap itself, so the knee starts at the capsule's surface);
    /// 0: a corner at the cap.
    pub prior_knee: f32,
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

/// The most bones a point is looked up in (the schedule's bound on `top_bones`).
pub const MAX_TOP_BONES: usize = 8;

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
}

/// What the plan says about one point besides its feature rows.
#[derive(Clone, Copy, Default)]
struct PointSkin {
    logits: [f32; MAX_TOP_BONES],
    logit_tangents: [[f32; 3]; MAX_TOP_BONES],
    root_slot: Option<usize>,
    root_rows: [u32; 8],
    root_coefficients: [f32; 8],
    root_coefficient_tangents: [[f32; 3]; 8],
    prior: f32,
    prior_tangent: [f32; 3],
}

/// Plans the lookup of `points` (`[N * 3]`, world) in the bones `frames`.
pub fn lookup(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: &[f32], tangents: bool) -> Lookup {
    let n = points.len() / 3;
    let c = config.corners();
    let mut rows = vec![0u32; n * c];
    let mut coefficients = vec![0.0f32; n * c];
    let mut coefficient_tangents = if tangents { vec![0.0f32; n * c * 3] } else { Vec::new() };
    let mut skins = vec![PointSkin::default(); n];
    // Points in chunks across threads; each chunk writes its own slices of the plan.
    const CHUNK: usize = 64;
    let tangent_chunks: Vec<&mut [f32]> =
        if tangents { coefficient_tangents.chunks_mut(CHUNK * c * 3).collect() } else { (0..n.div_ceil(CHUNK)).map(|_| &mut [][..]).collect() };
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
                let d_coefficients = if tangents { Some(&mut d_coefficients[k * c * 3..(k + 1) * c * 3]) } else { None };
                *skin = plan_point(config, levels, frames, skinning, point, &mut scratch, &mut rows[span.clone()], &mut coefficients[span], d_coefficients);
            }
        });
    let top = config.top();
    let mut plan = Lookup { rows, coefficients, coefficient_tangents, ..Lookup::default() };
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
        }
    }
    plan
}

/// A bone's squared distance to a point: the true one (the capsule prior's) and the one the
/// skinning weighs (`Skinning::distance_squared`), each with its world gradient.
struct BoneDistance {
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
struct Scratch {
    /// The chosen bones' distances to the point, ascending by bone.
    all: Vec<BoneDistance>,
    /// Every bone's skinning's squared distance while choosing: (distance, bone).
    nearest: Vec<(f32, usize)>,
    /// A softmax's weights and their world gradients.
    weights: Vec<(f32, [f32; 3])>,
}

/// Softmax weights of logits `sharpness d2` over `(d2, gradient of d2)` pairs, with the
/// weights' world gradients `w_j (d logit_j - sum_k w_k d logit_k)`, into `out`.
fn softmax_with_gradient(out: &mut Vec<(f32, [f32; 3])>, terms: impl Iterator<Item = (f32, [f32; 3])>, sharpness: f32) {
    out.clear();
    out.extend(terms.map(|(d2, g)| (d2 * sharpness, g.map(|v| v * sharpness))));
    // Shifted by the largest logit, so the exponentials stay finite.
    let max = out.iter().map(|w| w.0).fold(f32::NEG_INFINITY, f32::max);
    for w in out.iter_mut() {
        w.0 = (w.0 - max).exp();
    }
    let sum: f32 = out.iter().map(|w| w.0).sum();
    for w in out.iter_mut() {
        w.0 /= sum;
    }
    let mean_d_logit = [0, 1, 2].map(|x| out.iter().map(|w| w.0 * w.1[x]).sum::<f32>());
    for w in out.iter_mut() {
        w.1 = [0, 1, 2].map(|x| w.0 * (w.1[x] - mean_d_logit[x]));
    }
}

/// The trilinear cell around a point: its lowest vertex, and per corner (bit 0 the x side,
/// bit 1 y, bit 2 z) its weight and the weight's world gradient (zero unless asked for).
struct Cell {
    base: [usize; 3],
    weights: [f32; 8],
    gradients: [[f32; 3]; 8],
}

/// The trilinear cell around `local` in a grid of `dims` vertices spaced `cell` apart from
/// `-reach` on each local axis, with the weights' world gradients (through the bone's `axes`)
/// when `TANGENTS`; a point outside the grid is clamped to its border (a clamped axis has no
/// spatial derivative).
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
    Cell { base, weights, gradients }
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
) -> PointSkin {
    let tangents = d_coefficients.is_some();
    let skin = skin_point(config, frames, skinning, point, scratch, tangents);
    let chosen = &scratch.all[..config.top().min(scratch.all.len())];
    match d_coefficients {
        Some(d) => visit_cells::<true>(config, levels, frames, chosen, |k, _, cell_rows, cell| {
            rows[k..k + 8].copy_from_slice(&cell_rows);
            coefficients[k..k + 8].copy_from_slice(&cell.weights);
            d[k * 3..(k + 8) * 3].copy_from_slice(cell.gradients.as_flattened());
        }),
        None => visit_cells::<false>(config, levels, frames, chosen, |k, _, cell_rows, cell| {
            rows[k..k + 8].copy_from_slice(&cell_rows);
            coefficients[k..k + 8].copy_from_slice(&cell.weights);
        }),
    }
    skin
}

/// A point's skinning: the `top` nearest bones chosen (left, ascending by bone, at the head of
/// `scratch.all`), their logits, the capsule prior and the root's preference corners, with
/// their world gradients when `tangents` says.
fn skin_point(config: &GridConfig, frames: &[BoneFrame], skinning: Skinning, point: [f32; 3], scratch: &mut Scratch, tangents: bool) -> PointSkin {
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
    // do not change), with their gradients.
    let lead = (0..chosen.len()).min_by(|&a, &b| chosen[a].skinning_d2.total_cmp(&chosen[b].skinning_d2)).unwrap_or(0);
    let (max, d_max) = (chosen[lead].skinning_d2 * skinning.sharpness, chosen[lead].skinning_gradient.map(|g| g * skinning.sharpness));
    for (j, a) in chosen.iter().enumerate() {
        skin.logits[j] = a.skinning_d2 * skinning.sharpness - max;
        skin.logit_tangents[j] = [0, 1, 2].map(|x| a.skinning_gradient[x] * skinning.sharpness - d_max[x]);
    }
    // The capsule prior: the distance to the segments, weighted by a softmax of the true
    // distances (the root's cap would mix distances that differ by the whole cap where the
    // weights turn, a gradient far steeper than a distance's), minus the radius.
    softmax_with_gradient(&mut scratch.weights, chosen.iter().map(|a| (a.d2, a.gradient)), skinning.sharpness);
    skin.prior = -skinning.prior_radius;
    for (a, &(weight, d_weight)) in chosen.iter().zip(&scratch.weights) {
        let distance = (a.d2 + 1e-8).sqrt();
        skin.prior += weight * distance;
        for x in 0..3 {
            skin.prior_tangent[x] += d_weight[x] * distance + weight * a.gradient[x] / (2.0 * distance);
        }
    }
    if let Some(cap) = skinning.prior_cap {
        let (value, slope) = saturate(skin.prior, cap, skinning.prior_knee);
        skin.prior = value;
        skin.prior_tangent = skin.prior_tangent.map(|t| t * slope);
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

/// The capsule prior `x` capped at `cap`, and its slope: unchanged up to `cap - knee`, then a
/// parabola whose slope falls linearly to 0 at `cap + knee`, where it reaches the cap; with no
/// knee, a corner at the cap.
pub fn saturate(x: f32, cap: f32, knee: f32) -> (f32, f32) {
    if knee <= 0.0 {
        return if x > cap { (cap, 0.0) } else { (x, 1.0) };
    }
    let into = x - (cap - knee);
    if into <= 0.0 {
        (x, 1.0)
    } else if into >= 2.0 * knee {
        (cap, 0.0)
    } else {
        (x - into * into / (4.0 * knee), 1.0 - into / (2.0 * knee))
    }
}

/// Every cell of a point's lookup in its `chosen` bones, level by level: `cell(k, level, rows,
/// cell)` with `k` the place of its first corner in the plan (bone, then level, then corner;
/// an inactive level's 8 places are skipped, left at row 0 and weight 0), the weights' world
/// gradients computed only when `TANGENTS`.
fn visit_cells<const TANGENTS: bool>(
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

/// The features `[N, W]` and capsule prior of `points` straight from the table on the host, for
/// points that need no gradient (the samples that search a ray for the body): the plan's
/// skinning and corners and the fused op's weighted sum in one pass, so no plan is stored and
/// read back. Per point `W + 1` values: its features, then its prior. `preference` is the root's
/// preference grid (one logit per vertex) when the grid has one; `fade` weighs each level.
#[allow(clippy::too_many_arguments)]
pub fn features_on_host(
    config: &GridConfig,
    levels: &[Level],
    frames: &[BoneFrame],
    skinning: Skinning,
    points: &[f32],
    table: &[f32],
    preference: Option<&[f32]>,
    fade: &[f32],
) -> Vec<f32> {
    let (f, l) = (config.features, config.levels);
    let w = l * f;
    let n = points.len() / 3;
    let mut out = vec![0.0f32; n * (w + 1)];
    const CHUNK: usize = 64;
    out.par_chunks_mut(CHUNK * (w + 1)).enumerate().for_each(|(chunk, out)| {
        let mut scratch = Scratch::default();
        let mut per_bone = vec![0.0f32; MAX_TOP_BONES * w];
        for (k, out) in out.chunks_mut(w + 1).enumerate() {
            let i = chunk * CHUNK + k;
            let point = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
            let skin = skin_point(config, frames, skinning, point, &mut scratch, false);
            let chosen = &scratch.all[..config.top().min(scratch.all.len())];
            per_bone.iter_mut().for_each(|v| *v = 0.0);
            visit_cells::<false>(config, levels, frames, chosen, |k, level, rows, cell| {
                // As the fused op sums: each coefficient times the level's fade, times the entry.
                let sums = &mut per_bone[(k / 8) * f..(k / 8 + 1) * f];
                for (&row, &weight) in rows.iter().zip(&cell.weights) {
                    super::interpolate::add_row(table, row as usize, weight * fade[level], sums);
                }
            });
            // The skinning weights: a softmax of the logits plus the root's preference.
            let mut logits = [0.0f32; MAX_TOP_BONES];
            logits[..chosen.len()].copy_from_slice(&skin.logits[..chosen.len()]);
            if let (Some(j), Some(preference)) = (skin.root_slot, preference) {
                let value: f32 =
                    skin.root_rows.iter().zip(&skin.root_coefficients).map(|(&r, &c)| c * preference.get(r as usize).copied().unwrap_or(f32::NAN)).sum();
                logits[j] += value;
            }
            let logits = &mut logits[..chosen.len()];
            let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            logits.iter_mut().for_each(|v| *v = (*v - max).exp());
            let total: f32 = logits.iter().sum();
            let (features, prior) = out.split_at_mut(w);
            for (j, &e) in logits.iter().enumerate() {
                let weight = e / total;
                features.iter_mut().zip(&per_bone[j * w..(j + 1) * w]).for_each(|(o, v)| *o += weight * v);
            }
            prior[0] = skin.prior;
        }
    });
    out
}

/// Points `[N, 3]` on the host, and N (NaN-filled if the backend cannot give them, which the fit
/// then reports as a non-finite loss rather than a panic).
fn host_points(points: Tensor<2>) -> (Vec<f32>, usize) {
    let [n, _] = points.dims();
    (points.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_else(|_| vec![f32::NAN; n * 3]), n)
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
        let (values, n) = host_points(points);
        (lookup(&self.config, &self.active_layout(), frames, skinning, &values, tangents), n)
    }

    /// `encode` where nothing asks for a gradient (the table is not tracked): planned and summed
    /// in one pass on the host (`features_on_host`), the same values (a test pins them).
    fn encode_without_gradients(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning) -> GridFeatures {
        let device = points.device();
        let (values, n) = host_points(points);
        let preference = self.root_preference.as_ref().map(|p| p.val());
        let lookup = super::interpolate::HostLookup {
            config: self.config.clone(),
            levels: self.active_layout(),
            frames: frames.to_vec(),
            skinning,
            points: values,
            fade: self.fade(),
            preference: preference.is_some(),
        };
        let preference = preference.unwrap_or_else(|| Tensor::zeros([1, 1], &device));
        let out = super::interpolate::lookup_without_gradients(self.table.val(), preference, lookup);
        let w = self.config.width();
        GridFeatures { features: out.clone().slice([0..n, 0..w]), prior: out.slice([0..n, w..w + 1]).reshape([n]), tangents: None }
    }

    /// The layout with each level marked active or not (coarse to fine).
    fn active_layout(&self) -> Vec<Level> {
        let mut levels = self.config.layout();
        for (l, level) in levels.iter_mut().enumerate() {
            level.active = (l as f32) < self.active_levels;
        }
        levels
    }

    /// Each level's weight: levels beyond `active_levels` are faded out (coarse to fine).
    fn fade(&self) -> Vec<f32> {
        (0..self.config.levels).map(|l| (self.active_levels - l as f32).clamp(0.0, 1.0)).collect()
    }

    /// Looks `points` up in the posed bones `frames`.
    pub fn encode(&self, points: Tensor<2>, frames: &[BoneFrame], skinning: Skinning, tangents: bool) -> GridFeatures {
        let device = points.device();
        if !tangents && !self.composite && !self.table.val().is_require_grad() {
            return self.encode_without_gradients(points, frames, skinning);
        }
        let (plan, n) = self.plan(points, frames, skinning, tangents);
        let (per_bone, per_bone_tangents, plan) =
            if self.composite { self.interpolate_composite(plan, n, tangents) } else { self.interpolate_fused(plan, n, tangents) };
        let prior = Tensor::from_data(TensorData::new(plan.prior.clone(), [n]), &device);
        let (features, feature_tangents) = self.blend(&plan, n, per_bone, per_bone_tangents, &device);
        let tangents = feature_tangents.map(|t| {
            let prior_tangents: Tensor<2> = Tensor::from_data(TensorData::new(plan.prior_tangents, [n, 3]), &device);
            (t, prior_tangents.transpose())
        });
        GridFeatures { features, prior, tangents }
    }

    /// Each chosen bone's features (`[N, K W]`) and their tangents (`[3N, K W]`) by the fused
    /// op (`interpolate`).
    #[allow(clippy::type_complexity)]
    fn interpolate_fused(&self, mut plan: Lookup, n: usize, tangents: bool) -> (Tensor<2>, Option<Tensor<2>>, Lookup) {
        let config = &self.config;
        let groups = config.top() * config.levels;
        let fused = super::interpolate::Plan {
            points: n,
            levels: groups,
            corners: 8,
            features: config.features,
            rows: std::mem::take(&mut plan.rows),
            coefficients: std::mem::take(&mut plan.coefficients),
            tangents: tangents.then(|| std::mem::take(&mut plan.coefficient_tangents)),
            fade: self.fade().into_iter().cycle().take(groups).collect(),
            table_parts: config.levels,
        };
        let out = super::interpolate::interpolate(self.table.val(), fused);
        let width = groups * config.features;
        let per_bone = out.clone().slice([0..n, 0..width]);
        let per_bone_tangents = tangents.then(|| out.slice([n..4 * n, 0..width]));
        (per_bone, per_bone_tangents, plan)
    }

    /// The same by a composite of tensor ops (`select` of every corner's row, a product and a
    /// sum): the reference the fused op is tested against, and the step benchmark's "before".
    #[allow(clippy::type_complexity)]
    fn interpolate_composite(&self, plan: Lookup, n: usize, tangents: bool) -> (Tensor<2>, Option<Tensor<2>>, Lookup) {
        let device = self.table.val().device();
        let config = &self.config;
        let groups = config.top() * config.levels;
        let f = config.features;
        let m = plan.rows.len();
        let rows_index: Tensor<1, Int> = Tensor::from_data(TensorData::new(plan.rows.iter().map(|&r| r as i64).collect::<Vec<_>>(), [m]), &device);
        let rows = self.table.val().select(0, rows_index); // [M, F]
        let coefficients: Tensor<2> = Tensor::from_data(TensorData::new(plan.coefficients.clone(), [m, 1]), &device);
        let fade: Vec<f32> = self.fade().into_iter().cycle().take(groups).flat_map(|w| std::iter::repeat_n(w, f)).collect();
        let fade: Tensor<2> = Tensor::from_data(TensorData::new(fade, [1, groups * f]), &device);
        let per_bone = (rows.clone() * coefficients).reshape([n, groups, 8, f]).sum_dim(2).reshape([n, groups * f]) * fade.clone();
        let per_bone_tangents = tangents.then(|| {
            let d: Tensor<2> = Tensor::from_data(TensorData::new(plan.coefficient_tangents.clone(), [m, 3]), &device);
            let d = d.transpose().reshape([3, m, 1]);
            (rows.unsqueeze_dim::<3>(0) * d).reshape([3 * n, groups, 8, f]).sum_dim(2).reshape([3 * n, groups * f]) * fade
        });
        (per_bone, per_bone_tangents, plan)
    }

    /// The features (`[N, W]`) as the chosen bones' features weighted by the skinning: a
    /// softmax of the planned logits plus the root's learned preference; and their tangents
    /// (`[3N, W]`), through the weights' gradients too.
    fn blend(&self, plan: &Lookup, n: usize, per_bone: Tensor<2>, per_bone_tangents: Option<Tensor<2>>, device: &Device) -> (Tensor<2>, Option<Tensor<2>>) {
        let config = &self.config;
        let (k, w) = (config.top(), config.width());
        let logits: Tensor<2> = Tensor::from_data(TensorData::new(plan.logits.clone(), [n, k]), device);
        let root_slot: Tensor<2> = Tensor::from_data(TensorData::new(plan.root_slot.clone(), [n, k]), device);
        let tangents = per_bone_tangents.is_some();
        // The root's preference at each point (and its gradient), by the same fused op.
        let preference = self.root_preference.as_ref().map(|table| {
            let lookup = super::interpolate::Plan {
                points: n,
                levels: 1,
                corners: 8,
                features: 1,
                rows: plan.root_rows.clone(),
                coefficients: plan.root_coefficients.clone(),
                tangents: tangents.then(|| plan.root_coefficient_tangents.clone()),
                fade: vec![1.0],
                table_parts: 1,
            };
            super::interpolate::interpolate(table.val(), lookup)
        });
        let logits = match &preference {
            Some(p) => logits + root_slot.clone() * p.clone().slice([0..n, 0..1]),
            None => logits,
        };
        let weights = burn::tensor::activation::softmax(logits, 1); // [N, K]
        let per_bone = per_bone.reshape([n, k, w]);
        let features = (per_bone.clone() * weights.clone().reshape([n, k, 1])).sum_dim(1).reshape([n, w]);
        let feature_tangents = per_bone_tangents.map(|d_per_bone| {
            let d_logits: Tensor<3> = Tensor::<2>::from_data(TensorData::new(plan.logit_tangents.clone(), [n * k, 3]), device).transpose().reshape([3, n, k]);
            let d_logits = match &preference {
                Some(p) => d_logits + root_slot.unsqueeze_dim::<3>(0) * p.clone().slice([n..4 * n, 0..1]).reshape([3, n, 1]),
                None => d_logits,
            };
            let weights = weights.unsqueeze_dim::<3>(0); // [1, N, K]
            let d_weights = weights.clone() * (d_logits.clone() - (weights.clone() * d_logits).sum_dim(2)); // [3, N, K]
            let through_weights = d_weights.reshape([3, n, k, 1]) * per_bone.unsqueeze_dim::<4>(0);
            let through_features = weights.reshape([1, n, k, 1]) * d_per_bone.reshape([3, n, k, w]);
            (through_weights + through_features).sum_dim(2).reshape([3 * n, w])
        });
        (features, feature_tangents)
    }
}
