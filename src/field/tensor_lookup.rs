//! Planning a grid lookup with tensor ops on the points' own device: the plan `lookup` makes
//! on the host (each point's nearest bones, their skinning logits and the capsule prior with
//! their world gradients, every level's trilinear corners with their coefficients' world
//! derivatives, the root's preference corners), for a device that should not send its points
//! down and take a plan back on every lookup (a GPU). Every level is planned at once, as
//! `[points x bones, levels]` tensors. Tests pin it to the host's plan.

use super::layout::{GridConfig, Level, HASH_PRIMES};
use super::lookup::Skinning;
use crate::skeleton::BoneFrame;
use burn::tensor::{Device, Int, Tensor, TensorData};

/// A lookup planned on the device, laid out as `Lookup`: `N` points in `K` chosen bones (slots,
/// ascending by bone), `L` levels, 8 corners.
#[derive(Clone, Debug)]
pub struct TensorLookup {
    /// `[N, K]`: each slot's bone.
    pub bones: Tensor<2, Int>,
    /// `[N K L 8]` table rows and their trilinear coefficients (an inactive level's: row 0,
    /// coefficient 0).
    pub rows: Tensor<1, Int>,
    pub coefficients: Tensor<1>,
    /// `[N K L 8, 3]`: each coefficient's world derivative, when asked for.
    pub coefficient_tangents: Option<Tensor<2>>,
    /// `[N, K]`: the skinning's logits from distance, the largest 0; `[N, K, 3]` their world
    /// gradients, each through its own bone's distance, when asked for.
    pub logits: Tensor<2>,
    pub logit_tangents: Option<Tensor<3>>,
    /// `[N, K]`: 1 in the root's slot.
    pub root_slot: Tensor<2>,
    /// `[N 8]` the root's preference corners (zero where the root is not chosen), `[N 8, 3]`
    /// their coefficients' world derivatives.
    pub root_rows: Tensor<1, Int>,
    pub root_coefficients: Tensor<1>,
    pub root_coefficient_tangents: Tensor<2>,
    /// `[N]`: the capsule prior; `[N, K, 3]`: its world gradient through each slot's distance,
    /// when asked for.
    pub prior: Tensor<1>,
    pub prior_slot_tangents: Option<Tensor<3>>,
}

impl TensorLookup {
    /// `[N, 3]`: the capsule prior's world gradient, when planned.
    pub fn prior_tangents(&self) -> Option<Tensor<2>> {
        self.prior_slot_tangents.as_ref().map(|t| {
            let [n, _, _] = t.dims();
            t.clone().sum_dim(1).reshape([n, 3])
        })
    }
}

/// A row `[1, B]` of per-bone values.
fn per_bone(values: Vec<f32>, device: &Device) -> Tensor<2> {
    let count = values.len();
    Tensor::from_data(TensorData::new(values, [1, count]), device)
}

