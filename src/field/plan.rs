//! A planned lookup of the grid's table, and its arithmetic on the host: per point and level
//! the corner rows and their coefficients (`Plan`), what a carried shift's gradient follows
//! from (`Carried`), and the weighted sums, the table's gradient and the shift's gradient that
//! the CPU backends' fused op (`interpolate`) computes from them.

use super::host_lookup::add_row;
use rayon::prelude::*;

/// A planned interpolation of `points` points: per point and level, `corners` table rows with
/// their coefficients (point-major, then level, then corner) and, when the tangents are
/// wanted, each coefficient's derivative along the three world axes; `fade` weighs each level
/// (coarse to fine).
#[derive(Debug)]
pub struct Plan {
    pub points: usize,
    pub levels: usize,
    pub corners: usize,
    pub features: usize,
    pub rows: Vec<u32>,
    pub coefficients: Vec<f32>,
    pub tangents: Option<Vec<f32>>,
    /// What the coefficients' world derivatives follow from when the lookup carries a shift of
    /// its points (`interpolate_carrying`): only the shift's gradient reads it.
    pub carried: Option<Carried>,
    pub fade: Vec<f32>,
    /// The table's rows are this many equal runs, group `g`'s rows lying in run
    /// `g % table_parts` (the grid's table is level-major: its level count; 1 for any table).
    pub table_parts: usize,
}

/// A carried lookup's cells, from which each corner coefficient's world derivative follows: a
/// group is a (slot, level) pair (`groups = slots x levels`, slot-major), a slot one of the
/// point's chosen bones. Per cell (point, group) the point's fractions along the slot's bone's
/// local axes, plus 2 on an axis outside the grid (no derivative there); per point and slot the
/// bone's local axes in the world (row-major 3 x 3: row m is axis m); per level 1 / its cell
/// size. 3 floats a cell against the 24 of per-corner derivatives.
#[derive(Debug)]
pub struct Carried {
    /// Chosen bones per point, and levels per bone: `slots x levels` groups.
    pub slots: usize,
    pub levels: usize,
    pub fractions: Vec<f32>,
    pub axes: Vec<f32>,
    pub per_cell: Vec<f32>,
}

/// Corner `k`'s (bit 0 the x side, bit 1 y, bit 2 z) trilinear weight's derivatives along the
/// cell's three fractions `f`.
fn corner_slopes(f: [f32; 3], k: usize) -> [f32; 3] {
    let bit = [k & 1, (k >> 1) & 1, k >> 2];
    let factor = [0, 1, 2].map(|m| if bit[m] == 1 { f[m] } else { 1.0 - f[m] });
    [0, 1, 2].map(|m| {
        let sign = if bit[m] == 1 { 1.0 } else { -1.0 };
        sign * factor[(m + 1) % 3] * factor[(m + 2) % 3]
    })
}

impl Carried {
    /// Cell `(point, group)`'s fractions, and the derivative of each fraction along the world
    /// (row m: the slot's bone's axis m over the level's cell size; zero outside the grid).
    fn cell(&self, point: usize, group: usize) -> ([f32; 3], [[f32; 3]; 3]) {
        let cell = point * self.slots * self.levels + group;
        let raw = [0, 1, 2].map(|m| self.fractions.get(cell * 3 + m).copied().unwrap_or(f32::NAN));
        let (slot, level) = (group / self.levels, group % self.levels);
        let at = (point * self.slots + slot) * 9;
        let scale = self.per_cell.get(level).copied().unwrap_or(f32::NAN);
        let rows = [0, 1, 2].map(|m| match raw[m] < 2.0 {
            true => [0, 1, 2].map(|x| self.axes.get(at + m * 3 + x).copied().unwrap_or(f32::NAN) * scale),
            false => [0.0; 3],
        });
        (raw.map(|v| if v < 2.0 { v } else { v - 2.0 }), rows)
    }
}

impl Plan {
    /// Output rows: the features, then the tangents axis-major when planned.
    pub fn output_rows(&self) -> usize {
        self.points * self.blocks()
    }

    /// A carried shift's values per point: three per chosen bone (three without a carry).
    pub fn shift_width(&self) -> usize {
        3 * self.carried.as_ref().map_or(1, |c| c.slots)
    }

