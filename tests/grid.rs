//! The `grid` field: its lookup plan (rows inside the table, dense levels collision-free,
//! coefficients that sum to one), the closed-form spatial tangents of the plan and of the whole
//! SDF against finite differences, and the gradient to the feature table against finite
//! differences of the loss.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use umbra::field::grid::{lookup, RootSkinning, Skinning};
use umbra::field::{AvatarField, FieldConfig, PoseTensors};
use umbra::random::Stream;
use umbra::synth::character::{Character, Kind};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

struct Setup {
    character: Character,
    pose: umbra::skeleton::Pose,
    config: FieldConfig,
}

fn setup() -> Setup {
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.2, DVec3::new(0.05, 0.0, -0.1));
    let (lo, hi) = pose.bounds(&character.skeleton);
    let extent = (hi - lo).length() as f32;
    let mut config = FieldConfig::with_grid(character.skeleton.bones.iter().map(|b| b.length as f32).collect(), extent);
    // As a fit sets it up: the root's distance capped and its preference grid.
    let cap = umbra::field::ROOT_REACH_PER_WIDTH * config.skinning_width;
    let grid = config.grid.as_mut().unwrap();
    // Loose clothing 0.6 m from the pelvis's segment: the root's grids reach it.
    grid.root = Some(RootSkinning::for_body(0, cap, grid.reach, Some(0.6), extent));
    Setup { character, pose, config }
}

/// Points near the body's surface and a few farther out (outside some bones' boxes).
fn points(s: &Setup, count: usize, seed: u64) -> Vec<DVec3> {
    let mut stream = Stream::new(seed, 1, 0);
    let bones = s.character.skeleton.len();
    (0..count)
        .map(|k| {
            let b = (stream.uniform() * bones as f64) as usize % bones;
            let along = stream.uniform() * s.character.skeleton.bones[b].length;
            let spread = if k % 5 == 0 { 0.4 } else { 0.12 };
            let local = DVec3::new((stream.uniform() - 0.5) * spread, along, (stream.uniform() - 0.5) * spread);
            s.pose.to_world(b, local)
        })
        .collect()
}

/// Whether `p` lies within `h` of the root's cap, where the skinning's logits have a kink.
fn near_cap(s: &Setup, p: DVec3, h: f64) -> bool {
    let Some(root) = s.config.grid.as_ref().and_then(|g| g.root) else { return false };
    let (head, tail) = s.pose.segment(&s.character.skeleton, root.bone);
    let along = ((p - head).dot(tail - head) / (tail - head).length_squared()).clamp(0.0, 1.0);
    ((p - (head + (tail - head) * along)).length() - root.cap as f64).abs() < 2.0 * h
}

fn flat(points: &[DVec3]) -> Vec<f32> {
    points.iter().flat_map(|p| p.as_vec3().to_array()).collect()
}

/// The field's skinning: the root's distance capped.
fn skinning(config: &FieldConfig) -> Skinning {
    let skin = config.skinning();
    assert!(skin.root.is_some());
    skin
}

/// The same by distance alone.
fn uncapped(config: &FieldConfig) -> Skinning {
    Skinning { root: None, ..config.skinning() }
}

#[test]
fn the_plan_stays_in_the_table_and_interpolates_a_partition_of_unity() {
    let s = setup();
    let grid = s.config.grid.clone().unwrap();
    let levels = grid.layout();
    assert!(levels.first().unwrap().dense && !levels.last().unwrap().dense, "coarse levels are dense, the finest hashed");
    let device = Device::flex();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &device).frames;
    let pts = points(&s, 200, 3);
    let plan = lookup(&grid, &levels, &frames, skinning(&s.config), &flat(&pts), false);
    let rows = grid.table_rows();
    assert!(plan.rows.iter().all(|&r| (r as usize) < rows));
    for (p, chunk) in plan.coefficients.chunks(grid.corners()).enumerate() {
        for (g, cell) in chunk.chunks(8).enumerate() {
            // The trilinear weights of each chosen bone's cell at each level sum to one.
            let sum: f32 = cell.iter().sum();
            assert!((sum - 1.0).abs() < 1e-5, "point {p} bone and level {g}: {sum}");
        }
    }
    for (p, cell) in plan.root_coefficients.chunks(8).enumerate() {
        // And so do the root preference's, where the root is chosen (none elsewhere).
        let sum: f32 = cell.iter().sum();
        let chosen: f32 = plan.root_slot[p * grid.top()..(p + 1) * grid.top()].iter().sum();
        assert!((sum - chosen).abs() < 1e-5, "point {p}: root preference {sum}, root chosen {chosen}");
    }
    // A dense level lays the bones' grids one after another: every row of level 0 lies
    // within their total, which fits the level's table. The root's grids, which hold the
    // whole skeleton, are in a table of their own after it.
    let dense = &levels[0];
    let root = dense.root.expect("the root's grids have a table of their own");
    let others: Vec<usize> = (0..dense.dims.len()).filter(|&b| b != root.bone).collect();
    let size = |b: usize| dense.dims[b][0] * dense.dims[b][1] * dense.dims[b][2];
    let total: usize = others.iter().map(|&b| size(b)).sum();
    assert!(total <= grid.table_size() && root.dense && size(root.bone) <= grid.table_size());
    assert_eq!(root.offset, grid.table_size());
    let slots = plan.root_slot.chunks(grid.top());
    for (p, slot) in slots.enumerate() {
        for (j, &is_root) in slot.iter().enumerate() {
            let level0 = &plan.rows[p * grid.corners() + j * grid.levels * 8..][..8];
            let (lo, hi) = if is_root == 1.0 { (root.offset, root.offset + size(root.bone)) } else { (0, total) };
            assert!(level0.iter().all(|&r| (lo..hi).contains(&(r as usize))), "point {p} bone slot {j}: {level0:?} outside {lo}..{hi}");
        }
    }
    assert!(others.windows(2).all(|w| dense.offsets[w[1]] - dense.offsets[w[0]] == size(w[0])), "bones' grids do not overlap");
}

