//! The grid field's layout: its shape as the schedule and the body give it (`GridConfig`, the
//! root's skinning), validated, and each level's cell, per-bone grid sizes and place in the
//! table (`Level`, dense or hashed).

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
            Some(far) => Self { bone, cap, cell, reach: far.max(2.0 * reach), features_reach_body: true, prior_capped: true },
            None => Self { bone, cap, cell, reach: 2.0 * reach, features_reach_body: false, prior_capped: false },
        }
    }

    /// Vertices of the preference grid along the root's local axes.
    pub(super) fn dims(&self, length: f32) -> [usize; 3] {
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
}

/// The most bones a point is looked up in (the schedule's bound on `top_bones`).
pub const MAX_TOP_BONES: usize = 8;

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
pub(super) const HASH_PRIMES: [u32; 3] = [2_654_435_761, 805_459_861, 3_674_653_429];

impl Level {
    /// The table rows of the 8 vertices of the cell whose lowest vertex is `base` in bone
    /// `bone`'s grid, in `trilinear`'s corner order (bit 0 the x side, bit 1 y, bit 2 z):
    /// `row` of each, with each axis's part of the index or hash taken once for both of its
    /// sides rather than once per corner.
    #[inline(always)]
    pub fn corner_rows(&self, bone: usize, base: [usize; 3]) -> [usize; 8] {
        let (offset, dense) = self.grid_of(bone);
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

    /// Where bone `bone`'s grid lies in the table: its first row (a dense grid's vertex 0, a
    /// hashed one's hash 0) and whether it is dense.
    #[inline(always)]
    pub fn grid_of(&self, bone: usize) -> (usize, bool) {
        match self.root {
            Some(root) if root.bone == bone => (root.offset, root.dense),
            _ => (self.table_offset + if self.dense { self.offsets[bone] } else { 0 }, self.dense),
        }
    }

    /// The hash's mask: a hashed grid's rows are its first row plus the hash masked by it.
    pub fn hash_mask(&self) -> usize {
        self.table_mask
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
        let (offset, dense) = self.grid_of(bone);
        offset + if dense { within_grid } else { hashed() }
    }
}