    /// Output blocks of `points` rows: the features, and the three tangents when planned.
    pub fn blocks(&self) -> usize {
        if self.tangents.is_some() {
            4
        } else {
            1
        }
    }

    pub(super) fn width(&self) -> usize {
        self.levels * self.features
    }

    /// The weighted sums (`[output_rows, W]`, row-major) of `table` (`[T, F]`, row-major).
    pub(super) fn forward(&self, table: &[f32]) -> Vec<f32> {
        let (n, w, c) = (self.points, self.width(), self.corners);
        let mut out = vec![0.0f32; self.output_rows() * w];
        let (values, tangents) = out.split_at_mut(n * w);
        // Points in chunks across threads: each point owns its output rows.
        const CHUNK: usize = 256;
        let tangent_chunks: Vec<&mut [f32]> = match self.tangents {
            Some(_) => tangents.chunks_mut(n * w).collect(),
            None => Vec::new(),
        };
        let per_point = self.levels * c;
        values.par_chunks_mut(CHUNK * w).enumerate().for_each(|(chunk, values)| {
            for (k, row_out) in values.chunks_mut(w).enumerate() {
                let i = chunk * CHUNK + k;
                let rows = &self.rows[i * per_point..(i + 1) * per_point];
                let coefficients = &self.coefficients[i * per_point..(i + 1) * per_point];
                self.accumulate(table, rows, coefficients.iter().copied(), row_out);
            }
        });
        if let Some(d) = &self.tangents {
            // One axis per task: each writes its own `[N, W]` block.
            tangent_chunks.into_par_iter().enumerate().for_each(|(axis, block)| {
                for (i, row_out) in block.chunks_mut(w).enumerate() {
                    let rows = &self.rows[i * per_point..(i + 1) * per_point];
                    let d = &d[i * per_point * 3..(i + 1) * per_point * 3];
                    self.accumulate(table, rows, d.iter().skip(axis).step_by(3).copied(), row_out);
                }
            });
        }
        out
    }

    /// One point's weighted sum into `row_out` (`[W]`): level by level, each of its corners'
    /// table rows (`rows`, `levels x corners`) times its coefficient and the level's fade. A row
    /// outside the table (never planned) reads NaN, so it cannot pass unseen.
    fn accumulate(&self, table: &[f32], rows: &[u32], coefficients: impl Iterator<Item = f32>, row_out: &mut [f32]) {
        let (f, c) = (self.features, self.corners);
        let mut coefficients = coefficients;
        for ((out, level_rows), &fade) in row_out.chunks_mut(f).zip(rows.chunks(c)).zip(&self.fade) {
            for &row in level_rows {
                add_row(table, row as usize, coefficients.next().unwrap_or(0.0) * fade, out);
            }
        }
    }

    /// The table's gradient (`[table_rows, F]`) from the output's (`[output_rows, W]`). The
    /// table's rows are level-major (`table_parts` runs), so each thread takes a run of
    /// consecutive levels and fills their rows alone: no per-thread copies of the table to zero
    /// and add up (4-8 MB each, a quarter of this op's time).
    pub(super) fn backward(&self, grad: &[f32], table_rows: usize) -> Vec<f32> {
        let f = self.features;
        let parts = self.table_parts.max(1);
        let part_rows = table_rows / parts;
        let tasks = rayon::current_num_threads().clamp(1, parts);
        // Task t's levels, and the slice of the table holding their rows.
        let levels_of = |t: usize| (t * parts / tasks)..((t + 1) * parts / tasks);
        let mut total = vec![0.0f32; table_rows * f];
        let mut slices = Vec::with_capacity(tasks);
        let mut rest = total.as_mut_slice();
        for t in 0..tasks {
            let take = if t + 1 == tasks { rest.len() } else { levels_of(t).len() * part_rows * f };
            let (slice, tail) = rest.split_at_mut(take);
            slices.push(slice);
            rest = tail;
        }
        slices.into_par_iter().enumerate().for_each(|(t, values)| {
            let levels = levels_of(t);
            let first = levels.start * part_rows;
            // A level faded out (coarse to fine) adds nothing: its groups are skipped whole.
            let groups: Vec<usize> = (0..self.levels).filter(|g| levels.contains(&(g % parts)) && self.fade[*g] != 0.0).collect();
            match f {
                2 => self.scatter::<2>(grad, values, first, &groups),
                _ => self.scatter_any(grad, values, first, &groups),
            }
        });
        total
    }
}