#[test]
fn a_cells_eight_rows_at_once_are_each_vertexs_row() {
    let s = setup();
    let grid = s.config.grid.clone().unwrap();
    let levels = grid.layout();
    assert!(levels.iter().any(|l| l.dense) && levels.iter().any(|l| !l.dense) && levels.iter().any(|l| l.root.is_some()));
    let mut stream = Stream::new(5, 6, 0);
    let mut checked = 0;
    for level in &levels {
        for (bone, dims) in level.dims.iter().enumerate() {
            for _ in 0..50 {
                let base = [0, 1, 2].map(|m| ((stream.uniform() * (dims[m] - 1) as f64) as usize).min(dims[m] - 2));
                let rows = level.corner_rows(bone, base);
                for (k, &row) in rows.iter().enumerate() {
                    let v = [base[0] + (k & 1), base[1] + ((k >> 1) & 1), base[2] + ((k >> 2) & 1)];
                    assert_eq!(row, level.row(bone, v), "cell {base:?} of bone {bone}, corner {k}");
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 1000);
}

#[test]
fn the_roots_grids_reach_a_skirts_hem_that_the_other_bones_grids_do_not() {
    // A point of a bell skirt's hem: 0.36 m out from the pelvis's head and 0.36 m below it,
    // 0.5 m from its segment, farther than the other bones' boxes reach. The root carries it;
    // its features must still change with the point along every axis, as they do only inside
    // a grid (outside, a grid is clamped to its border: the features are constant there).
    let s = setup();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &Device::flex()).frames;
    let hem = s.pose.to_world(0, DVec3::new(0.36, -0.36, 0.0));
    let root_changes_along_every_axis = |grid: &umbra::field::grid::GridConfig| {
        assert!(grid.reach < 0.5, "the other bones' boxes stop short of the hem");
        let plan = lookup(grid, &grid.layout(), &frames, skinning(&s.config), &hem.as_vec3().to_array(), true);
        let slot = plan.root_slot.iter().position(|&r| r == 1.0).expect("the root is chosen at the hem");
        // The root's corners at the finest level: their coefficients' derivatives along each
        // of the root's own axes (a clamped axis has none).
        let corners = (slot * grid.levels + grid.levels - 1) * 8..(slot * grid.levels + grid.levels) * 8;
        let axes = frames[0].axes;
        let along = |m: usize| corners.clone().map(|k| (0..3).map(|x| plan.coefficient_tangents[k * 3 + x] * axes[m][x]).sum::<f32>().abs()).sum::<f32>();
        (0..3).all(|m| along(m) > 1e-3)
    };
    let grid = s.config.grid.clone().unwrap();
    assert!(root_changes_along_every_axis(&grid), "the root's grids reach as far as its skeleton");
    // As the root's grids were before (as far as the other bones'): clamped at the hem.
    let mut short = grid.clone();
    short.root = short.root.map(|r| RootSkinning { features_reach_body: false, ..r });
    assert!(!root_changes_along_every_axis(&short));
}

#[test]
fn plan_tangents_match_finite_differences() {
    let s = setup();
    plan_tangents_match_finite_differences_with(&s, uncapped(&s.config));
}

#[test]
fn plan_tangents_match_finite_differences_with_the_root_capped() {
    let s = setup();
    let skin = skinning(&s.config);
    // A point far from every bone: the cap makes the root one of its chosen bones, and the
    // one with the largest logit (0 after the shift).
    let (grid, frames) = (s.config.grid.clone().unwrap(), PoseTensors::new(&s.pose, &s.character.skeleton, &Device::flex()).frames);
    let far = DVec3::new(0.0, 1.0, 0.6);
    let free = lookup(&grid, &grid.layout(), &frames, uncapped(&s.config), &far.as_vec3().to_array(), false);
    let capped = lookup(&grid, &grid.layout(), &frames, skin, &far.as_vec3().to_array(), false);
    assert_ne!(free.rows, capped.rows, "the cap changes which bones a far point is looked up in");
    assert_eq!(free.prior, capped.prior, "the prior keeps the true distances");
    let root = capped.root_slot.iter().position(|&s| s == 1.0).expect("the root is chosen");
    assert_eq!(capped.logits[root], 0.0, "the root leads");
    plan_tangents_match_finite_differences_with(&s, skin);
}

fn plan_tangents_match_finite_differences_with(s: &Setup, skin: Skinning) {
    let grid = s.config.grid.clone().unwrap();
    let levels = grid.layout();
    let device = Device::flex();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &device).frames;
    let pts = points(s, 60, 5);
    let plan = lookup(&grid, &levels, &frames, skin, &flat(&pts), true);
    let h = 5e-5f32;
    let (mut checked, mut kinks) = (0, 0);
    for (p, point) in pts.iter().enumerate() {
        for axis in 0..3 {
            let shifted = |sign: f32| {
                let mut q = point.as_vec3().to_array();
                q[axis] += sign * h;
                lookup(&grid, &levels, &frames, skin, &q, false)
            };
            let (plus, minus, here) = (shifted(1.0), shifted(-1.0), lookup(&grid, &levels, &frames, skin, &point.as_vec3().to_array(), false));
            // A cell face, a box face or a change of nearest bones within h makes a kink (or
            // moves rows): central differences do not apply there, and those cases are counted.
            if plus.rows != here.rows
                || minus.rows != here.rows
                || plus.root_rows != here.root_rows
                || minus.root_rows != here.root_rows
                || (skin.root.is_some() && near_cap(s, *point, h as f64))
            {
                kinks += 1;
                continue;
            }
            let c = grid.corners();
            let scale = 1.0 / grid.finest_cell;
            let slopes: Vec<(f32, f32)> =
                (0..c).map(|k| ((plus.coefficients[k] - here.coefficients[k]) / h, (here.coefficients[k] - minus.coefficients[k]) / h)).collect();
            if slopes.iter().any(|(f, b)| (f - b).abs() > 0.02 * scale) {
                kinks += 1;
                continue;
            }
            for (k, (forward, backward)) in slopes.into_iter().enumerate() {
                let analytic = plan.coefficient_tangents[(p * c + k) * 3 + axis];
                let central = 0.5 * (forward + backward);
                assert!((analytic - central).abs() < 5e-3 * scale, "point {p} axis {axis} corner {k}: {analytic} vs {central}");
                checked += 1;
            }
            // Each logit's tangent is its own bone's distance's; the logits are shifted so the
            // largest is 0, so their differences are what the shifted logits' show.
            let top = grid.top();
            let lead = (0..top).find(|&j| here.logits[j] == 0.0).expect("a logit leads");
            let tangent = |j: usize| plan.logit_tangents[(p * top + j) * 3 + axis];
            for j in 0..top {
                let fd = (plus.logits[j] - minus.logits[j]) / (2.0 * h);
                let analytic = tangent(j) - tangent(lead);
                assert!((analytic - fd).abs() < 2e-3 * fd.abs().max(1.0 / grid.finest_cell), "point {p} logit {j}: {analytic} vs {fd}");
            }
            // The prior's tangent is the sum of its parts through each bone.
            let parts: f32 = (0..top).map(|j| plan.prior_slot_tangents[(p * top + j) * 3 + axis]).sum();
            assert!((parts - plan.prior_tangents[p * 3 + axis]).abs() < 1e-5, "prior parts {parts} vs {}", plan.prior_tangents[p * 3 + axis]);
            for k in 0..8 {
                let fd = (plus.root_coefficients[k] - minus.root_coefficients[k]) / (2.0 * h);
                let analytic = plan.root_coefficient_tangents[(p * 8 + k) * 3 + axis];
                assert!((analytic - fd).abs() < 5e-3 * scale, "point {p} root corner {k}: {analytic} vs {fd}");
            }
            let prior_fd = (plus.prior[0] - minus.prior[0]) / (2.0 * h);
            assert!((plan.prior_tangents[p * 3 + axis] - prior_fd).abs() < 2e-3, "prior: {} vs {prior_fd}", plan.prior_tangents[p * 3 + axis]);
        }
    }
    assert!(checked > 10_000 && kinks * 10 < pts.len() * 3, "checked {checked}, kinks {kinks}");
}

/// A grid field whose table and decoder hold O(1) random values, so its SDF has real structure.
/// With `all_active`, every hidden unit's bias is large enough that no ReLU switches near the
/// test points: the SDF is then smooth inside each cell and finite differences are sharp.
/// The SDF decoder's output weights in `busy_field`: with every unit on (first-layer bias 5) an
/// SDF of a metre or two, as a body's is. (At 3 it reached 28 m, whose f32 rounding, a few
/// ulps of 2e-6, is 1e-2 in a 1 mm finite difference: no reference for the tangents.)
const OUTPUT_WEIGHT: f32 = 0.3;

fn busy_field(config: &FieldConfig, device: &Device, all_active: bool) -> AvatarField {
    let mut field = config.init(device, 7);
    let mut stream = Stream::new(11, 2, 0);
    let grid = field.grid.take().unwrap();
    let [rows, features] = grid.table.val().dims();
    let table: Vec<f32> = (0..rows * features).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    // The root's preference: a few logits either way.
    let root_preference = grid.root_preference.map(|p| {
        let [rows, _] = p.val().dims();
        let values: Vec<f32> = (0..rows).map(|_| (stream.uniform() * 2.0 - 1.0) as f32 * 3.0).collect();
        Param::from_tensor(Tensor::from_data(TensorData::new(values, [rows, 1]), device))
    });
    field.grid = Some(umbra::field::grid::FeatureGrid {
        table: Param::from_tensor(Tensor::from_data(TensorData::new(table, [rows, features]), device)),
        root_preference,
        config: grid.config,
        active_levels: grid.active_levels,
        route: umbra::field::grid::Route::Fused,
    });
    let [i, o] = field.output.weight.val().dims();
    let w: Vec<f32> = (0..i * o).map(|_| (stream.uniform() * 2.0 - 1.0) as f32 * OUTPUT_WEIGHT).collect();
    field.output.weight = Param::from_tensor(Tensor::from_data(TensorData::new(w, [i, o]), device));
    if all_active {
        // Each feature lies in [-1, 1] (per level, weights summing to one over table values in
        // [-1, 1]), so with 16 features and |w| <= 1/4 a first-layer bias of 5 keeps every unit
        // on; non-negative weights after it keep the next layers on too. Small biases keep
        // f32 rounding below the finite differences' resolution.
        for (l, layer) in field.hidden.iter_mut().enumerate() {
            let [inputs, width] = layer.weight.val().dims();
            if l > 0 {
                let w = values(layer.weight.val()).into_iter().map(f32::abs).collect::<Vec<_>>();
                layer.weight = Param::from_tensor(Tensor::from_data(TensorData::new(w, [inputs, width]), device));
            }
            let bias = if l == 0 { 5.0 } else { 0.1 };
            layer.bias = Some(Param::from_tensor(Tensor::from_data(TensorData::new(vec![bias; width], [width]), device)));
        }
    }
    field
}

#[test]
fn sdf_gradient_by_tangents_matches_finite_differences() {
    let s = setup();
    let device = Device::flex();
    let field = busy_field(&s.config, &device, true);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let pts = points(&s, 200, 9);
    let grid_config = s.config.grid.clone().unwrap();
    let levels = grid_config.layout();
    let skin = skinning(&s.config);
    let n = pts.len();
    let tensor = |p: &[DVec3]| Tensor::<2>::from_data(TensorData::new(flat(p), [p.len(), 3]), &device);
    let (sdf, gradient) = field.sdf_and_gradient(tensor(&pts), &pose);
    let (sdf, gradient) = (values(sdf), values(gradient));
    let plain = values(field.sdf(tensor(&pts), &pose));
    for k in 0..n {
        assert!((sdf[k] - plain[k]).abs() < 1e-6, "the tangent pass computes the same SDF");
    }
    // 1 mm: the SDF's f32 rounding (~1e-7 of its magnitude) stays far below h x the slope; a
    // step this long often crosses a cell face, so those cases are skipped and many points used.
    let h = 1e-3;
    let (mut checked, mut kinks) = (0, 0);
    for axis in 0..3 {
        let shift = |sign: f64| pts.iter().map(|p| *p + DVec3::from_array([0, 1, 2].map(|a| if a == axis { sign * h } else { 0.0 }))).collect::<Vec<_>>();
        let plus = values(field.sdf(tensor(&shift(1.0)), &pose));
        let minus = values(field.sdf(tensor(&shift(-1.0)), &pose));
        for k in 0..n {
            let forward = (plus[k] - sdf[k]) as f64 / h;
            let backward = (sdf[k] - minus[k]) as f64 / h;
            // Rows that change within h (a cell face, another nearest bone): not differentiable.
            let rows = |p: DVec3| {
                let l = lookup(&grid_config, &levels, &pose.frames, skin, &p.as_vec3().to_array(), false);
                (l.rows, l.root_rows)
            };
            if rows(shift(-1.0)[k]) != rows(pts[k]) || rows(pts[k]) != rows(shift(1.0)[k]) || near_cap(&s, pts[k], h) {
                kinks += 1;
                continue;
            }
            // Where a limb hands a far point over to the root the skinning turns within a few
            // millimetres: the one-sided slopes differ and central differences are no reference.
            if (forward - backward).abs() > 2e-2 * forward.abs().max(1.0) {
                kinks += 1;
                continue;
            }
            let central = 0.5 * (forward + backward);
            let analytic = gradient[k * 3 + axis] as f64;
            assert!(
                (analytic - central).abs() < 2e-3 * central.abs().max(1.0),
                "point {k} axis {axis}: {analytic} vs {central} (forward {forward}, backward {backward})"
            );
            checked += 1;
        }
    }
    assert!(checked >= 40, "checked {checked}, kinks {kinks}");
}

#[test]
fn table_gradient_matches_finite_differences() {
    let s = setup();
    let device = Device::flex().autodiff();
    let field = busy_field(&s.config, &device, false);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let pts = points(&s, 30, 13);
    let input = Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
    let loss = |f: &AvatarField| {
        let out = f.forward(input.clone(), &pose);
        (out.sdf.powf_scalar(2.0).sum() + out.albedo.sum()).reshape([1])
    };
    let grads = loss(&field).backward();
    let grid = field.grid.as_ref().unwrap();
    let analytic = values(grid.table.grad(&grads).unwrap());
    let table = values(grid.table.val());
    let features = grid.config.features;
    // The entries with the largest gradients (they are touched by many corners).
    let mut order: Vec<usize> = (0..analytic.len()).collect();
    order.sort_by(|a, b| analytic[*b].abs().total_cmp(&analytic[*a].abs()));
    // The loss point by point, summed in f64: the points an entry does not touch cancel
    // exactly, so the f32 rounding of the others does not swamp a short step's change. A step
    // this short rarely switches a decoder unit, even in an entry of the root's coarsest grids
    // (they hold loose clothing, and the root is one of nearly every point's bones).
    let per_point = |f: &AvatarField| {
        let out = f.forward(input.clone(), &pose);
        values(out.sdf.powf_scalar(2.0) + out.albedo.sum_dim(1).reshape([pts.len()])).into_iter().map(f64::from).collect::<Vec<f64>>()
    };
    let h = 1e-4f32;
    let mut checked = 0;
    for &k in order.iter().take(12) {
        let perturbed = |delta: f32| {
            let mut t = table.clone();
            t[k] += delta;
            let mut f = field.clone();
            let g = f.grid.take().unwrap();
            f.grid = Some(umbra::field::grid::FeatureGrid {
                table: Param::from_tensor(Tensor::from_data(TensorData::new(t, [table.len() / features, features]), &device)),
                root_preference: g.root_preference,
                config: g.config,
                active_levels: g.active_levels,
                route: g.route,
            });
            per_point(&f)
        };
        let here = per_point(&field);
        let slope = |other: Vec<f64>, sign: f64| other.iter().zip(&here).map(|(a, b)| sign * (a - b)).sum::<f64>() / h as f64;
        let (forward, backward) = (slope(perturbed(h), 1.0), slope(perturbed(-h), -1.0));
        // A ReLU of the decoder switching within h: the one-sided slopes differ; skipped.
        if (forward - backward).abs() > 2e-2 * forward.abs().max(1e-1) {
            continue;
        }
        let fd = 0.5 * (forward + backward);
        assert!((analytic[k] as f64 - fd).abs() < 2e-2 * fd.abs().max(1e-1), "entry {k}: {} vs {fd}", analytic[k]);
        checked += 1;
    }
    assert!(checked >= 6, "only {checked} entries away from a kink");
}

#[test]
fn root_preference_gradient_matches_finite_differences() {
    let s = setup();
    let device = Device::flex().autodiff();
    // Every decoder unit on: no ReLU switches within a step.
    let field = busy_field(&s.config, &device, true);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    // Points 10-20 cm from a bone, about the root's cap: there the root shares the weight with
    // other bones (near a limb it has almost none, around the pelvis almost all, and its
    // preference little gradient either way).
    let mut stream = Stream::new(13, 1, 0);
    let pts: Vec<DVec3> = (0..40)
        .map(|_| {
            let b = 1 + (stream.uniform() * 16.0) as usize % 16;
            let (r, angle) = (0.1 + 0.1 * stream.uniform(), stream.uniform() * std::f64::consts::TAU);
            let along = stream.uniform() * s.character.skeleton.bones[b].length;
            s.pose.to_world(b, DVec3::new(r * angle.cos(), along, r * angle.sin()))
        })
        .collect();
    let input = Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
    // The SDF's sum: small (a few metres), so its f32 rounding stays far below the changes.
    let loss = |f: &AvatarField| f.sdf(input.clone(), &pose).sum().reshape([1]);
    let grads = loss(&field).backward();
    let grid = field.grid.as_ref().unwrap();
    let preference = grid.root_preference.as_ref().unwrap();
    let analytic = values(preference.grad(&grads).unwrap());
    let start = values(preference.val());
    let mut order: Vec<usize> = (0..analytic.len()).collect();
    order.sort_by(|a, b| analytic[*b].abs().total_cmp(&analytic[*a].abs()));
    let largest = analytic[order[0]].abs() as f64;
    assert!(largest > 1e-5, "the preference gets a gradient: {largest}");
    // A logit step this long keeps the loss's change far above its f32 rounding (at 0.02 a
    // vertex with a sixth of the largest gradient moved its points' SDF by a few ulps: its
    // central differences at h and h/2 disagreed by 1.6%). The softmax curves over it, so
    // one-sided slopes differ; central differences at h and h/2 agree where nothing switches
    // within the step (and the second is the reference).
    let h = 0.1f32;
    let mut checked = 0;
    for &k in order.iter().take(24) {
        let perturbed = |delta: f32| {
            let mut v = start.clone();
            v[k] += delta;
            let mut f = field.clone();
            let mut g = f.grid.take().unwrap();
            g.root_preference = Some(Param::from_tensor(Tensor::from_data(TensorData::new(v, [start.len(), 1]), &device)));
            f.grid = Some(g);
            values(f.sdf(input.clone(), &pose))
        };
        // Point by point, summed in f64: the points the vertex does not touch cancel exactly,
        // so the rounding of the others' SDF (a few metres in f32) does not swamp the change.
        let central = |step: f32| perturbed(step).iter().zip(perturbed(-step)).map(|(a, b)| *a as f64 - b as f64).sum::<f64>() / (2.0 * step as f64);
        let (coarse, fine) = (central(h), central(h / 2.0));
        let scale = fine.abs().max(1e-2 * largest);
        if (coarse - fine).abs() > 2e-2 * scale {
            continue;
        }
        assert!((analytic[k] as f64 - fine).abs() < 2e-2 * scale, "vertex {k}: {} vs {fine} (coarse {coarse}, largest {largest})", analytic[k]);
        checked += 1;
    }
    assert!(checked >= 6, "only {checked} vertices away from a kink");
}

#[test]
fn feature_tangents_match_finite_differences() {
    let s = setup();
    let device = Device::flex();
    let field = busy_field(&s.config, &device, false);
    let grid = field.grid.as_ref().unwrap();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &device).frames;
    let skin = skinning(&s.config);
    let pts = points(&s, 40, 9);
    let n = pts.len();
    let tensor = |p: &[DVec3]| Tensor::<2>::from_data(TensorData::new(flat(p), [p.len(), 3]), &device);
    let encoded = grid.encode(tensor(&pts), &frames, skin, true, None);
    let width = grid.config.width();
    let (feature_tangents, _) = encoded.tangents.unwrap();
    let (here, tangents) = (values(encoded.features), values(feature_tangents));
    let levels = grid.config.layout();
    // Features are sums of many f32 products: a shorter step drowns in their rounding.
    let h = 2e-4;
    let (mut checked, mut kinks) = (0, 0);
    for axis in 0..3 {
        let shift = |sign: f64| pts.iter().map(|p| *p + DVec3::from_array([0, 1, 2].map(|a| if a == axis { sign * h } else { 0.0 }))).collect::<Vec<_>>();
        let plus = values(grid.encode(tensor(&shift(1.0)), &frames, skin, false, None).features);
        let minus = values(grid.encode(tensor(&shift(-1.0)), &frames, skin, false, None).features);
        for k in 0..n {
            // Rows that change within h (a cell face, another nearest bone): not differentiable there.
            let rows = |p: DVec3| {
                let l = lookup(&grid.config, &levels, &frames, skin, &p.as_vec3().to_array(), false);
                (l.rows, l.root_rows)
            };
            let (a, b, c) = (rows(shift(-1.0)[k]), rows(pts[k]), rows(shift(1.0)[k]));
            if a != b || b != c || near_cap(&s, pts[k], h) {
                kinks += 1;
                continue;
            }
            for j in 0..width {
                let central = (plus[k * width + j] - minus[k * width + j]) as f64 / (2.0 * h);
                let analytic = tangents[(axis * n + k) * width + j] as f64;
                assert!(
                    (analytic - central).abs() < 1e-2 * central.abs().max(1.0),
                    "point {k} axis {axis} feature {j}: {analytic} vs {central} (value {})",
                    here[k * width + j]
                );
                checked += 1;
            }
        }
    }
    // Each of 8 levels x 3 bones can cross a cell face within a step: under half are skipped.
    assert!(checked > 0 && kinks * 2 < 3 * n, "checked {checked}, kinks {kinks}");
}