/// Plans the lookup of `points` (`[N, 3]`, world) in the bones `frames`, as `lookup` does.
pub fn lookup_on_device(config: &GridConfig, levels: &[Level], frames: &[BoneFrame], skinning: Skinning, points: Tensor<2>, tangents: bool) -> TensorLookup {
    let device = points.device();
    let [n, _] = points.dims();
    let b = frames.len();
    let k = config.top().min(b);
    // Every bone's frame: the point in it (`[N, B]` per axis), as `BoneFrame::to_local` sums.
    let relative = [0, 1, 2].map(|x| points.clone().slice([0..n, x..x + 1]) - per_bone(frames.iter().map(|f| f.origin[x]).collect(), &device));
    let axis = |m: usize, x: usize| per_bone(frames.iter().map(|f| f.axes[m][x]).collect(), &device);
    let local = [0, 1, 2].map(|m| relative[0].clone() * axis(m, 0) + relative[1].clone() * axis(m, 1) + relative[2].clone() * axis(m, 2));
    let lengths = per_bone(frames.iter().map(|f| f.length).collect(), &device).expand([n, b]);
    let along = local[1].clone() - local[1].clone().clamp_min(0.0).min_pair(lengths);
    let d2 = local[0].clone() * local[0].clone() + along.clone() * along.clone() + local[2].clone() * local[2].clone();
    // The skinning's distance: the root's capped (`Skinning::distance_squared`).
    let skinning_d2 = match skinning.root {
        Some((root, cap)) if root < b => {
            let capped = d2.clone().slice([0..n, root..root + 1]).clamp_max(cap * cap);
            d2.clone().slice_assign([0..n, root..root + 1], capped)
        }
        _ => d2.clone(),
    };
    let chosen = nearest(skinning_d2.clone(), k);
    let flat = chosen.clone().reshape([n * k]);
    let in_slots = |t: &Tensor<2>| t.clone().gather(1, chosen.clone());
    let of_slots = |values: Vec<f32>| Tensor::<1>::from_data(TensorData::new(values, [b]), &device).select(0, flat.clone()).reshape([n, k]);
    let (d2, skinning_d2) = (in_slots(&d2), in_slots(&skinning_d2));
    let slot_local = local.clone().map(|l| in_slots(&l));
    let offset = [slot_local[0].clone(), in_slots(&along), slot_local[2].clone()];
    let slot_axes: [[Tensor<2>; 3]; 3] = [0, 1, 2].map(|m| [0, 1, 2].map(|x| of_slots(frames.iter().map(|f| f.axes[m][x]).collect())));
    // The skinning's logits: shifted by the nearest bone's.
    let sharpness = skinning.sharpness;
    let logits = skinning_d2.clone() * sharpness - skinning_d2.clone().min_dim(1) * sharpness;
    // The capsule prior: a softmax of the true distances weighs the distances to the segments.
    let weights = burn::tensor::activation::softmax(d2.clone() * sharpness, 1);
    let distances = (d2.clone() + 1e-8).sqrt();
    let mean = (weights.clone() * distances.clone()).sum_dim(1);
    let prior = mean.clone() - skinning.prior_radius;
    let (prior, slope) = match skinning.prior_cap {
        Some(cap) => (prior.clone().clamp_max(cap), prior.lower_equal_elem(cap).float()),
        None => (prior, Tensor::ones([n, 1], &device)),
    };
    // Their world gradients, only when asked for (a lookup without gradients, most of a step's
    // and every one of the search's, needs none).
    let (logit_tangents, prior_slot_tangents) = match tangents {
        true => {
            // The squared distance's world gradient, per slot and axis.
            let gradient: [Tensor<2>; 3] = [0, 1, 2].map(|x| {
                (slot_axes[0][x].clone() * offset[0].clone() + slot_axes[1][x].clone() * offset[1].clone() + slot_axes[2][x].clone() * offset[2].clone()) * 2.0
            });
            let stack3 = |parts: [Tensor<2>; 3]| Tensor::stack::<3>(parts.to_vec(), 2);
            // A logit's gradient is its own bone's (none where the root's distance is capped).
            let moves = skinning_d2.equal(d2).float();
            let logit_tangents = stack3(gradient.clone().map(|g| g * moves.clone() * sharpness));
            let through = slope * ((distances.clone() - mean) * weights.clone() * sharpness + weights / (distances * 2.0));
            (Some(logit_tangents), Some(stack3(gradient.map(|g| g * through.clone()))))
        }
        false => (None, None),
    };
    let root_slot = match config.root {
        Some(root) => chosen.clone().equal_elem(root.bone as i64).float(),
        None => Tensor::zeros([n, k], &device),
    };
    let (root_rows, root_coefficients, root_coefficient_tangents) = root_corners(config, frames, &local, root_slot.clone(), tangents);
    let corners = level_corners(config, levels, frames, &chosen, &slot_local, &slot_axes, tangents);
    TensorLookup {
        bones: chosen,
        rows: corners.rows,
        coefficients: corners.weights,
        coefficient_tangents: corners.tangents,
        logits,
        logit_tangents,
        root_slot,
        root_rows,
        root_coefficients,
        root_coefficient_tangents,
        prior: prior.reshape([n]),
        prior_slot_tangents,
    }
}

