//! What of a given motion is noise: the share of its second differences (each bone's turn over
//! the next step less the last step's, per training frame in time) that a tracker's errors,
//! drawn anew each frame, account for rather than the movement, and the noise's size; and from
//! them how hard the refined motion's smoothness and prior weigh on a capture
//! (`MotionCorrections::smoothness_scale`, `MotionCorrections::prior_scale`).

/// Rows of a frame's correction or of its given motion's second difference: one per bone, then
/// the skeleton's shift.
pub(super) type Rows = Vec<[f64; 3]>;

/// The smoothness's weight per unit of the given motion's noise-to-motion ratio, as a share of
/// the schedule's (`MotionCorrections::smoothness_scale`). A tracker's 2.5 degrees per joint on
/// a walk sampled 12, 20 and 30 times a cycle give ratios of 8, 36 and 61; the weights that
/// measured best there (`docs/measurements.md`) are about 0.01, 0.05 and 0.1, and 0.01 on
/// exact motion, whose ratio is about 0.3: 0.15 of the schedule's 0.01 per unit, at least the
/// schedule's.
pub const SMOOTHNESS_PER_NOISE_RATIO: f64 = 0.15;

/// The largest share of the given motion's second differences taken as noise: the
/// smoothness weighs at most `0.15 f / (1 - f)`, about 15 times the schedule's weight, where the
/// estimate's own scatter over a few dozen frames would otherwise let it grow without bound.
pub const MOST_NOISE_SHARE: f64 = 0.99;

/// The given motion's noise per frame that the schedule's `motion_prior` weight holds a correction
/// against (radians per axis): 2.5 degrees, the tracker's error the weight was measured at
/// (`docs/measurements.md`). A prior is as strong as the given motion is sure: a capture whose
/// given motion carries less noise holds its corrections in proportion to `1 / noise^2`.
pub const PRIOR_NOISE: f64 = 2.5 * std::f64::consts::PI / 180.0;

/// The most the prior weighs, as a share of the schedule's (`prior_scale`): a motion whose
/// second differences show no noise at all would otherwise be held without bound.
pub const MOST_PRIOR_SCALE: f64 = 1000.0;

/// `MotionCorrections::prior_scale` of the given motion's noise (radians per axis): the
/// schedule's weight times `(PRIOR_NOISE / noise)^2`, never less than the schedule's (a
/// noisier motion than the weight was measured at is not measured) nor more than
/// `MOST_PRIOR_SCALE` times it.
pub(super) fn prior_scale(noise: f64) -> f64 {
    match noise > 0.0 {
        true => (PRIOR_NOISE / noise).powi(2).clamp(1.0, MOST_PRIOR_SCALE),
        false => MOST_PRIOR_SCALE,
    }
}

/// The given motion's noise per frame (radians per axis) of its second differences
/// (`acceleration`, the frames with both neighbours, the bones' rows): noise drawn anew each
/// frame with deviation `s` gives a second difference of variance `6 s^2`, so `s` is the root of
/// the `noise_share` of their mean square over 6. None (zero) without such frames.
pub(super) fn noise(acceleration: &[Rows], neighbours: &[Option<(usize, usize)>], noise_share: f64) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for (rows, _) in acceleration.iter().zip(neighbours).filter(|(_, n)| n.is_some()) {
        for row in &rows[..rows.len().saturating_sub(1)] {
            sum += row.iter().map(|v| v * v).sum::<f64>();
            count += 3;
        }
    }
    match count {
        0 => 0.0,
        _ => (noise_share * sum / count as f64 / 6.0).sqrt(),
    }
}

/// The bias a given motion's noise leaves over `frames` training frames (radians, the expected
/// length of a bone's mean error over them): errors of deviation `noise` per axis drawn anew
/// each frame have a mean of deviation `noise / sqrt(frames)` per axis, and a vector of three
/// such normal components is `sqrt(8 / pi)` times that long on average (a Maxwell
/// distribution's mean). The images cannot tell it from the body (`docs/measurements.md`): the
/// avatar carries it. None (zero) without frames.
pub(super) fn bias(noise: f64, frames: usize) -> f64 {
    match frames {
        0 => 0.0,
        n => (8.0 / std::f64::consts::PI).sqrt() * noise / (n as f64).sqrt(),
    }
}

/// `MotionCorrections::smoothness_scale` of a noise share.
pub(super) fn smoothness_scale(noise_share: f64) -> f64 {
    (SMOOTHNESS_PER_NOISE_RATIO * noise_share / (1.0 - noise_share)).max(1.0)
}