#[test]
fn inactive_levels_contribute_nothing_and_a_fading_level_contributes_in_part() {
    let s = setup();
    let device = Device::flex();
    let mut field = busy_field(&s.config, &device, false);
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &device).frames;
    let pts = points(&s, 20, 21);
    let input = Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
    let full = values(field.grid.as_ref().unwrap().encode(input.clone(), &frames, skinning(&s.config), false, None).features);
    field.grid.as_mut().unwrap().active_levels = 4.5;
    let encoded = field.grid.as_ref().unwrap().encode(input, &frames, skinning(&s.config), true, None);
    let (faded, tangents) = (values(encoded.features), values(encoded.tangents.unwrap().0));
    let f = s.config.grid.as_ref().unwrap().features;
    let width = 8 * f;
    for (k, (a, b)) in full.iter().zip(&faded).enumerate() {
        let level = (k % width) / f;
        let expected = match level {
            0..=3 => *a,
            4 => 0.5 * a,
            _ => 0.0,
        };
        assert!((b - expected).abs() < 1e-6, "feature {k} (level {level}): {b} vs {expected}");
    }
    assert!(tangents.iter().enumerate().all(|(k, t)| (k % width) / f < 5 || *t == 0.0), "inactive levels have no spatial derivative");
}

/// The fused interpolation op against the composite of tensor ops it replaced: the same
/// features, tangents and table gradient (for a loss weighing every output differently), with
/// the finest level half faded in, on both CPU backends; and it is linear in the table, so a
/// finite difference of the loss along a random direction must match the gradient exactly.
#[test]
#[allow(deprecated)] // burn-ndarray stays our --backend ndarray
fn fused_interpolation_matches_the_composite_and_its_gradient() {
    let s = setup();
    for device in [Device::flex().autodiff(), Device::ndarray().autodiff()] {
        let mut field = busy_field(&s.config, &device, false);
        let grid = field.grid.as_mut().unwrap();
        grid.active_levels = grid.config.levels as f32 - 1.5;
        let grid = field.grid.as_ref().unwrap();
        let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
        let pts = points(&s, 120, 21);
        let input = || Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
        let mut stream = Stream::new(5, 5, 5);
        let n = pts.len();
        let width = grid.config.levels * grid.config.features;
        let weights: Vec<f32> = (0..4 * n * width).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
        let weights = Tensor::<2>::from_data(TensorData::new(weights, [4 * n, width]), &device);
        let run = |composite: bool| {
            let mut grid = grid.clone();
            grid.route = if composite { umbra::field::grid::Route::Composite } else { umbra::field::grid::Route::Fused };
            let f = grid.encode(input(), &pose.frames, skinning(&s.config), true, None);
            let (tangents, _) = f.tangents.unwrap();
            let out = Tensor::cat(vec![f.features, tangents], 0);
            let loss = (out.clone() * weights.clone()).sum();
            let grads = loss.clone().backward();
            let g = grid.table.grad(&grads).unwrap();
            (values(out.inner()), values(loss.inner()), values(g))
        };
        let (fused, loss, fused_grad) = run(false);
        let (composite, _, composite_grad) = run(true);
        let worst = fused.iter().zip(&composite).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "outputs differ by {worst}");
        let scale = composite_grad.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
        let worst = fused_grad.iter().zip(&composite_grad).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(scale > 1e-3 && worst < 1e-4 * scale.max(1.0), "gradients differ by {worst} (largest {scale})");
        // Directional finite difference in f64 of the (linear) loss.
        let table = values(grid.table.val().inner());
        let [rows, features] = grid.table.val().dims();
        let direction: Vec<f32> = (0..table.len()).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
        let h = 1e-2f32;
        let shifted: Vec<f32> = table.iter().zip(&direction).map(|(t, d)| t + h * d).collect();
        let mut moved = field.clone();
        moved.grid.as_mut().unwrap().table = Param::from_tensor(Tensor::from_data(TensorData::new(shifted, [rows, features]), &device));
        let moved_grid = moved.grid.as_ref().unwrap();
        let f = moved_grid.encode(input(), &pose.frames, skinning(&s.config), true, None);
        let out = Tensor::cat(vec![f.features, f.tangents.unwrap().0], 0);
        let moved_loss = values((out * weights.clone()).sum().inner())[0];
        let fd = (moved_loss as f64 - loss[0] as f64) / h as f64;
        let analytic: f64 = fused_grad.iter().zip(&direction).map(|(g, d)| *g as f64 * *d as f64).sum();
        assert!((fd - analytic).abs() < 1e-3 * analytic.abs().max(1.0), "finite difference {fd} vs gradient {analytic}");
    }
}