/// `[N, K]`: the `k` bones of least `distance` (`[N, B]`) per point, ascending by bone.
fn nearest(distance: Tensor<2>, k: usize) -> Tensor<2, Int> {
    let device = distance.device();
    let [n, b] = distance.dims();
    let bones: Tensor<2, Int> = Tensor::<1, Int>::arange(0..b as i64, &device).reshape([1, b]).expand([n, b]);
    let mut remaining = distance;
    let mut picked = Vec::with_capacity(k);
    for _ in 0..k {
        let at = remaining.clone().argmin(1); // [N, 1]
        remaining = remaining.mask_fill(bones.clone().equal(at.clone().expand([n, b])), f32::INFINITY);
        picked.push(at);
    }
    // Nearest first, then sorted by bone: each slot's rank among the picked bones.
    let picked = Tensor::cat(picked, 1); // [N, K]
    let mine = picked.clone().reshape([n, k, 1]).expand([n, k, k]);
    let others = picked.clone().reshape([n, 1, k]).expand([n, k, k]);
    let rank = others.lower(mine).int().sum_dim(2); // [N, K, 1]
    let slots = Tensor::<1, Int>::arange(0..k as i64, &device).reshape([1, 1, k]).expand([n, k, k]);
    let placed = rank.expand([n, k, k]).equal(slots).int() * picked.reshape([n, k, 1]).expand([n, k, k]);
    placed.sum_dim(1).reshape([n, k])
}

/// Planned corners: rows, coefficients and, when asked, the coefficients' world derivatives.
struct Corners {
    rows: Tensor<1, Int>,
    weights: Tensor<1>,
    tangents: Option<Tensor<2>>,
}

/// A table `[B, L]` of per (bone, level) values, taken for each slot (`flat`, `[M]`): `[M, L]`.
fn per_slot_level(values: Vec<f32>, b: usize, l: usize, flat: &Tensor<1, Int>) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(values, [b, l]), &flat.device()).select(0, flat.clone())
}

/// The same for integers (rows, sizes, the hash's salt).
fn per_slot_level_int(values: Vec<i64>, b: usize, l: usize, flat: &Tensor<1, Int>) -> Tensor<2, Int> {
    Tensor::<2, Int>::from_data(TensorData::new(values, [b, l]), &flat.device()).select(0, flat.clone())
}

/// A hash prime as the i32 of the same bits: an integer tensor's low 32 bits then multiply as
/// the host's wrapping u32 product, whether the device's integers are i32 or i64.
fn prime(p: u32) -> i64 {
    p as i32 as i64
}

