//! Adam on a few numbers kept on the host, in rows of three with their moments: the cameras'
//! colours (`camera_colour`) and the motion's corrections (`motion`), too small to be worth a
//! parameter group on the device.

/// Adam's decay rates and its guard against a zero second moment (burn's defaults).
const BETAS: (f64, f64) = (0.9, 0.999);
const EPSILON: f64 = 1e-8;

/// Step `t` (from 1) of Adam at `rate` on `values`, with `gradient` and the moments `first` and
/// `second` (all one row per value row).
pub fn step(values: &mut [[f64; 3]], first: &mut [[f64; 3]], second: &mut [[f64; 3]], gradient: &[[f64; 3]], t: u64, rate: f64) {
    let (b1, b2) = BETAS;
    let t = t.min(i32::MAX as u64) as i32;
    let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
    for (((value, m), v), g) in values.iter_mut().zip(first.iter_mut()).zip(second.iter_mut()).zip(gradient) {
        for c in 0..3 {
            m[c] = b1 * m[c] + (1.0 - b1) * g[c];
            v[c] = b2 * v[c] + (1.0 - b2) * g[c] * g[c];
            value[c] -= rate * (m[c] / c1) / ((v[c] / c2).sqrt() + EPSILON);
        }
    }
}