/// A lookup with no gradients wanted (an untracked table: the samples that search a ray for the
/// body) runs planned and summed in one pass on the host; it must give the features and prior of
/// the planned op (tracked table), with the root's preference in the skinning, a level half
/// faded and one left out, the root capped and not, on both CPU backends.
#[test]
#[allow(deprecated)] // burn-ndarray stays our --backend ndarray
fn a_lookup_without_gradients_is_the_planned_lookup() {
    let s = setup();
    for device in [Device::flex().autodiff(), Device::ndarray().autodiff()] {
        let mut field = busy_field(&s.config, &device, false);
        let grid = field.grid.as_mut().unwrap();
        grid.active_levels = grid.config.levels as f32 - 1.5;
        let tracked = field.grid.as_ref().unwrap();
        let still = field.valid();
        let untracked = still.grid.as_ref().unwrap();
        assert!(tracked.table.val().is_require_grad() && !untracked.table.val().is_require_grad());
        let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
        let pts = points(&s, 300, 23);
        let input = || Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
        for skin in [skinning(&s.config), uncapped(&s.config)] {
            let planned = tracked.encode(input(), &pose.frames, skin, false, None);
            let host = untracked.encode(input().inner(), &pose.frames, skin, false, None);
            let (a, b) = (values(planned.features.inner()), values(host.features));
            assert_eq!(a.len(), b.len());
            let worst = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "features differ by {worst}");
            assert!(a.iter().any(|v| v.abs() > 0.1), "the features are not all near zero");
            let (a, b) = (values(planned.prior.inner()), values(host.prior));
            let worst = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-6, "priors differ by {worst}");
        }
    }
}