/// Every level's cells of each point in each chosen bone (`visit_cells`), at once as
/// `[N K, L]` tensors.
fn level_corners(
    config: &GridConfig,
    levels: &[Level],
    frames: &[BoneFrame],
    chosen: &Tensor<2, Int>,
    local: &[Tensor<2>; 3],
    slot_axes: &[[Tensor<2>; 3]; 3],
    tangents: bool,
) -> Corners {
    let device = chosen.device();
    let [n, k] = chosen.dims();
    let (b, l) = (frames.len(), levels.len());
    let m = n * k;
    let flat = chosen.clone().reshape([m]);
    let table =
        |f: &dyn Fn(usize, &Level) -> f32| per_slot_level((0..b).flat_map(|bone| levels.iter().map(move |level| f(bone, level))).collect(), b, l, &flat);
    let table_int =
        |f: &dyn Fn(usize, &Level) -> i64| per_slot_level_int((0..b).flat_map(|bone| levels.iter().map(move |level| f(bone, level))).collect(), b, l, &flat);
    let reach = table(&|bone, _| config.bone_reach(bone));
    let per_cell = table(&|_, level| 1.0 / level.cell);
    let top = [0, 1, 2].map(|axis| table(&|bone, level| level.dims[bone][axis] as f32 - 1.0));
    let local = local.clone().map(|t| t.reshape([m, 1]).expand([m, l]));
    let axes = tangents.then(|| slot_axes.clone().map(|row| row.map(|t| t.reshape([m, 1]).expand([m, l]))));
    let cells = trilinear(&local, reach, per_cell, &top, axes.as_ref());
    // Rows: a dense grid's vertex index or the spatial hash, after the grid's first row.
    let first = table_int(&|bone, level| level.grid_of(bone).0 as i64);
    let dense = table_int(&|bone, level| level.grid_of(bone).1 as i64);
    let width = table_int(&|bone, level| level.dims[bone][0] as i64);
    let height = table_int(&|bone, level| level.dims[bone][1] as i64);
    let salt = table_int(&|bone, _| prime((bone as u32).wrapping_mul(HASH_PRIMES[2])));
    let mask = levels.first().map_or(0, |level| level.hash_mask()) as i64;
    let active = Tensor::<2, Int>::from_data(TensorData::new(levels.iter().map(|level| level.active as i64).collect::<Vec<_>>(), [1, l]), &device);
    let mut rows = Vec::with_capacity(8);
    let mut weights = Vec::with_capacity(8);
    for (corner, weight) in cells.weights.into_iter().enumerate() {
        let v = [0, 1, 2].map(|axis| cells.base[axis].clone().add_scalar(((corner >> axis) & 1) as i64));
        let within = v[0].clone() + width.clone() * (v[1].clone() + height.clone() * v[2].clone());
        let hashed = v[0]
            .clone()
            .bitwise_xor(salt.clone())
            .bitwise_xor(v[1].clone().mul_scalar(prime(HASH_PRIMES[0])))
            .bitwise_xor(v[2].clone().mul_scalar(prime(HASH_PRIMES[1])));
        let hashed = hashed.bitwise_and_scalar(mask);
        let row = first.clone() + dense.clone() * within + (dense.clone().neg().add_scalar(1)) * hashed;
        rows.push((row * active.clone()).reshape([m, l, 1]));
        weights.push((weight * active.clone().float()).reshape([m, l, 1]));
    }
    let tangents = cells.gradients.map(|gradients| {
        let per_corner: Vec<Tensor<4>> =
            gradients.into_iter().map(|g| (Tensor::stack::<3>(g.to_vec(), 2) * active.clone().float().reshape([1, l, 1])).reshape([m, l, 1, 3])).collect();
        Tensor::cat(per_corner, 2).reshape([m * l * 8, 3])
    });
    Corners { rows: Tensor::cat(rows, 2).reshape([m * l * 8]), weights: Tensor::cat(weights, 2).reshape([m * l * 8]), tangents }
}

/// Trilinear cells (`lookup::trilinear`), elementwise: per element its point in the bone's
/// frame (`local`), the grid's reach, 1 / its cell and its top vertex per axis, and when
/// `axes` (the bone's axes in the world, `[m][x]`) are given, the weights' world gradients.
struct Cells {
    base: [Tensor<2, Int>; 3],
    weights: Vec<Tensor<2>>,
    gradients: Option<Vec<[Tensor<2>; 3]>>,
}