/// `MotionCorrections::noise_share` of the given motion's second differences per corrected
/// frame (`acceleration`, the shift's row left out: its units are not a turn's), pooled over
/// the bones and axes of every pair of neighbouring frames that both have them: with `rho`
/// their correlation, `(1 - rho) / (5/3)`. Without two such pairs there is nothing to tell
/// noise from motion by, and half is taken; a given motion without second differences beyond
/// rounding's is smooth already (none).
pub(super) fn noise_share(acceleration: &[Rows], neighbours: &[Option<(usize, usize)>]) -> f64 {
    let (mut pairs, mut count, mut product, mut here, mut next) = (0usize, 0usize, 0.0, 0.0, 0.0);
    for k in 0..acceleration.len().saturating_sub(1) {
        if neighbours[k].is_none() || neighbours[k + 1].is_none() {
            continue;
        }
        pairs += 1;
        let bones = acceleration[k].len().saturating_sub(1);
        for (a, b) in acceleration[k][..bones].iter().zip(&acceleration[k + 1][..bones]) {
            for c in 0..3 {
                count += 1;
                product += a[c] * b[c];
                here += a[c] * a[c];
                next += b[c] * b[c];
            }
        }
    }
    if pairs < 2 {
        return 0.5;
    }
    // Second differences at rounding's size (a micro-radian) are a motion at constant speed.
    if here.min(next) <= count as f64 * 1e-12 {
        return 0.0;
    }
    let rho = product / (here * next).sqrt();
    ((1.0 - rho) * 0.6).clamp(0.0, MOST_NOISE_SHARE)
}

#[cfg(test)]
mod tests {
    use super::{bias, noise, noise_share, prior_scale, smoothness_scale, Rows, MOST_NOISE_SHARE, MOST_PRIOR_SCALE, PRIOR_NOISE, SMOOTHNESS_PER_NOISE_RATIO};
    use crate::random::Stream;

    /// Per frame, `bones` rows of three channels from `channel(frame, row, axis)` and a shift
    /// row of zeros; the given motion's second differences of them, as `MotionCorrections::new`
    /// takes them.
    fn accelerations(frames: usize, bones: usize, channel: impl Fn(usize, usize, usize) -> f64) -> (Vec<Rows>, Vec<Option<(usize, usize)>>) {
        let neighbours: Vec<_> = (0..frames).map(|k| (k > 0 && k + 1 < frames).then(|| (k - 1, k + 1))).collect();
        let acceleration = (0..frames)
            .map(|k| {
                let mut rows: Rows = (0..bones)
                    .map(|b| match neighbours[k] {
                        Some((p, n)) => [0, 1, 2].map(|c| channel(n, b, c) - 2.0 * channel(k, b, c) + channel(p, b, c)),
                        None => [0.0; 3],
                    })
                    .collect();
                rows.push([0.0; 3]);
                rows
            })
            .collect();
        (acceleration, neighbours)
    }

