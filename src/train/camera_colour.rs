//! Each training camera's colour: a learned gain per channel (its exposure times its white
//! balance), normalised so that the gains' mean over the cameras is 1 in each channel (the light
//! and the albedo keep their meaning: renders and relights are of the mean camera). The body's
//! colour is multiplied by its camera's gain before it is composited over the camera's plate,
//! which is in that camera's colour already. Three numbers a camera: they live on the host, with
//! their own Adam moments, and go up as one small tensor a step.

use crate::scene::{Scene, Split};
use burn::tensor::{Device, Int, Tensor, TensorData};

/// The cameras' log gains and their optimiser's state.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraColours {
    /// Per scene camera, its row (none for a camera without training images).
    rows: Vec<Option<usize>>,
    /// Per row: the camera's index in the scene, and its log gain per channel (unnormalised).
    cameras: Vec<usize>,
    log_gains: Vec<[f64; 3]>,
    first: Vec<[f64; 3]>,
    second: Vec<[f64; 3]>,
    steps: u64,
}

impl CameraColours {
    /// For a scene whose training images come from two or more cameras; none otherwise (one
    /// camera has nothing to be told apart from).
    pub fn new(scene: &Scene) -> Option<Self> {
        let mut rows = vec![None; scene.cameras.len()];
        let mut cameras = Vec::new();
        for view in scene.views.iter().filter(|v| v.split == Split::Train) {
            if rows[view.camera].is_none() {
                rows[view.camera] = Some(cameras.len());
                cameras.push(view.camera);
            }
        }
        let n = cameras.len();
        (n >= 2).then(|| Self { rows, cameras, log_gains: vec![[0.0; 3]; n], first: vec![[0.0; 3]; n], second: vec![[0.0; 3]; n], steps: 0 })
    }

    /// The log gains as a leaf tensor `[cameras, 3]` whose gradient a step reads back.
    pub fn leaf(&self, device: &Device) -> Tensor<2> {
        let values: Vec<f32> = self.log_gains.iter().flatten().map(|&v| v as f32).collect();
        Tensor::from_data(TensorData::new(values, [self.cameras.len(), 3]), device).require_grad()
    }

    /// Per ray, its camera's normalised gain `[rays, 3]` from the leaf, for rays of the given
    /// scene cameras.
    pub fn per_ray(&self, leaf: Tensor<2>, cameras: &[usize], device: &Device) -> Tensor<2> {
        let rows: Vec<i64> = cameras.iter().map(|&c| self.rows.get(c).copied().flatten().unwrap_or(0) as i64).collect();
        let index = Tensor::<1, Int>::from_data(TensorData::new(rows, [cameras.len()]), device);
        normalised(leaf).select(0, index)
    }

    /// One Adam step of `rate` on the leaf's gradient (`[cameras, 3]`, row-major).
    pub fn step(&mut self, gradient: &[f32], rate: f64) {
        if gradient.len() != 3 * self.cameras.len() || gradient.iter().any(|g| !g.is_finite()) {
            return;
        }
        self.steps += 1;
        let rows: Vec<[f64; 3]> = gradient.chunks(3).map(|g| [g[0] as f64, g[1] as f64, g[2] as f64]).collect();
        super::host_adam::step(&mut self.log_gains, &mut self.first, &mut self.second, &rows, self.steps, rate);
    }

    /// Each camera (scene index) with its normalised gain per channel.
    pub fn gains(&self) -> Vec<(usize, [f64; 3])> {
        let n = self.cameras.len() as f64;
        let mean: [f64; 3] = std::array::from_fn(|c| self.log_gains.iter().map(|g| g[c].exp()).sum::<f64>() / n);
        self.cameras.iter().zip(&self.log_gains).map(|(&camera, g)| (camera, std::array::from_fn(|c| g[c].exp() / mean[c]))).collect()
    }

    /// The state a checkpoint keeps.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({"cameras": self.cameras, "log_gains": self.log_gains, "first": self.first, "second": self.second, "steps": self.steps})
    }

    /// The state from a checkpoint's `to_json`, refused when it is not this scene's cameras.
    pub fn restore(&mut self, value: &serde_json::Value) -> Result<(), String> {
        let cameras: Vec<usize> = serde_json::from_value(value["cameras"].clone()).map_err(|e| format!("cameras: {e}"))?;
        if cameras != self.cameras {
            return Err(format!("cameras {cameras:?}, the scene's training cameras are {:?}", self.cameras));
        }
        let rows = |key: &str| -> Result<Vec<[f64; 3]>, String> {
            let rows: Vec<[f64; 3]> = serde_json::from_value(value[key].clone()).map_err(|e| format!("{key}: {e}"))?;
            match rows.len() == cameras.len() && rows.iter().flatten().all(|v| v.is_finite()) {
                true => Ok(rows),
                false => Err(format!("{key}: one finite [r, g, b] per camera")),
            }
        };
        self.log_gains = rows("log_gains")?;
        self.first = rows("first")?;
        self.second = rows("second")?;
        self.steps = value["steps"].as_u64().ok_or("steps: missing")?;
        Ok(())
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
        let mut colours = CameraColours {
            rows: vec![Some(0), None, Some(1)],
            cameras: vec![0, 2],
            log_gains: vec![[0.0; 3]; 2],
            first: vec![[0.0; 3]; 2],
            second: vec![[0.0; 3]; 2],
            steps: 0,
        };
        colours.step(&[1.0, -2.0, 0.0, 0.5, 0.0, -0.1], 0.01);
        assert!((colours.log_gains[0][0] + 0.01).abs() < 1e-6 && (colours.log_gains[0][1] - 0.01).abs() < 1e-6 && colours.log_gains[0][2] == 0.0);
        colours.step(&[f32::NAN; 6], 0.01);
        assert_eq!(colours.steps, 1, "a non-finite gradient is not taken");
        let mut back = CameraColours { log_gains: vec![[0.0; 3]; 2], first: vec![[0.0; 3]; 2], second: vec![[0.0; 3]; 2], steps: 0, ..colours.clone() };
        back.restore(&colours.to_json()).unwrap();
        assert_eq!(back, colours);
        let gains = colours.gains();
        assert!((0..3).all(|c| ((gains[0].1[c] + gains[1].1[c]) / 2.0 - 1.0).abs() < 1e-12));
        assert!(back.restore(&serde_json::json!({"cameras": [0, 1]})).is_err());
    }
}