/// With its own decoder the albedo cannot move the surface: changing the albedo decoder's
/// weights changes the albedo and leaves the SDF bit for bit; with a shared decoder (the
/// checkpoints of earlier fits) the albedo is the decoder's last three outputs.
#[test]
fn an_albedo_decoder_of_its_own_leaves_the_sdf_alone() {
    let s = setup();
    let device = Device::flex();
    let separate = FieldConfig { albedo_layers: 2, ..s.config.clone() };
    let mut field = busy_field(&separate, &device, false);
    assert_eq!(field.output.weight.val().dims()[1], 1, "the SDF's decoder has one output");
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let pts = points(&s, 64, 5);
    let tensor = || Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
    let before = field.forward(tensor(), &pose);
    let (sdf_before, albedo_before) = (values(before.sdf), values(before.albedo));
    let head = field.albedo_output.take().unwrap();
    let [i, o] = head.weight.val().dims();
    let mut stream = Stream::new(3, 4, 0);
    let w: Vec<f32> = (0..i * o).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    field.albedo_output = Some(burn::nn::Linear { weight: Param::from_tensor(Tensor::from_data(TensorData::new(w, [i, o]), &device)), ..head });
    let after = field.forward(tensor(), &pose);
    assert_eq!(values(after.sdf), sdf_before);
    let moved = values(after.albedo).iter().zip(&albedo_before).filter(|(a, b)| (*a - *b).abs() > 1e-3).count();
    assert!(moved > albedo_before.len() / 2, "the albedo follows its decoder ({moved} of {} values moved)", albedo_before.len());
    assert_eq!(values(field.sdf(tensor(), &pose)), sdf_before, "sdf() skips the albedo's decoder and agrees");

    let shared = FieldConfig { albedo_layers: 0, ..s.config.clone() };
    let field = busy_field(&shared, &device, false);
    assert!(field.albedo_output.is_none() && field.albedo_hidden.is_empty());
    assert_eq!(field.output.weight.val().dims()[1], 4, "a shared decoder gives SDF and albedo");
}

/// A ray's albedo is composited from the samples that carry weight only
/// (`render::composite_albedo`): where every other sample's weight is zero it is the full
/// compositing sum, value and gradients (to the albedo's decoder and to the weights); where they
/// are small but not zero, it is off by at most what they carry.
#[test]
fn the_albedo_is_composited_from_the_samples_that_carry_weight() {
    let s = setup();
    let device = Device::flex().autodiff();
    let separate = FieldConfig { albedo_layers: 2, ..s.config.clone() };
    let field = busy_field(&separate, &device, false);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let (rays, samples) = (24, 8);
    let pts = points(&s, rays * samples, 9);
    let tensor = || Tensor::<2>::from_data(TensorData::new(flat(&pts), [pts.len(), 3]), &device);
    let mut stream = Stream::new(4, 1, 0);
    // Each ray: a few samples with weight, the rest zero or (second set) just under the floor.
    let floor = umbra::render::ALBEDO_WEIGHT_FLOOR;
    let carried: Vec<bool> = (0..rays * samples).map(|k| k % samples == 0 || stream.uniform() < 0.3).collect();
    let weights_with = |small: f32| -> Vec<f32> {
        let mut stream = Stream::new(5, 1, 0);
        carried.iter().map(|&c| if c { 0.05 + 0.1 * stream.uniform() as f32 } else { small }).collect()
    };
    let run = |w: &[f32], pruned: bool| {
        let weights = Tensor::<2>::from_data(TensorData::new(w.to_vec(), [rays, samples]), &device).require_grad();
        let albedo = if pruned {
            let decoded = field.decode(tensor(), &pose);
            umbra::render::composite_albedo(&field, &decoded, &weights, floor)
        } else {
            let all = field.forward(tensor(), &pose).albedo.reshape([rays, samples, 3]);
            (weights.clone().unsqueeze_dim::<3>(2) * all).sum_dim(1).reshape([rays, 3])
        };
        // A loss that weighs the channels differently.
        let loss = (albedo.clone() * Tensor::<1>::from_data(TensorData::new(vec![1.0f32, -0.5, 2.0], [3]), &device).reshape([1, 3])).sum();
        let grads = loss.backward();
        let head = values(field.albedo_output.as_ref().unwrap().weight.grad(&grads).unwrap());
        let to_weights = values(weights.grad(&grads).unwrap());
        (values(albedo), head, to_weights)
    };
    let close = |a: &[f32], b: &[f32], tol: f32, what: &str| {
        for (k, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= tol * (1.0 + y.abs()), "{what}[{k}]: {x} against {y}");
        }
    };
    let exact = weights_with(0.0);
    let (albedo, head, to_weights) = run(&exact, true);
    let (albedo_full, head_full, to_weights_full) = run(&exact, false);
    close(&albedo, &albedo_full, 1e-5, "albedo");
    close(&head, &head_full, 1e-4, "decoder gradient");
    // The weights' gradient is the sample's albedo (times the loss's channel weights) where a
    // sample is kept; a dropped sample has none (which is why training keeps every sample).
    for (k, (&g, &g_full)) in to_weights.iter().zip(&to_weights_full).enumerate() {
        let expected = if carried[k] { g_full } else { 0.0 };
        assert!((g - expected).abs() <= 1e-4 * (1.0 + expected.abs()), "weight gradient [{k}]: {g} against {expected}");
    }
    // Weights just under the floor are dropped: each ray is off by at most what they hold.
    let small = weights_with(0.9 * floor);
    let (albedo, _, _) = run(&small, true);
    let (albedo_full, _, _) = run(&small, false);
    for ray in 0..rays {
        let dropped: f32 = (0..samples).filter(|&j| !carried[ray * samples + j]).map(|_| 0.9 * floor).sum();
        for c in 0..3 {
            let (a, b) = (albedo[3 * ray + c], albedo_full[3 * ray + c]);
            assert!(b - a >= -1e-6 && b - a <= dropped + 1e-6, "ray {ray}: {a} against {b}, dropped weight {dropped}");
        }
    }
}

