//! The command line's arguments: every subcommand and option, with its help text.

use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "umbra", version, about = "Relightable neural avatars: Gaussian shadow casting, fitting, relighting")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Validate a scene and print a summary of it (exit 0 when valid).
    Inspect {
        /// A scene folder (or its scene.json).
        scene: PathBuf,
    },
    /// Generate a synthetic scene with exact ground truth.
    Synth {
        /// The folder to create.
        #[arg(long)]
        out: PathBuf,
        /// Replace `out` if it is a scene `umbra synth` wrote that holds nothing else (any
        /// other folder is refused, and so are the working folder and its parents).
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        options: crate::synth::SynthOptions,
    },
    /// Import a capture (nerfstudio cameras, a BVH, masks) into a new scene/1 scene.
    Import {
        /// The capture folder: a transforms.json, one .bvh, the images (or name them below).
        capture: PathBuf,
        /// The scene folder to create (new or empty).
        #[arg(long)]
        out: PathBuf,
        /// The capture's light, unknown but of this kind: `sun`, `point` or `uniform`.
        #[arg(long, value_enum)]
        light: crate::capture::CaptureLight,
        /// The capture's length unit (inferred from the skeleton's size when absent).
        #[arg(long, value_enum)]
        units: Option<crate::capture::Units>,
        /// The capture's up axis.
        #[arg(long, value_enum, default_value = "+y", allow_hyphen_values = true)]
        up: crate::capture::Up,
        /// The camera file (nerfstudio transforms.json), when not the capture's own.
        #[arg(long)]
        cameras: Option<PathBuf>,
        /// The motion: a BVH, or per-frame joint transforms as JSON (src/capture/joints.rs), when
        /// not the capture's only .bvh or its joints.json.
        #[arg(long)]
        motion: Option<PathBuf>,
        /// A folder of masks named after the images (<name>.png, or <camera>/<name>.png as the
        /// images are), for images whose camera file names no mask_path.
        #[arg(long)]
        masks: Option<PathBuf>,
        /// Downscale images by a whole factor until neither side exceeds this many pixels
        /// (at least 16).
        #[arg(long, value_name = "PIXELS", value_parser = crate::capture::parse_max_size)]
        max_size: Option<usize>,
    },
    /// Fit an avatar, its light and its albedo to a scene's training images.
    Fit {
        /// A scene folder (or its scene.json).
        scene: PathBuf,
        /// The run folder: fit.json, losses.csv/png, gaussians.json, checkpoint/, renders/.
        #[arg(long)]
        out: PathBuf,
        /// The loss schedule.
        #[arg(long, default_value = "schedules/default.toml")]
        schedule: PathBuf,
        /// Override the schedule's iteration count.
        #[arg(long, value_parser = parse_iterations)]
        iterations: Option<usize>,
        /// The seed of the fit's random draws (Gaussians, batches): 0 unless given; a resumed
        /// fit keeps its own.
        #[arg(long)]
        seed: Option<u64>,
        /// Continue from the run's last checkpoint.
        #[arg(long, conflicts_with = "force")]
        resume: bool,
        /// Replace an earlier run in the same folder.
        #[arg(long)]
        force: bool,
        /// With --resume: continue although the schedule or --iterations differs from the run's
        /// (the learning-rate decays and stages then follow the new one).
        #[arg(long, requires = "resume")]
        force_schedule: bool,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
        /// Skip rendering and scoring the test images at the end.
        #[arg(long)]
        no_eval: bool,
    },
    /// Render a fit. Without options: its test images rendered and scored (novel poses, novel
    /// views, relighting by the scene's other lights, albedo) into RUN/renders. With --motion:
    /// every frame of a clip (BVH or joints.json) driving the fitted bones. With --camera,
    /// --frame, --orbit, --size or --light: those views of the scene (into --out, default
    /// RUN/views).
    Render {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The scene to render (default: the one in RUN/fit.json), e.g. with more test images.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
        #[command(flatten)]
        views: RenderViews,
    },
    /// Score a fit: its test images (or training images) rendered and scored (PSNR over the
    /// whole image and the foreground, SSIM, per image and group), the light's error, and the
    /// fitted surface against the ground-truth meshes the scene's frames carry (accuracy,
    /// completeness, Chamfer distance, normal angle). Writes metrics.{json,md,csv} with the
    /// renders.
    Eval {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The scene to score on (default: the one in RUN/fit.json).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Which images: `test` (into RUN/renders) or `train` (into RUN/renders-train).
        #[arg(long, value_enum, default_value_t = EvalSplit::Test)]
        split: EvalSplit,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Render a fitted avatar under a new light: a sun, a point light, uniform light or an HDR
    /// environment map, in any of the scene's cameras and poses. Writes one PNG per view and a
    /// contact sheet.
    Relight {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// A light of the scene by name, a JSON file with one light in the scene format (e.g.
        /// {"type": "directional", "direction": [0, 1, 1], "irradiance": [1, 1, 1]}), or an
        /// equirectangular .exr environment map.
        #[arg(long)]
        light: String,
        /// Cameras to render, by index (default: all), e.g. --camera 0,3.
        #[arg(long, value_delimiter = ',')]
        camera: Option<Vec<usize>>,
        /// Frames to render, by position in the scene's frames (default: all).
        #[arg(long, value_delimiter = ',')]
        frame: Option<Vec<usize>>,
        /// Sky directions per pixel for environment and uniform lights (MIS of the map and the
        /// cosine lobe).
        #[arg(long, default_value_t = crate::scoring::SKY_SAMPLES)]
        samples: usize,
        /// The scene whose cameras and poses to use (default: the run's).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Output folder (default: RUN/relit/LIGHT).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
        /// Relight through a visibility basis of DIRECTIONS directions (default 1024) precomputed
        /// per view, instead of tracing shadow rays for the light: writes basis.md with the
        /// precompute and relight times and the first view's error against the direct estimator.
        #[arg(long, value_name = "DIRECTIONS", num_args = 0..=1, default_missing_value = "1024")]
        basis: Option<usize>,
        /// A turntable: N views on a circle around the body (at the scene's cameras' height and
        /// distance) in the first frame (or each --frame), one PNG per view and an animated PNG
        /// per frame (orbit_fFFFF.png).
        #[arg(long, value_name = "N", conflicts_with = "camera", value_parser = crate::relight::parse_orbit)]
        orbit: Option<usize>,
        /// Render at WIDTHxHEIGHT (e.g. 512x512, 1920x1080), the cameras' intrinsics scaled.
        #[arg(long, value_name = "WxH", value_parser = crate::relight::parse_size)]
        size: Option<(usize, usize)>,
        /// Turn the light by DEG degrees about the world's up axis (counter-clockwise seen from
        /// above): a sun's direction, a point light around the body, an environment map.
        #[arg(long, value_name = "DEG", default_value_t = 0.0, allow_negative_numbers = true)]
        rotate: f64,
        /// Multiply the light's strength (irradiance, intensity, radiance, ambient) by X.
        #[arg(long, value_name = "X", default_value_t = 1.0)]
        intensity: f64,
        #[command(flatten)]
        ground: GroundArgs,
    },
    /// Write RUN/report.html (self-contained: the recovered light against the scene's, stage
    /// times, losses, metrics, renders beside the truth, and a relighting panel: drag the sun or
    /// pick an environment) and RUN/report.md. `fit` writes it at the end too.
    Report {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The view of the relighting panel: a camera by index and a frame by position.
        #[arg(long, default_value_t = 0)]
        camera: usize,
        /// The frame of the relighting panel, by position in the scene's frames.
        #[arg(long, default_value_t = 0)]
        frame: usize,
        /// Directions of the panel's visibility basis.
        #[arg(long, default_value_t = crate::report::PANEL_DIRECTIONS)]
        directions: usize,
        /// The scene whose cameras and poses to use (default: the run's).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Export the fitted surface in one of the scene's poses as an OBJ mesh (marching tetrahedra
    /// on the fitted SDF at a cell of 1/160 of the body's size, vertex colours from the albedo,
    /// normals from the SDF's gradient).
    ExportMesh {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The pose: a frame by position in the scene's frames (with --out).
        #[arg(long, requires = "out", conflicts_with = "all_frames")]
        frame: Option<usize>,
        /// The OBJ file to write (with --frame).
        #[arg(long, requires = "frame")]
        out: Option<PathBuf>,
        /// Write one OBJ per frame of the scene into this folder (frame_PPPP.obj).
        #[arg(long)]
        all_frames: Option<PathBuf>,
        /// The scene whose poses to use (default: the run's).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Write the fitted avatar as a skinned, animated glTF 2.0 binary (.glb): the surface in
    /// the scene's first frame, a joint per bone with the field's skinning weights, vertex
    /// colours from the albedo, animated by the scene's frames or --motion.
    ExportAvatar {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The .glb file to write.
        #[arg(long)]
        out: PathBuf,
        /// A clip (BVH or joints.json) to animate with instead of the scene's frames.
        #[arg(long, value_name = "CLIP")]
        motion: Option<PathBuf>,
        /// The clip's length unit (inferred from its skeleton's size when absent).
        #[arg(long, value_enum, requires = "motion")]
        units: Option<crate::capture::Units>,
        /// The scene whose poses to use (default: the run's).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Write the fitted shadow Gaussians posed in one frame as a 3D Gaussian splatting PLY
    /// (x y z, scale_0..2 as logs, rot_0..3, opacity as a logit, f_dc_0..2), for splat viewers.
    ExportGaussians {
        /// The run folder `umbra fit` wrote.
        run: PathBuf,
        /// The pose: a frame by position in the scene's frames.
        #[arg(long, default_value_t = 0)]
        frame: usize,
        /// The PLY file to write.
        #[arg(long)]
        out: PathBuf,
        /// The scene whose poses to use (default: the run's).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Fit one scene with several schedules and compare the runs in one table: light error,
    /// PSNR of novel poses, views, relighting and albedo, time and final loss. Writes
    /// OUT/<schedule>/ per run and OUT/ablation.{csv,md,png}.
    Ablate {
        /// A scene folder (or its scene.json) to fit with every schedule.
        scene: PathBuf,
        /// A schedule to compare (at least two), e.g. --schedule schedules/default.toml.
        #[arg(long = "schedule", required = true)]
        schedules: Vec<PathBuf>,
        /// The folder of the runs (one per schedule, named by its file) and the tables.
        #[arg(long)]
        out: PathBuf,
        /// Override every schedule's iteration count (a quick comparison).
        #[arg(long, value_parser = parse_iterations)]
        iterations: Option<usize>,
        /// The seed of the fits' random draws.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Replace earlier runs in OUT.
        #[arg(long)]
        force: bool,
        /// The tensor backend: `flex` (the default, fast on CPU), `ndarray`, or `wgpu` (a GPU; built with `--features gpu`).
        #[arg(long, value_enum, default_value_t = crate::backend::Backend::Flex)]
        backend: crate::backend::Backend,
    },
    /// Run a benchmark and write its table (Markdown, CSV) and plot (PNG).
    Bench {
        /// Which benchmark.
        #[arg(value_enum)]
        which: BenchKind,
        /// Where the tables and plots go.
        #[arg(long, default_value = "runs/bench")]
        out: PathBuf,
        /// Fewer sizes and shorter timings (a smoke run).
        #[arg(long)]
        quick: bool,
        /// A training scene whose whole training steps `gradients` also times, or that `fit`
        /// fits (default: datasets-synthetic/human-sun for `gradients`,
        /// datasets-synthetic/human-sun-128 for `fit`).
        #[arg(long)]
        scene: Option<PathBuf>,
        /// `fit`: the field kinds to compare.
        #[arg(long, value_enum, value_delimiter = ',', default_value = "mlp,grid")]
        kinds: Vec<crate::schedule::FieldKind>,
        /// `fit`, `steps`: the schedule (its `[field]` is replaced by each variant's).
        #[arg(long, default_value = "schedules/default.toml")]
        schedule: PathBuf,
        /// `fit`: scoring points per fit.
        #[arg(long, default_value_t = 6)]
        evaluations: usize,
        /// `fit`: override the schedule's iteration count.
        #[arg(long, value_parser = parse_iterations)]
        iterations: Option<usize>,
        /// The seed of the fits' random draws.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// `scenes`: fit every scene once per seed (instead of `--seed`) and add a table of each
        /// scene's mean and standard deviation over them: one seed's figure of a fit varies by
        /// about half a dB, so a difference between scenes is read off their means.
        #[arg(long, value_delimiter = ',')]
        seeds: Vec<u64>,
        /// `memory`: training images per size.
        #[arg(long, default_value_t = 240)]
        images: usize,
        /// `fit`: then fit the grid again for as many iterations as fill the MLP's training
        /// time, so the two fields are also compared at equal cost.
        #[arg(long)]
        equal_time: bool,
        /// `scenes`: the scenes to fit (default: every `datasets-synthetic/*` scene, then
        /// `../shared/examples/quadruped-tiny`).
        #[arg(long, value_delimiter = ',')]
        scenes: Vec<PathBuf>,
        /// `render`: the run folder of a fit whose views to time; `steps`, `breakdown`: of a fit
        /// whose fitted field's steps to time as well (`steps`: with and without culling).
        #[arg(long)]
        run: Option<PathBuf>,
        /// `memory`: the tensor backend its fits run on (default flex; `wgpu`, built with
        /// `--features gpu`, also reports the device's memory).
        #[arg(long, value_enum)]
        backend: Option<crate::backend::Backend>,
    },
}

/// `--iterations`: a whole number within the bounds a schedule's `iterations` has.
fn parse_iterations(text: &str) -> Result<usize, String> {
    let n: usize = text.parse().map_err(|_| format!("{text:?} is not a whole number from 1 to {}", crate::schedule::MAX_COUNT))?;
    crate::schedule::check_iterations(n).map_err(|_| format!("{n} is not from 1 to {} (the schedule's own limit)", crate::schedule::MAX_COUNT))
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EvalSplit {
    Test,
    Train,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum BenchKind {
    /// Gaussian shadow casting: throughput, culling, closed form vs ray marching.
    Shadows,
    /// SDF gradients (normals, Eikonal): forward-mode tangents vs central differences.
    Gradients,
    /// Training-step cost per field kind, with and without the work a step need not do.
    Steps,
    /// Time against error: a scene fitted once per field kind, novel-pose foreground PSNR,
    /// SSIM, albedo PSNR and light error along the way.
    Fit,
    /// Where the time goes: milliseconds per part of a training step and of a render.
    Breakdown,
    /// The CPU against the GPU (a build with `--features gpu`): milliseconds per training step
    /// in two stages and the seconds of a short fit, on flex and on the wgpu device.
    Device,
    /// Sky light: per-pixel MIS against the previous shared sampler and the research code's
    /// estimator, error against a 4096-sample reference at 16, 64 and 256 samples.
    Environment,
    /// Every shipped scene fitted once: light error, foreground PSNR, SSIM and wall time in one
    /// table (`scenes.md`, `scenes.csv`; each fit in `OUT/NAME`).
    Scenes,
    /// Seconds per view of a fitted run (--run RUN) in its fitted light, a sun, a point light
    /// and a sky at 64 samples per pixel, with every thread and with one; and views one after
    /// another against several at once.
    Render,
    /// Peak memory and wall time of a short fit at capture sizes: a scene's training images
    /// upscaled to 128 and 1024 pixels (--quick: 512) and repeated to --images, each fitted in
    /// a process of its own (`memory.md`, `memory.csv`).
    Memory,
}

/// The views `umbra render` draws instead of the scored test images.
#[derive(clap::Args, Debug)]
pub struct RenderViews {
    /// A clip to drive the fitted bones: a BVH, or per-frame joint transforms as JSON. Joints
    /// are matched to bones by name; one PNG per clip frame (fNNNN.png) and animation.png.
    #[arg(long, value_name = "CLIP")]
    pub motion: Option<PathBuf>,
    /// The clip's length unit (inferred from its skeleton's size when absent).
    #[arg(long, value_enum, requires = "motion")]
    pub units: Option<crate::capture::Units>,
    /// Cameras to render, by index (default: all; with --motion one, default 0).
    #[arg(long, value_delimiter = ',')]
    pub camera: Option<Vec<usize>>,
    /// Frames to render, by position in the scene's frames (default: all).
    #[arg(long, value_delimiter = ',')]
    pub frame: Option<Vec<usize>>,
    /// A turntable of N views around the body (with --motion: a camera going once around every
    /// N frames).
    #[arg(long, value_name = "N", conflicts_with = "camera", value_parser = crate::relight::parse_orbit)]
    pub orbit: Option<usize>,
    /// Render at WIDTHxHEIGHT (e.g. 512x512, 1920x1080), the cameras' intrinsics scaled.
    #[arg(long, value_name = "WxH", value_parser = crate::relight::parse_size)]
    pub size: Option<(usize, usize)>,
    /// A stated light instead of the fitted one: a light of the scene, a light .json or an
    /// environment .exr.
    #[arg(long)]
    pub light: Option<String>,
    /// Sky directions per pixel for environment and uniform lights.
    #[arg(long, default_value_t = crate::scoring::SKY_SAMPLES)]
    pub samples: usize,
    /// The output folder (default: RUN/views; required with --motion).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub ground: GroundArgs,
}

/// A ground under the avatar that receives its shadow.
#[derive(clap::Args, Debug)]
pub struct GroundArgs {
    /// Add a ground under the avatar that receives its Gaussian shadow, at the lowest point of
    /// the posed body in each frame; writes RGBA PNGs (alpha: the body's coverage plus the
    /// shadow's opacity) to composite over a plate.
    #[arg(long)]
    pub ground: bool,
    /// The ground's height (m, along the world's +Y) instead of the body's lowest point.
    #[arg(long, value_name = "H", allow_negative_numbers = true)]
    pub ground_height: Option<f64>,
}

impl GroundArgs {
    pub fn options(&self) -> Option<crate::relight::ground::GroundOptions> {
        (self.ground || self.ground_height.is_some()).then_some(crate::relight::ground::GroundOptions { height: self.ground_height })
    }
}