impl Plan {
    /// `backward`'s work for one run of the table (`values`, whose first row is `first`) and
    /// its `groups`, with `F` features a row: per point and group the output's gradient (and
    /// its tangents' gradients) read once, faded, then added into each corner's row.
    fn scatter<const F: usize>(&self, grad: &[f32], values: &mut [f32], first: usize, groups: &[usize]) {
        let (n, w, c) = (self.points, self.width(), self.corners);
        let count = values.len() / F;
        for i in 0..n {
            for &g in groups {
                let column = g * F;
                let fade = self.fade[g];
                let value: [f32; F] = std::array::from_fn(|q| grad[i * w + column + q] * fade);
                let along: Option<[[f32; F]; 3]> =
                    self.tangents.as_ref().map(|_| std::array::from_fn(|axis| std::array::from_fn(|q| grad[(n + axis * n + i) * w + column + q] * fade)));
                let at = (i * self.levels + g) * c;
                for j in 0..c {
                    // A row outside this run (or the table) is a level left out of the plan:
                    // row 0, coefficient 0, nothing to add.
                    let row = (self.rows[at + j] as usize).wrapping_sub(first);
                    if row >= count {
                        continue;
                    }
                    let k = self.coefficients[at + j];
                    let mut sum: [f32; F] = std::array::from_fn(|q| k * value[q]);
                    if let (Some(d), Some(along)) = (&self.tangents, &along) {
                        for axis in 0..3 {
                            let slope = d[(at + j) * 3 + axis];
                            for q in 0..F {
                                sum[q] += slope * along[axis][q];
                            }
                        }
                    }
                    for (out, add) in values[row * F..(row + 1) * F].iter_mut().zip(sum) {
                        *out += add;
                    }
                }
            }
        }
    }

    /// `scatter` for any number of features a row.
    fn scatter_any(&self, grad: &[f32], values: &mut [f32], first: usize, groups: &[usize]) {
        let (n, w, f, c) = (self.points, self.width(), self.features, self.corners);
        let count = values.len() / f;
        for i in 0..n {
            for &g in groups {
                let fade = self.fade[g];
                for j in 0..c {
                    let at = (i * self.levels + g) * c + j;
                    let row = (self.rows[at] as usize).wrapping_sub(first);
                    if row >= count {
                        continue;
                    }
                    for q in 0..f {
                        let column = g * f + q;
                        let mut sum = self.coefficients[at] * grad[i * w + column];
                        if let Some(d) = &self.tangents {
                            for axis in 0..3 {
                                sum += d[at * 3 + axis] * grad[(n + axis * n + i) * w + column];
                            }
                        }
                        values[row * f + q] += sum * fade;
                    }
                }
            }
        }
    }
}