/// `render_still` (pictures: densities from the sample search, composited on the CPU, the
/// albedo decoded only where samples carry weight) gives what `render` (training: every sample
/// evaluated again, with gradients) gives on the same rays and samples.
/// `count` rays from one eye 3 m off the body toward random points of its bounds, each bounded
/// to 2.5 m around its target (some hit the body, some miss).
fn rays_through_the_body(s: &Setup, count: usize, stream: &mut Stream) -> umbra::render::RaySet {
    let (lo, hi) = s.pose.bounds(&s.character.skeleton);
    let eye = (lo + hi) * 0.5 + DVec3::new(0.3, 0.2, 3.0);
    let mut rays = umbra::render::RaySet::default();
    for _ in 0..count {
        let target = lo + (hi - lo) * DVec3::new(stream.uniform(), stream.uniform(), stream.uniform());
        let far = (target - eye).length() + 1.0;
        rays.push(eye, (target - eye).normalize(), Some((far - 2.5, far)));
    }
    rays
}

#[test]
fn a_still_render_is_the_training_render_without_its_gradients() {
    let s = setup();
    let device = Device::flex();
    // The albedo from a decoder of its own and from the SDF's (its albedo read off the decoded
    // points the search kept, or looked up again).
    for albedo_layers in [2, 0] {
        let mut config = FieldConfig { albedo_layers, ..s.config.clone() };
        // The prior uncapped: the busy field's random residual on a capped prior leaves no empty
        // space for rays to miss, and the comparison needs both.
        let grid = config.grid.as_mut().unwrap();
        grid.root = grid.root.map(|r| RootSkinning { prior_capped: false, ..r });
        let field = busy_field(&config, &device, false);
        let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
        let mut stream = Stream::new(8, 1, 0);
        let rays = rays_through_the_body(&s, 96, &mut stream);
        for sampling in [
            umbra::render::Sampling { coarse: 16, probe: 16, fine: 16, albedo_floor: umbra::render::ALBEDO_WEIGHT_FLOOR, cull: false },
            umbra::render::Sampling { coarse: 24, probe: 0, fine: 0, albedo_floor: 0.0, cull: false },
        ] {
            let jitter: Vec<f32> = (0..rays.len() * sampling.draws()).map(|_| stream.uniform() as f32).collect();
            let normals = Some(umbra::field::GRADIENT);
            let trained = umbra::render::render(&field, &pose, &rays, sampling, &jitter, normals, &device);
            let still = umbra::render::render_still(&field, &pose, &rays, sampling, &jitter, normals, &device);
            let accumulation = values(trained.accumulation.clone());
            assert!(
                accumulation.iter().filter(|&&a| a > 0.5).count() > 10 && accumulation.iter().filter(|&&a| a < 0.5).count() > 10,
                "rays both hit and miss: {accumulation:?}"
            );
            let close = |x: f32, y: f32| (x - y).abs() <= 1e-3 * (1.0 + x.abs());
            let still_albedo = values(still.albedo.clone());
            let pairs = [
                ("accumulation", accumulation, values(still.accumulation)),
                ("depth", values(trained.depth), values(still.depth)),
                ("albedo", values(trained.albedo), still_albedo.clone()),
                ("surface", values(trained.surface.clone()), values(still.surface)),
            ];
            for (what, a, b) in pairs {
                assert_eq!(a.len(), b.len());
                for (k, (x, y)) in a.iter().zip(&b).enumerate() {
                    assert!(close(*x, *y), "{what}[{k}] ({sampling:?}): training {x}, still {y}");
                }
            }
            // Normals: the same SDF gradient at surface points that agree to rounding. A trilinear
            // grid's gradient jumps across a cell's face, so where a surface point lies within
            // rounding of one the two normals may be its two sides: then each must be the normal
            // just before or just after the point along the ray, and such rays must be rare.
            let (trained_normal, still_normal) = (values(trained.normal.unwrap()), values(still.normal.unwrap()));
            let surface = values(trained.surface);
            let mut on_a_face = 0;
            for ray in 0..rays.len() {
                let agree = |a: &[f32], b: &[f32]| (0..3).all(|c| close(a[3 * ray + c], b[3 * ray + c]));
                // A ray that carries no albedo shades to zero whatever its normal: the still render
                // gives it the ray's reverse direction instead of an SDF gradient.
                if still_albedo[3 * ray..3 * ray + 3].iter().all(|&a| a == 0.0) {
                    assert!((0..3).all(|c| still_normal[3 * ray + c] == -rays.directions[3 * ray + c]), "ray {ray}: {still_normal:?}");
                    continue;
                }
                if agree(&trained_normal, &still_normal) {
                    continue;
                }
                let side = |step: f32| {
                    let p: Vec<f32> = (0..3).map(|c| surface[3 * ray + c] + step * rays.directions[3 * ray + c]).collect();
                    let g = values(field.sdf_gradient(Tensor::from_data(TensorData::new(p, [1, 3]), &device), &pose, umbra::field::GRADIENT));
                    let norm = g.iter().map(|x| x * x).sum::<f32>().sqrt();
                    let mut n = vec![0.0; 3 * rays.len()];
                    n[3 * ray..3 * ray + 3].copy_from_slice(&[g[0] / norm, g[1] / norm, g[2] / norm]);
                    n
                };
                let (before, after) = (side(-1e-5), side(1e-5));
                assert!(!agree(&before, &after), "ray {ray} ({sampling:?}): normals differ where the gradient is continuous");
                for (what, n) in [("training", &trained_normal), ("still", &still_normal)] {
                    assert!(agree(n, &before) || agree(n, &after), "ray {ray} ({sampling:?}): the {what} normal is neither side's");
                }
                on_a_face += 1;
            }
            assert!(on_a_face <= 2, "{on_a_face} of {} rays' normals differ ({sampling:?})", rays.len());
        }
    }
}

/// Beyond the root's cap the capsule prior is the cap (less the prior's radius) in every pose:
/// a point carried rigidly by the pelvis (a skirt's side at its hem) keeps its prior while the
/// thighs swing inside the skirt; uncapped, the prior follows the nearest thigh.
#[test]
fn the_capped_prior_holds_a_hem_point_still_while_the_legs_swing() {
    let s = setup();
    let device = Device::flex();
    let hem = DVec3::new(0.36, -0.36, 0.0);
    let prior_at = |config: &FieldConfig, phase: f64| -> f32 {
        let field = config.init(&device, 0);
        let pose = s.character.pose(phase, 0.2, DVec3::ZERO);
        let frames = PoseTensors::new(&pose, &s.character.skeleton, &device).frames;
        let point = pose.to_world(0, hem);
        let input = Tensor::<2>::from_data(TensorData::new(vec![point.x as f32, point.y as f32, point.z as f32], [1, 3]), &device);
        values(field.grid.as_ref().unwrap().encode(input, &frames, config.skinning(), false, None).prior)[0]
    };
    let capped = &s.config;
    let root = capped.grid.as_ref().unwrap().root.unwrap();
    assert!(root.prior_capped, "a loose body's root caps the prior");
    let mut uncapped = s.config.clone();
    uncapped.grid.as_mut().unwrap().root = Some(RootSkinning { prior_capped: false, ..root });
    let phases = [0.0, 0.25, 0.5];
    let free: Vec<f32> = phases.iter().map(|&p| prior_at(&uncapped, p)).collect();
    let held: Vec<f32> = phases.iter().map(|&p| prior_at(capped, p)).collect();
    let spread = |v: &[f32]| v.iter().cloned().fold(f32::MIN, f32::max) - v.iter().cloned().fold(f32::MAX, f32::min);
    assert!(spread(&free) > 0.01, "the uncapped prior follows the legs: {free:?}");
    for h in &held {
        assert!((h - (root.cap - capped.prior_radius)).abs() < 1e-6, "{held:?}");
    }
}

/// The capped prior: unchanged below the cap with slope 1, the cap above it with slope 0.
#[test]
fn the_capped_prior_stops_at_its_cap() {
    use umbra::field::grid::saturate;
    let cap = 0.09f32;
    assert_eq!(saturate(cap - 0.001, cap), (cap - 0.001, 1.0));
    assert_eq!(saturate(cap + 0.001, cap), (cap, 0.0));
    assert_eq!(saturate(cap, cap), (cap, 1.0));
}