fn trilinear(local: &[Tensor<2>; 3], reach: Tensor<2>, per_cell: Tensor<2>, top: &[Tensor<2>; 3], axes: Option<&[[Tensor<2>; 3]; 3]>) -> Cells {
    let axis = |m: usize| {
        let u = (local[m].clone() + reach.clone()) * per_cell.clone();
        // Below the grid (or NaN) to 0, above it to its top vertex; either way outside.
        let low = u.clone().greater_elem(0.0).bool_not();
        let high = u.clone().greater_equal(top[m].clone());
        let u = u.mask_fill(low.clone(), 0.0).mask_where(high.clone(), top[m].clone());
        let at = u.clone().floor().min_pair(top[m].clone() - 1.0);
        (at.clone().int(), u - at, low.bool_or(high).bool_not().float())
    };
    let [(b0, f0, i0), (b1, f1, i1), (b2, f2, i2)] = [0, 1, 2].map(axis);
    let (base, fraction, inside) = ([b0, b1, b2], [f0, f1, f2], [i0, i1, i2]);
    let factors: Vec<[Tensor<2>; 2]> = fraction.iter().map(|f| [f.clone().neg() + 1.0, f.clone()]).collect();
    let bit = |corner: usize, m: usize| (corner >> m) & 1;
    let weights = (0..8).map(|c| factors[0][bit(c, 0)].clone() * factors[1][bit(c, 1)].clone() * factors[2][bit(c, 2)].clone()).collect();
    let gradients = axes.map(|axes| {
        // d u_m / d x: the bone's axis m over the cell, on axes inside the grid.
        let du: Vec<[Tensor<2>; 3]> = (0..3).map(|m| axes[m].clone().map(|a| a * per_cell.clone() * inside[m].clone())).collect();
        (0..8)
            .map(|c| {
                let d_tri: Vec<Tensor<2>> = (0..3)
                    .map(|m| {
                        let product = factors[(m + 1) % 3][bit(c, (m + 1) % 3)].clone() * factors[(m + 2) % 3][bit(c, (m + 2) % 3)].clone();
                        if bit(c, m) == 1 {
                            product
                        } else {
                            product.neg()
                        }
                    })
                    .collect();
                [0, 1, 2].map(|x| d_tri[0].clone() * du[0][x].clone() + d_tri[1].clone() * du[1][x].clone() + d_tri[2].clone() * du[2][x].clone())
            })
            .collect()
    });
    Cells { base, weights, gradients }
}

/// The root's preference corners (`[N 8]` rows and coefficients, `[N 8, 3]` derivatives), zero
/// where the root is not among the chosen bones.
fn root_corners(
    config: &GridConfig,
    frames: &[BoneFrame],
    local: &[Tensor<2>; 3],
    root_slot: Tensor<2>,
    tangents: bool,
) -> (Tensor<1, Int>, Tensor<1>, Tensor<2>) {
    let device = root_slot.device();
    let [n, _] = root_slot.dims();
    let Some((root, frame)) = config.root.and_then(|root| frames.get(root.bone).map(|frame| (root, frame))) else {
        return (Tensor::zeros([n * 8], &device), Tensor::zeros([n * 8], &device), Tensor::zeros([n * 8, 3], &device));
    };
    let dims = root.dims(frame.length);
    let full = |value: f32| Tensor::<2>::full([n, 1], value, &device);
    let local = local.clone().map(|l| l.slice([0..n, root.bone..root.bone + 1]));
    let top = [0, 1, 2].map(|axis| full(dims[axis] as f32 - 1.0));
    let axes = frame.axes.map(|row| row.map(full));
    let cells = trilinear(&local, full(root.reach), full(1.0 / root.cell), &top, tangents.then_some(&axes));
    let chosen = root_slot.sum_dim(1); // [N, 1]
    let chosen_int = chosen.clone().int();
    let rows: Vec<Tensor<2, Int>> = (0..8)
        .map(|c| {
            let v = [0, 1, 2].map(|axis| cells.base[axis].clone().add_scalar(((c >> axis) & 1) as i64));
            (v[0].clone() + (v[1].clone() + v[2].clone().mul_scalar(dims[1] as i64)).mul_scalar(dims[0] as i64)) * chosen_int.clone()
        })
        .collect();
    let weights: Vec<Tensor<2>> = cells.weights.into_iter().map(|w| w * chosen.clone()).collect();
    let gradients = match cells.gradients {
        Some(gradients) => {
            Tensor::cat(gradients.into_iter().map(|g| Tensor::stack::<3>(g.to_vec(), 2) * chosen.clone().reshape([n, 1, 1])).collect(), 1).reshape([n * 8, 3])
        }
        None => Tensor::zeros([n * 8, 3], &device),
    };
    (Tensor::cat(rows, 1).reshape([n * 8]), Tensor::cat(weights, 1).reshape([n * 8]), gradients)
}
