//! The grid's lookup where nothing is differentiated (the samples that search a ray for the
//! body): the plan's skinning and corners (`lookup`) and the fused op's weighted sum in one pass
//! on the host, and the one weighted sum of a table row both use.

use super::layout::{GridConfig, Level, MAX_TOP_BONES};
use super::lookup::{skin_point, visit_cells, Scratch, Skinning};
use crate::skeleton::BoneFrame;
use rayon::prelude::*;

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
                    add_row(table, row as usize, weight * fade[level], sums);
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

/// Adds `coefficient` times table row `row` (`sums.len()` features wide) to `sums`: the one
/// weighted sum of the planned op and of the one-pass lookup. A row outside the table (never
/// planned) reads NaN, so it cannot pass unseen.
#[inline(always)]
pub(super) fn add_row(table: &[f32], row: usize, coefficient: f32, sums: &mut [f32]) {
    // Two features per entry (the default grid, as instant-NGP's) on a path of its own: the
    // general one's loop and slice cost as much as the sum itself there.
    if let [s0, s1] = sums {
        match table.get(2 * row..2 * row + 2) {
            Some(&[t0, t1]) => {
                *s0 += coefficient * t0;
                *s1 += coefficient * t1;
            }
            _ => (*s0, *s1) = (f32::NAN, f32::NAN),
        }
        return;
    }
    let start = row * sums.len();
    match table.get(start..start + sums.len()) {
        Some(entry) => sums.iter_mut().zip(entry).for_each(|(o, t)| *o += coefficient * t),
        None => sums.iter_mut().for_each(|o| *o = f32::NAN),
    }
}
