//! Each training camera's colour: a learned gain per channel (its exposure times its white
//! balance), normalised so that the gains' mean over the cameras is 1 in each channel (the light
//! and the albedo keep their meaning: renders and relights are of the mean camera). The body's
//! colour is multiplied by its camera's gain before it is composited over the camera's plate,
//! which is in that camera's colour already. Three numbers a camera: they live on the host, with
//! their own Adam moments, and go up as one small tensor a step.

use super::host_adam::CameraRows;
use crate::scene::Scene;
use burn::tensor::{Device, Int, Tensor, TensorData};

/// The cameras' log gains (unnormalised) and their optimiser's state.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraColours {
    log_gains: CameraRows,
}

impl CameraColours {
    /// For a scene whose training images come from two or more cameras; none otherwise (one
    /// camera has nothing to be told apart from).
    pub fn new(scene: &Scene) -> Option<Self> {
        CameraRows::of_training_cameras(scene).map(|log_gains| Self { log_gains })
    }

    /// The log gains as a leaf tensor `[cameras, 3]` whose gradient a step reads back.
    pub fn leaf(&self, device: &Device) -> Tensor<2> {
        let values: Vec<f32> = self.log_gains.values.iter().flatten().map(|&v| v as f32).collect();
        Tensor::from_data(TensorData::new(values, [self.log_gains.values.len(), 3]), device).require_grad()
    }

    /// Per ray, its camera's normalised gain `[rays, 3]` from the leaf, for rays of the given
    /// scene cameras.
    pub fn per_ray(&self, leaf: Tensor<2>, cameras: &[usize], device: &Device) -> Tensor<2> {
        let rows: Vec<i64> = cameras.iter().map(|&c| self.log_gains.row(c).unwrap_or(0) as i64).collect();
        let index = Tensor::<1, Int>::from_data(TensorData::new(rows, [cameras.len()]), device);
        normalised(leaf).select(0, index)
    }

    /// One Adam step of `rate` on the leaf's gradient (`[cameras, 3]`, row-major).
    pub fn step(&mut self, gradient: &[f32], rate: f64) {
        self.log_gains.step(gradient, rate);
    }

    /// Each camera (scene index) with its normalised gain per channel.
    pub fn gains(&self) -> Vec<(usize, [f64; 3])> {
        let logs = &self.log_gains.values;
        let n = logs.len() as f64;
        let mean: [f64; 3] = std::array::from_fn(|c| logs.iter().map(|g| g[c].exp()).sum::<f64>() / n);
        self.log_gains.cameras().iter().zip(logs).map(|(&camera, g)| (camera, std::array::from_fn(|c| g[c].exp() / mean[c]))).collect()
    }

    /// The state a checkpoint keeps.
    pub fn to_json(&self) -> serde_json::Value {
        self.log_gains.to_json("log_gains")
    }

    /// The state from a checkpoint's `to_json`, refused when it is not this scene's cameras.
    pub fn restore(&mut self, value: &serde_json::Value) -> Result<(), String> {
        self.log_gains.restore(value, "log_gains")
    }
}

/// `exp(log) / mean over cameras of exp(log)`, per channel.
fn normalised(log: Tensor<2>) -> Tensor<2> {
    let gains = log.exp();
    let mean = gains.clone().mean_dim(0);
    gains / mean
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The normalised gains' gradient against central differences of the same function on the
    /// host, and their mean of 1.
    #[test]
    fn normalised_gains_and_their_gradient() {
        let device = Device::flex().autodiff();
        let log = [[0.1, -0.2, 0.05], [-0.3, 0.25, 0.0], [0.2, 0.1, -0.15]];
        let weights = [[0.3, -1.2, 0.7], [0.5, 0.9, -0.4], [1.1, 0.2, 0.6]];
        let objective = |log: &[[f64; 3]; 3]| -> f64 {
            (0..3)
                .map(|c| {
                    let mean = log.iter().map(|r| r[c].exp()).sum::<f64>() / 3.0;
                    (0..3).map(|k| weights[k][c] * log[k][c].exp() / mean).sum::<f64>()
                })
                .sum()
        };
        let leaf = Tensor::<2>::from_data(TensorData::new(log.iter().flatten().map(|&v| v as f32).collect::<Vec<_>>(), [3, 3]), &device).require_grad();
        let w = Tensor::<2>::from_data(TensorData::new(weights.iter().flatten().map(|&v| v as f32).collect::<Vec<_>>(), [3, 3]), &device);
        let gains = normalised(leaf.clone());
        let means = crate::backend::host_values(gains.clone().mean_dim(0));
        assert!(means.iter().all(|m| (m - 1.0).abs() < 1e-6), "{means:?}");
        let grads = (gains * w).sum().backward();
        let gradient = crate::backend::host_values(leaf.grad(&grads).expect("a gradient"));
        let h = 1e-5;
        for k in 0..9 {
            let (mut up, mut down) = (log, log);
            up[k / 3][k % 3] += h;
            down[k / 3][k % 3] -= h;
            let expected = (objective(&up) - objective(&down)) / (2.0 * h);
            assert!((gradient[k] as f64 - expected).abs() < 1e-4, "{k}: {} vs {expected}", gradient[k]);
        }
    }

    /// Adam's first steps move each value by about the rate, against its gradient's sign; the
    /// state survives a checkpoint's round trip.
    #[test]
    fn adam_steps_and_the_checkpoint_round_trip() {
        let fresh = || CameraColours { log_gains: CameraRows::zeros(vec![Some(0), None, Some(1)], vec![0, 2]) };
        let mut colours = fresh();
        colours.step(&[1.0, -2.0, 0.0, 0.5, 0.0, -0.1], 0.01);
        let logs = &colours.log_gains.values;
        assert!((logs[0][0] + 0.01).abs() < 1e-6 && (logs[0][1] - 0.01).abs() < 1e-6 && logs[0][2] == 0.0);
        colours.step(&[f32::NAN; 6], 0.01);
        assert_eq!(colours.log_gains.steps(), 1, "a non-finite gradient is not taken");
        let mut back = fresh();
        back.restore(&colours.to_json()).unwrap();
        assert_eq!(back, colours);
        let gains = colours.gains();
        assert!((0..3).all(|c| ((gains[0].1[c] + gains[1].1[c]) / 2.0 - 1.0).abs() < 1e-12));
        assert!(back.restore(&serde_json::json!({"cameras": [0, 1]})).is_err());
    }
}