#[test]
fn a_lookup_asked_for_more_bones_than_a_plan_holds_takes_the_most_it_can() {
    // `umbra bench steps` asked for every bone of the human (17): the plan holds at most
    // MAX_TOP_BONES per point, and asking for more must not index past them.
    let s = setup();
    let mut grid = s.config.grid.clone().unwrap();
    grid.top_bones = s.character.skeleton.len();
    assert!(grid.top_bones > umbra::field::grid::MAX_TOP_BONES);
    assert_eq!(grid.top(), umbra::field::grid::MAX_TOP_BONES);
    let levels = grid.layout();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &Device::flex()).frames;
    let pts = points(&s, 50, 5);
    let plan = lookup(&grid, &levels, &frames, skinning(&s.config), &flat(&pts), true);
    assert_eq!(plan.coefficients.len(), pts.len() * grid.corners());
    assert_eq!(plan.root_slot.len(), pts.len() * grid.top());
}

/// The gradient of every parameter of `field`, by name, summed over its forks.
fn named_gradients(grads: &mut burn::tensor::Gradients, field: &AvatarField, forks: &[AvatarField]) -> Vec<(String, Vec<f32>)> {
    struct Collect<'a> {
        grads: &'a burn::optim::GradientsParams,
        path: Vec<String>,
        out: Vec<(String, Vec<f32>)>,
    }
    impl burn::module::ModuleVisitor for Collect<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let g = self.grads.get::<D>(param.id).map(values).unwrap_or_default();
            self.out.push((self.path.join("."), g));
        }
    }
    let summed = umbra::render::sum_gradients(grads, field, forks);
    let mut collect = Collect { grads: &summed, path: Vec::new(), out: Vec::new() };
    field.visit(&mut collect);
    collect.out
}

#[test]
fn a_render_split_over_threads_is_the_whole_render_and_so_are_its_gradients() {
    let s = setup();
    let device = Device::flex().autodiff();
    let field = busy_field(&FieldConfig { albedo_layers: 2, ..s.config.clone() }, &device, false);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let mut stream = Stream::new(9, 1, 0);
    // 301 rays: three parts of 101, 101 and 99 (the last one short).
    let rays = rays_through_the_body(&s, 301, &mut stream);
    let sampling = umbra::render::Sampling { coarse: 16, probe: 16, fine: 16, albedo_floor: umbra::render::ALBEDO_WEIGHT_FLOOR, cull: false };
    let jitter: Vec<f32> = (0..rays.len() * sampling.draws()).map(|_| stream.uniform() as f32).collect();
    let run = |parts: usize| {
        let (d, split) = umbra::render::render_in_parts(&field, &pose, &rays, sampling, &jitter, Some(umbra::field::GRADIENT), &device, parts);
        assert_eq!(split.forks().len(), if parts == 1 { 0 } else { parts });
        let normal = d.normal.clone().unwrap();
        // Every output in the loss, each weighted differently per ray so that a part out of
        // place changes it.
        let r = rays.len();
        let ramp = Tensor::<1>::from_data(TensorData::new((0..r).map(|i| 1.0 + i as f32 / r as f32).collect::<Vec<_>>(), [r]), &device);
        let loss = (d.accumulation.clone() * ramp.clone()).sum()
            + (d.albedo.clone().sum_dim(1).reshape([r]) * ramp.clone()).sum()
            + (normal.sum_dim(1).reshape([r]) * ramp.clone()).sum()
            + (d.depth.clone() * d.accumulation.clone() * ramp.clone()).sum() * 1e-2
            + (d.surface.clone().sum_dim(1).reshape([r]) * ramp).sum() * 1e-2
            + d.sample_density.clone().sum() * 1e-3;
        let outputs = [values(d.accumulation.clone()), values(d.albedo.clone()), values(d.depth.clone()), values(d.sample_points.clone())];
        // Each part's backward pass on a thread of its own, from its outputs' gradients.
        let mut grads = split.backward(&loss.reshape([1]), true);
        (outputs, named_gradients(&mut grads, &field, split.forks()))
    };
    let (whole, whole_grads) = run(1);
    let (split, split_grads) = run(3);
    assert!(whole[0].iter().filter(|&&a| a > 0.5).count() > 10, "rays hit the body");
    for (k, (a, b)) in whole.iter().zip(&split).enumerate() {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-4 * (1.0 + x.abs()), "output {k}: whole {x}, split {y}");
        }
    }
    assert_same_gradients(&whole_grads, &split_grads, "split");
}

/// Every parameter's gradient `b` within 1e-3 of the largest of `a`'s, and at least four
/// parameters with any gradient at all.
fn assert_same_gradients(a: &[(String, Vec<f32>)], b: &[(String, Vec<f32>)], what: &str) {
    assert_eq!(a.len(), b.len());
    let mut nonzero = 0;
    for ((name, a), (_, b)) in a.iter().zip(b) {
        assert_eq!(a.len(), b.len(), "{name}: a gradient on one side only");
        let scale = a.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-6);
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-3 * scale, "{name}: whole {x}, {what} {y} (largest {scale})");
        }
        nonzero += usize::from(a.iter().any(|&x| x != 0.0));
    }
    assert!(nonzero >= 4, "only {nonzero} parameters have gradients");
}

#[test]
fn a_culled_render_is_the_full_render_and_so_are_its_gradients() {
    let s = setup();
    let device = Device::flex().autodiff();
    // A surface about as sharp as a fit's (beta 2 mm; fits end at 0.5 mm), so that most samples
    // lie in empty space or behind the surface, as they do in training.
    let config = FieldConfig { albedo_layers: 2, initial_beta: 0.002, ..s.config.clone() };
    let field = busy_field(&config, &device, false);
    let pose = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let mut stream = Stream::new(10, 1, 0);
    let rays = rays_through_the_body(&s, 200, &mut stream);
    let full = umbra::render::Sampling { coarse: 16, probe: 16, fine: 16, albedo_floor: 0.0, cull: false };
    let jitter: Vec<f32> = (0..rays.len() * full.draws()).map(|_| stream.uniform() as f32).collect();
    let run = |sampling: umbra::render::Sampling| {
        let (d, split) =
            umbra::render::render_in_parts(&field, &pose, &rays, sampling, &jitter, Some(umbra::field::GRADIENT), &device, if sampling.cull { 2 } else { 1 });
        let r = rays.len();
        let ramp = Tensor::<1>::from_data(TensorData::new((0..r).map(|i| 1.0 + i as f32 / r as f32).collect::<Vec<_>>(), [r]), &device);
        let loss = (d.accumulation.clone() * ramp.clone()).sum()
            + (d.albedo.clone().sum_dim(1).reshape([r]) * ramp.clone()).sum()
            // Depth and normal as shading sees them: scaled by the ray's coverage.
            + (d.depth.clone() * d.accumulation.clone() * ramp.clone()).sum()
            + (d.normal.clone().unwrap().sum_dim(1).reshape([r]) * d.accumulation.clone() * ramp).sum();
        let outputs = [values(d.accumulation.clone()), values(d.albedo.clone()), values(d.depth.clone()), values(d.sample_density.clone())];
        let mut grads = split.backward(&loss.reshape([1]), true);
        (outputs, named_gradients(&mut grads, &field, split.forks()), d.evaluated)
    };
    let (whole, whole_grads, all) = run(full);
    let (culled, culled_grads, kept) = run(umbra::render::Sampling { cull: true, ..full });
    assert_eq!(all, rays.len() * full.total());
    assert!(whole[0].iter().filter(|&&a| a > 0.5).count() > 20 && whole[0].iter().filter(|&&a| a < 0.5).count() > 20, "rays hit and miss the body");
    // Every fine sample is kept (half the samples); most coarse ones go.
    assert!(kept * 8 < all * 5, "culling leaves out most coarse samples: {kept} of {all} evaluated");
    for (k, (a, b)) in whole.iter().zip(&culled).enumerate() {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            // A ray that sees next to nothing has no depth to speak of (its weighted mean
            // distance over a vanishing weight); what it shades is scaled by that weight.
            if k == 2 && whole[0][i] < 1e-2 {
                continue;
            }
            assert!((x - y).abs() <= 1e-4 * (1.0 + x.abs()), "output {k}: full {x}, culled {y}");
        }
    }
    assert_same_gradients(&whole_grads, &culled_grads, "culled");
}