    /// A standard normal draw per (frame, row, axis), the same for the same arguments.
    fn normal(seed: u64, frame: usize, row: usize, axis: usize) -> f64 {
        let mut stream = Stream::new(seed, frame as u64, (row * 3 + axis) as u64);
        let (u, v) = (stream.uniform().max(1e-300), stream.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    #[test]
    fn the_noise_share_tells_a_trackers_errors_from_the_motion() {
        let walk =
            |frames_a_cycle: f64| move |k: usize, b: usize, c: usize| 0.4 * (std::f64::consts::TAU * k as f64 / frames_a_cycle + b as f64 + c as f64).sin();
        // Errors drawn anew each frame: all noise.
        let (a, n) = accelerations(30, 20, |k, b, c| 0.04 * normal(1, k, b, c));
        assert!(noise_share(&a, &n) > 0.9, "independent errors: {}", noise_share(&a, &n));
        assert_eq!(noise_share(&a, &n), MOST_NOISE_SHARE.min(noise_share(&a, &n)));
        // A motion sampled 30 times a cycle: none.
        let (a, n) = accelerations(30, 20, walk(30.0));
        assert!(noise_share(&a, &n) < 0.02, "a sampled walk: {}", noise_share(&a, &n));
        // Both, at a known share: a sine's second difference is its value times
        // -4 sin^2(w / 2) and independent errors' is six times their variance.
        let sigma = 0.005;
        let (a, n) = accelerations(30, 20, |k, b, c| walk(30.0)(k, b, c) + sigma * normal(2, k, b, c));
        let motion = (0.4f64.powi(2) / 2.0) * (4.0 * (std::f64::consts::PI / 30.0).sin().powi(2)).powi(2);
        let truth = 6.0 * sigma * sigma / (6.0 * sigma * sigma + motion);
        let share = noise_share(&a, &n);
        assert!((share - truth).abs() < 0.1, "share {share} against {truth}");
        assert!(truth > 0.3 && truth < 0.7, "the case is a mixture: {truth}");
        // The shift's row is not a turn and is left out.
        let (mut a, n) = accelerations(30, 20, walk(30.0));
        a.iter_mut().for_each(|rows| *rows.last_mut().unwrap() = [1.0, -1.0, 1.0]);
        assert!(noise_share(&a, &n) < 0.02);
        // Too few frames to tell: half; a motion without second differences: none.
        let (a, n) = accelerations(3, 20, |k, b, c| normal(3, k, b, c));
        assert_eq!(noise_share(&a, &n), 0.5);
        let (a, n) = accelerations(30, 20, |k, _, _| 0.1 * k as f64);
        assert_eq!(noise_share(&a, &n), 0.0);
    }

    #[test]
    fn the_bias_is_the_mean_length_of_a_bones_mean_error_over_the_frames() {
        // 4,000 bones' errors of 0.04 radians per axis drawn anew in each of 12 and 30 frames:
        // their means' lengths average to the bias within 3% (the average's own scatter is
        // about 0.7%).
        for frames in [12, 30] {
            let bones = 4000;
            let lengths: f64 = (0..bones)
                .map(|b| {
                    let mean = [0, 1, 2].map(|c| (0..frames).map(|k| 0.04 * normal(7, k, b, c)).sum::<f64>() / frames as f64);
                    mean.iter().map(|m| m * m).sum::<f64>().sqrt()
                })
                .sum();
            let found = lengths / bones as f64;
            assert!((found / bias(0.04, frames) - 1.0).abs() < 0.03, "{frames} frames: {found} against {}", bias(0.04, frames));
        }
        assert_eq!(bias(0.04, 0), 0.0);
    }

    #[test]
    fn the_noise_is_a_trackers_deviation_and_the_prior_holds_in_proportion_to_its_inverse_square() {
        let walk =
            |frames_a_cycle: f64| move |k: usize, b: usize, c: usize| 0.4 * (std::f64::consts::TAU * k as f64 / frames_a_cycle + b as f64 + c as f64).sin();
        let estimate = |(a, n): (Vec<Rows>, Vec<Option<(usize, usize)>>)| noise(&a, &n, noise_share(&a, &n));
        // A tracker's errors alone, and on a walk sampled 30 and 12 times a cycle: its deviation,
        // within the estimate's scatter over 30 frames; a walk sampled coarsely reads partly as
        // noise (its second differences correlate less), so over, not under.
        for sigma in [0.01, 0.04] {
            for (frames_a_cycle, within) in [(f64::INFINITY, (0.9, 1.1)), (30.0, (0.9, 1.1)), (12.0, (0.9, 1.35))] {
                let found = estimate(accelerations(30, 20, |k, b, c| {
                    let motion = if frames_a_cycle.is_finite() { walk(frames_a_cycle)(k, b, c) } else { 0.0 };
                    motion + sigma * normal(4, k, b, c)
                }));
                let (low, high) = within;
                assert!(found / sigma > low && found / sigma < high, "{sigma} on a walk {frames_a_cycle} frames a cycle: {found}");
            }
        }
        // A walk alone sampled finely: next to none, held the most.
        let found = estimate(accelerations(30, 20, walk(30.0)));
        assert!(found < 0.002, "a sampled walk: {found}");
        assert_eq!(prior_scale(found), MOST_PRIOR_SCALE);
        // The schedule's weight at the measured noise and beyond, four times it at half.
        assert_eq!(prior_scale(PRIOR_NOISE), 1.0);
        assert_eq!(prior_scale(3.0 * PRIOR_NOISE), 1.0);
        assert!((prior_scale(PRIOR_NOISE / 2.0) - 4.0).abs() < 1e-9);
        assert_eq!(prior_scale(0.0), MOST_PRIOR_SCALE);
        // Frames without both neighbours carry no second difference: none.
        assert_eq!(noise(&[vec![[1.0; 3]; 3]], &[None], 0.5), 0.0);
    }

    #[test]
    fn the_smoothness_weighs_the_noise_to_motion_ratio_and_never_less_than_the_schedule() {
        for share in [0.0, 0.25, 0.5, 0.85] {
            assert_eq!(smoothness_scale(share), 1.0, "a mostly smooth given motion at {share}");
        }
        // A ratio of 49 (98% noise) and 99 (the most).
        assert!((smoothness_scale(0.98) - SMOOTHNESS_PER_NOISE_RATIO * 49.0).abs() < 1e-9);
        assert!((smoothness_scale(MOST_NOISE_SHARE) - SMOOTHNESS_PER_NOISE_RATIO * 99.0).abs() < 1e-9);
        assert!(smoothness_scale(0.95) < smoothness_scale(0.98));
    }
}