impl Plan {
    /// The gradient (`[N, 3 S]`, row-major: per point, per slot, per axis) of a shift of each
    /// point's lookup in each of its `S` chosen bones, to first order, from the output's
    /// (`[N, W]`): per point and slot, each corner's table row against the output's gradient,
    /// times the level's fade and the coefficient's world derivative, contracted per cell along
    /// its fractions before it is turned into the world (`Carried`).
    pub(super) fn shift_backward(&self, grad: &[f32], table: &[f32]) -> Vec<f32> {
        let (w, f, c) = (self.width(), self.features, self.corners);
        let row = self.shift_width();
        let Some(carried) = &self.carried else { return vec![0.0; row * self.points] };
        let per_point = self.levels * c;
        let mut out = vec![0.0f32; row * self.points];
        // Points in chunks across threads: each point owns its row.
        const CHUNK: usize = 256;
        out.par_chunks_mut(row * CHUNK).enumerate().for_each(|(chunk, shifts)| {
            for (k, point_shifts) in shifts.chunks_mut(row).enumerate() {
                let i = chunk * CHUNK + k;
                for g in 0..self.levels {
                    let fade = self.fade[g];
                    let grad = &grad[i * w + g * f..i * w + (g + 1) * f];
                    // A level faded out, or one whose output nothing weighs, moves nothing.
                    if fade == 0.0 || grad.iter().all(|&v| v == 0.0) {
                        continue;
                    }
                    // The corners contracted along the cell's fractions first, then turned
                    // into the world once per cell.
                    let (fractions, rows) = carried.cell(i, g);
                    let mut along_fractions = [0.0f32; 3];
                    for j in 0..c {
                        let row = self.rows[i * per_point + g * c + j] as usize;
                        let along: f32 = match table.get(row * f..(row + 1) * f) {
                            Some(entry) => entry.iter().zip(grad).map(|(t, g)| t * g).sum(),
                            None => f32::NAN,
                        };
                        let slopes = corner_slopes(fractions, j);
                        for m in 0..3 {
                            along_fractions[m] += along * slopes[m];
                        }
                    }
                    let slot = g / carried.levels;
                    for (axis, s) in point_shifts.iter_mut().skip(3 * slot).take(3).enumerate() {
                        *s += fade * (0..3).map(|m| along_fractions[m] * rows[m][axis]).sum::<f32>();
                    }
                }
            }
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table's gradient summed as plainly as it can be: every planned corner's coefficient
    /// (and tangent coefficients) times the output's gradient, times the level's fade.
    fn plain_backward(plan: &Plan, grad: &[f32], table_rows: usize) -> Vec<f32> {
        let (n, w, f, c) = (plan.points, plan.width(), plan.features, plan.corners);
        let mut values = vec![0.0f64; table_rows * f];
        for i in 0..n {
            for g in 0..plan.levels {
                for j in 0..c {
                    let at = (i * plan.levels + g) * c + j;
                    let row = plan.rows[at] as usize;
                    for q in 0..f {
                        let column = g * f + q;
                        let mut sum = plan.coefficients[at] as f64 * grad[i * w + column] as f64;
                        if let Some(d) = &plan.tangents {
                            for axis in 0..3 {
                                sum += d[at * 3 + axis] as f64 * grad[(n + axis * n + i) * w + column] as f64;
                            }
                        }
                        values[row * f + q] += sum * plan.fade[g] as f64;
                    }
                }
            }
        }
        values.into_iter().map(|v| v as f32).collect()
    }

    /// A plan of `n` points over a table of `parts` levels of `per_level` rows, each point in
    /// three bones' grids, the coarse levels' corners close together and the fine ones' spread,
    /// with a level faded out and one half in.
    fn random_plan(n: usize, features: usize, tangents: bool) -> (Plan, Vec<f32>, usize) {
        let (parts, per_level, slots) = (4usize, 512usize, 3usize);
        let levels = parts * slots;
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let (mut rows, mut coefficients) = (Vec::new(), Vec::new());
        for i in 0..n {
            for g in 0..levels {
                let level = g % parts;
                let spread = (16usize << (2 * level)).min(per_level);
                let base = (i * 7) % (per_level - spread + 1);
                for _ in 0..8 {
                    rows.push((level * per_level + base + next() as usize % spread) as u32);
                    coefficients.push((next() % 1000) as f32 / 1000.0);
                }
            }
        }
        let slopes = tangents.then(|| (0..rows.len() * 3).map(|_| (next() % 2001) as f32 / 1000.0 - 1.0).collect());
        let fade = (0..levels).map(|g| [1.0, 1.0, 0.37, 0.0][g % parts]).collect();
        let plan = Plan { points: n, levels, corners: 8, features, rows, coefficients, tangents: slopes, carried: None, fade, table_parts: parts };
        let blocks = if tangents { 4 } else { 1 };
        let grad = (0..n * blocks * levels * features).map(|_| (next() % 2001) as f32 / 1000.0 - 1.0).collect();
        (plan, grad, parts * per_level)
    }

    /// The two-feature path and the any-width one each against the plain sum, with and without
    /// tangents: every run of the table, faded levels, corners shared by many points.
    #[test]
    fn the_tables_gradient_is_the_plain_sum_of_every_corners_part() {
        for features in [2, 3] {
            for tangents in [false, true] {
                let (plan, grad, table_rows) = random_plan(300, features, tangents);
                let fast = plan.backward(&grad, table_rows);
                let plain = plain_backward(&plan, &grad, table_rows);
                let scale = plain.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                let worst = fast.iter().zip(&plain).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst <= 1e-5 * scale, "{features} features, tangents {tangents}: off by {worst} of {scale}");
                assert!(plain.iter().any(|&v| v != 0.0) && fast.len() == plain.len());
            }
        }
    }
}