/// The plan made with tensor ops on the points' device (`lookup_on_device`, a GPU's) is the
/// host's (`lookup`): the same bones, rows and root corners, and the same coefficients,
/// logits, prior and world derivatives to f32 rounding; with the root capped or not, a
/// level inactive, dense and hashed levels and the root's own table.
#[test]
fn the_plan_made_on_the_device_is_the_hosts() {
    use umbra::field::tensor_lookup::lookup_on_device;
    let s = setup();
    let grid = s.config.grid.clone().unwrap();
    let device = Device::flex();
    let frames = PoseTensors::new(&s.pose, &s.character.skeleton, &device).frames;
    let mut pts = points(&s, 300, 9);
    // Far outside every bone's box (clamped to the grids' borders) and on a bone's axis.
    pts.push(DVec3::new(3.0, -2.0, 4.0));
    pts.push(s.pose.to_world(2, DVec3::new(0.0, 0.05, 0.0)));
    let n = pts.len();
    let ints = |t: Tensor<1, burn::tensor::Int>| t.into_data().convert::<i64>().try_to_vec::<i64>().unwrap();
    for (what, skin, inactive) in [("capped root", skinning(&s.config), 8), ("by distance", uncapped(&s.config), 5)] {
        let mut levels = grid.layout();
        for level in levels.iter_mut().skip(inactive) {
            level.active = false;
        }
        assert!(levels.iter().any(|l| l.dense) && levels.iter().any(|l| !l.dense));
        let host = lookup(&grid, &levels, &frames, skin, &flat(&pts), true);
        let points = Tensor::<2>::from_data(TensorData::new(flat(&pts), [n, 3]), &device);
        let plan = lookup_on_device(&grid, &levels, &frames, skin, points, true);
        let bones: Vec<u32> = ints(plan.bones.clone().reshape([n * grid.top()])).iter().map(|&b| b as u32).collect();
        assert_eq!(bones, host.bones, "{what}: bones");
        let rows: Vec<u32> = ints(plan.rows.clone()).iter().map(|&r| r as u32).collect();
        let differ = rows.iter().zip(&host.rows).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "{what}: {differ} of {} rows differ", rows.len());
        let root_rows: Vec<u32> = ints(plan.root_rows.clone()).iter().map(|&r| r as u32).collect();
        assert_eq!(root_rows, host.root_rows, "{what}: root rows");
        let close = |name: &str, a: Vec<f32>, b: &[f32], tolerance: f32| {
            assert_eq!(a.len(), b.len(), "{what}: {name}");
            let scale = b.iter().map(|v| v.abs()).fold(0.0f32, f32::max).max(1e-6);
            let (at, worst) = a.iter().zip(b).map(|(x, y)| (x - y).abs()).enumerate().fold((0, 0.0f32), |m, (i, d)| if d > m.1 { (i, d) } else { m });
            assert!(worst <= tolerance * scale, "{what}: {name} differs by {worst} at {at} ({} against {}; largest {scale})", a[at], b[at]);
        };
        close("coefficients", values(plan.coefficients.clone()), &host.coefficients, 1e-6);
        close("coefficient tangents", values(plan.coefficient_tangents.clone().unwrap()), &host.coefficient_tangents, 1e-5);
        close("logits", values(plan.logits.clone()), &host.logits, 1e-6);
        close("logit tangents", values(plan.logit_tangents.clone().unwrap()), &host.logit_tangents, 1e-6);
        close("root slot", values(plan.root_slot.clone()), &host.root_slot, 0.0);
        close("root coefficients", values(plan.root_coefficients.clone()), &host.root_coefficients, 1e-6);
        close("root coefficient tangents", values(plan.root_coefficient_tangents.clone()), &host.root_coefficient_tangents, 1e-5);
        close("prior", values(plan.prior.clone()), &host.prior, 1e-6);
        close("prior tangents", values(plan.prior_tangents().unwrap()), &host.prior_tangents, 1e-5);
        close("prior slot tangents", values(plan.prior_slot_tangents.clone().unwrap()), &host.prior_slot_tangents, 1e-5);
        // Without tangents: the same plan, and no gradients computed.
        let points = Tensor::<2>::from_data(TensorData::new(flat(&pts), [n, 3]), &device);
        let bare = lookup_on_device(&grid, &levels, &frames, skin, points, false);
        assert!(bare.coefficient_tangents.is_none() && bare.logit_tangents.is_none() && bare.prior_slot_tangents.is_none(), "{what}");
        assert_eq!(ints(bare.rows), ints(plan.rows.clone()), "{what}: rows without tangents");
        close("coefficients without tangents", values(bare.coefficients), &host.coefficients, 1e-6);
        close("prior without tangents", values(bare.prior), &host.prior, 1e-6);
    }
}

/// The field's outputs with its grid lookup on `route`: the SDF of points carrying a motion and
/// a view increment, weighted and summed; the table's, the root preference's and both
/// increments' gradients; the SDF's spatial gradient (the tangents) and the SDF without
/// gradients.
fn outputs_by_route(route: umbra::field::grid::Route, field: &AvatarField, s: &Setup, pts: &[DVec3]) -> Vec<(&'static str, Vec<f32>)> {
    use umbra::skeleton::{MotionIncrement, ViewIncrement};
    let device = Device::flex().autodiff();
    let mut field = field.clone();
    field.grid.as_mut().unwrap().route = route;
    let n = pts.len();
    let mut tensors = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    tensors.motion = Some(MotionIncrement::new(&s.character.skeleton, &s.pose, &device));
    let origins: Vec<f32> = (0..n).flat_map(|k| [0.3 * (k % 3) as f32, 1.0, -2.5]).collect();
    let rows: Vec<u32> = (0..n as u32).map(|k| k % 2).collect();
    let view = ViewIncrement::new(2, 0.01, &device);
    let along = view.along(&rows, origins);
    let input = || Tensor::<2>::from_data(TensorData::new(flat(pts), [n, 3]), &device);
    let mut stream = Stream::new(4, 4, 0);
    let w: Vec<f32> = (0..n).map(|_| (stream.uniform() * 2.0 - 1.0) as f32).collect();
    let weights = Tensor::<1>::from_data(TensorData::new(w, [n]), &device);
    let grid = field.grid.as_ref().unwrap();
    let features = grid.encode_carrying(input(), &tensors.frames, s.config.skinning(), false, tensors.motion.as_ref(), Some(&along));
    let sdf = field.decode(input(), &tensors).sdf;
    let loss = (sdf.clone() * weights.clone()).sum() + (features.features * 0.1).sum() + (features.prior * weights).sum();
    let grads = loss.backward();
    let grid = field.grid.as_ref().unwrap();
    let plain = PoseTensors::new(&s.pose, &s.character.skeleton, &device);
    let (_, normal) = field.sdf_and_gradient(input(), &plain);
    vec![
        ("sdf", values(sdf.inner())),
        ("table gradient", values(grid.table.grad(&grads).expect("the table is in the graph"))),
        ("root preference gradient", values(grid.root_preference.as_ref().unwrap().grad(&grads).expect("the preference is in the graph"))),
        ("motion gradient", values(tensors.motion.as_ref().unwrap().leaf.grad(&grads).expect("the motion is in the graph"))),
        ("view gradient", values(view.leaf.grad(&grads).expect("the view is in the graph"))),
        ("sdf gradient", values(normal)),
        ("sdf without gradients", values(field.valid().decode(input().inner(), &plain).sdf)),
    ]
}

/// The lookup by tensor ops alone, planned on the device as a GPU runs it (`Route::Tensors`),
/// and the composite of the host's plan (`Route::Composite`) give the fused op's values and
/// gradients (to the table, the root's preference, a carried motion and view), its tangents
/// and its lookup without gradients, on the CPU.
#[test]
fn the_lookup_by_tensor_ops_is_the_fused_lookup() {
    use umbra::field::grid::Route;
    let s = setup();
    let field = busy_field(&s.config, &Device::flex().autodiff(), true);
    let pts = points(&s, 240, 12);
    let fused = outputs_by_route(Route::Fused, &field, &s, &pts);
    for route in [Route::Tensors, Route::Composite] {
        for ((what, a), (_, b)) in outputs_by_route(route, &field, &s, &pts).iter().zip(&fused) {
            assert_eq!(a.len(), b.len(), "{route:?} {what}");
            let scale = b.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
            let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            assert!(scale > 1e-6, "{what}: nothing to compare");
            assert!(worst <= 1e-5 * scale, "{route:?} {what}: differs by {worst} (largest {scale})");
        }
    }
}
