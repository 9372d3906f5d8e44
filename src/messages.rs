//! What a fit tells whoever runs it (typed messages the CLI turns into progress), and the
//! statistics of one training step.

use crate::shading::LightKind;
use std::collections::BTreeMap;

/// What the fit tells whoever runs it.
#[derive(Clone, Debug)]
pub enum TrainMessage {
    /// Images of the scene decoded so far.
    Loading {
        done: usize,
        total: usize,
    },
    Loaded {
        scene: String,
        training_images: usize,
        frames: usize,
        light: LightKind,
    },
    Started {
        first: usize,
        iterations: usize,
    },
    Step {
        iteration: usize,
        stats: StepStats,
    },
    Checkpoint {
        iteration: usize,
    },
    Evaluating {
        images: usize,
    },
    /// What a render of many views will cost, said before the first: the views, their size and
    /// the PNG bytes they will take at most (8-bit RGBA, uncompressed).
    Planned {
        views: usize,
        width: usize,
        height: usize,
    },
    /// `done` of `total` frames' fitted surfaces meshed and compared with the scene's
    /// ground-truth meshes (0 as the check starts, then after each frame).
    Meshed {
        done: usize,
        total: usize,
    },
    /// One image rendered, with its PSNR when there is a ground truth to score it against.
    Rendered {
        done: usize,
        total: usize,
        name: String,
        psnr: Option<f64>,
    },
    Done,
}

/// The losses of one step (unweighted) and the weighted total.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StepStats {
    pub total: f64,
    pub terms: BTreeMap<String, f64>,
    pub seconds: f64,
    /// Wall seconds per part of the step, in order (`PHASES`; the sun search only when it ran).
    /// burn's CPU backends run eagerly, so each part's tensor work is done within its span.
    #[serde(skip)]
    pub phases: Vec<(&'static str, f64)>,
    /// The process's CPU seconds per part of the step, as `phases` (the render's three parts
    /// share theirs in proportion to their times); empty where it cannot be read.
    #[serde(skip)]
    pub phase_cpu: Vec<(&'static str, f64)>,
    /// The process's CPU seconds over the whole step, where they can be read.
    #[serde(skip)]
    pub cpu_seconds: Option<f64>,
    /// The first training light after the step (`FittedLight::location`): a sun's unit
    /// direction or a point light's position (m); none when no light is fitted. Kept in
    /// `losses.csv`, so a run's path of the light survives `--resume` (`fit.json`: `light_path`).
    pub light: Option<[f64; 3]>,
    /// What the device's allocator held after the step (`backend::device_memory_bytes`): a
    /// GPU's, none on the CPU backends.
    #[serde(skip)]
    pub device_memory_bytes: Option<u64>,
}

/// The parts of a training step `StepStats::phases` times.
pub const PHASES: [&str; 10] = [
    "sun search",
    "batch sampling (CPU)",
    crate::render::RENDER_PARTS[0],
    crate::render::RENDER_PARTS[1],
    crate::render::RENDER_PARTS[2],
    "shading + shadows",
    "mask, grey, density and Gaussian losses",
    "Eikonal + curvature (SDF gradients)",
    "backward",
    "optimiser step",
];
