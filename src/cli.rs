//! The command line: argument parsing, progress bars and the report each subcommand prints.
//! Everything it does is a library call, so tests and examples use the same entry points.

use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};

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
        /// A folder of masks named after the images (<name>.png), for images whose camera file
        /// names no mask_path.
        #[arg(long)]
        masks: Option<PathBuf>,
        /// Downscale images by a whole factor until neither side exceeds this many pixels.
        #[arg(long)]
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        #[arg(long, value_name = "N", conflicts_with = "camera")]
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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
        /// The tensor backend: `flex` (the default, fast on CPU) or `ndarray`.
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

/// Runs the CLI and returns the process exit code.
fn print_avatar(out: &Path, e: &crate::export::AvatarExported) {
    println!("wrote {}: {} vertices, {} triangles, {} joints, {} animation frames", out.display(), e.vertices, e.triangles, e.bones, e.frames);
    if let Some((frame, s)) = e.skin_check {
        println!(
            "skinning check in frame {frame}: the skinned mesh lies {:.1} mm (mean) from the surface meshed in that frame, which lies {:.1} mm from it",
            s.accuracy * 1e3,
            s.completeness * 1e3
        );
    }
}

/// The views `umbra render` draws instead of the scored test images.
#[derive(clap::Args, Debug)]
pub struct RenderViews {
    /// A clip to drive the fitted bones: a BVH, or per-frame joint transforms as JSON. Joints
    /// are matched to bones by name; one PNG per clip frame (fNNNN.png) and animation.png.
    #[arg(long, value_name = "CLIP")]
    motion: Option<PathBuf>,
    /// The clip's length unit (inferred from its skeleton's size when absent).
    #[arg(long, value_enum, requires = "motion")]
    units: Option<crate::capture::Units>,
    /// Cameras to render, by index (default: all; with --motion one, default 0).
    #[arg(long, value_delimiter = ',')]
    camera: Option<Vec<usize>>,
    /// Frames to render, by position in the scene's frames (default: all).
    #[arg(long, value_delimiter = ',')]
    frame: Option<Vec<usize>>,
    /// A turntable of N views around the body (with --motion: a camera going once around every
    /// N frames).
    #[arg(long, value_name = "N", conflicts_with = "camera")]
    orbit: Option<usize>,
    /// Render at WIDTHxHEIGHT (e.g. 512x512, 1920x1080), the cameras' intrinsics scaled.
    #[arg(long, value_name = "WxH", value_parser = crate::relight::parse_size)]
    size: Option<(usize, usize)>,
    /// A stated light instead of the fitted one: a light of the scene, a light .json or an
    /// environment .exr.
    #[arg(long)]
    light: Option<String>,
    /// Sky directions per pixel for environment and uniform lights.
    #[arg(long, default_value_t = crate::scoring::SKY_SAMPLES)]
    samples: usize,
    /// The output folder (default: RUN/views; required with --motion).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    ground: GroundArgs,
}

/// A ground under the avatar that receives its shadow.
#[derive(clap::Args, Debug)]
pub struct GroundArgs {
    /// Add a ground under the avatar that receives its Gaussian shadow, at the lowest point of
    /// the posed body in each frame; writes RGBA PNGs (alpha: the body's coverage plus the
    /// shadow's opacity) to composite over a plate.
    #[arg(long)]
    ground: bool,
    /// The ground's height (m, along the world's +Y) instead of the body's lowest point.
    #[arg(long, value_name = "H", allow_negative_numbers = true)]
    ground_height: Option<f64>,
}

impl GroundArgs {
    fn options(&self) -> Option<crate::relight::ground::GroundOptions> {
        (self.ground || self.ground_height.is_some()).then_some(crate::relight::ground::GroundOptions { height: self.ground_height })
    }
}

pub fn main() -> i32 {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Inspect { scene } => inspect(&scene),
        Command::Synth { out, force, options } => synth(&out, force, &options),
        Command::Import { capture, out, light, units, up, cameras, motion, masks, max_size } => {
            import(&crate::capture::ImportOptions { capture, out, light, units, up, cameras, motion, masks, max_size })
        }
        Command::Fit { scene, out, schedule, iterations, seed, resume, force, force_schedule, backend, no_eval } => {
            let seed = seed.or_else(|| resume.then(|| crate::fit::recorded_seed(&out)).flatten()).unwrap_or(0);
            fit(&crate::fit::FitOptions { scene, out, schedule, iterations, seed, resume, force, force_schedule, backend, evaluate: !no_eval })
        }
        Command::Render { run, scene, backend, views } => render(run, scene, backend, views),
        Command::Eval { run, scene, split, backend } => eval(&run, scene.as_deref(), split, backend),
        Command::Ablate { scene, schedules, out, iterations, seed, force, backend } => {
            ablate(&crate::ablate::AblateOptions { scene, schedules, out, iterations, seed, force, backend })
        }
        Command::Relight { run, light, camera, frame, samples, scene, out, backend, basis, orbit, size, rotate, intensity, ground } => {
            let light = Some(light);
            let ground = ground.options();
            relight(&crate::relight::RelightOptions {
                run,
                scene,
                light,
                cameras: camera,
                frames: frame,
                samples,
                out,
                backend,
                basis,
                orbit,
                size,
                rotate,
                intensity,
                ground,
            })
        }
        Command::ExportMesh { run, frame, out, all_frames, scene, backend } => export_mesh(run, frame, out, all_frames, scene, backend),
        Command::ExportAvatar { run, out, motion, units, scene, backend } => {
            let options = crate::export::AvatarOptions { run, scene, motion, units, out: out.clone(), backend };
            crate::export::export_avatar(&options).map(|e| print_avatar(&out, &e)).map_err(|e| e.to_string())
        }
        Command::ExportGaussians { run, frame, out, scene, backend } => crate::export::export_gaussians(&run, scene.as_deref(), frame, &out, backend)
            .map(|count| println!("wrote {count} Gaussians posed in frame {frame} to {}", out.display()))
            .map_err(|e| e.to_string()),
        Command::Report { run, camera, frame, directions, scene, backend } => {
            report(&crate::report::ReportOptions { run, scene, camera, frame, directions, backend })
        }
        Command::Bench { which: BenchKind::Render, out, quick, run, .. } => match run {
            Some(run) => crate::bench::render(&run, &out, quick).map(|table| print!("{table}")).map_err(|e| e.to_string()),
            None => Err("bench render needs --run RUN (the folder of a fit)".into()),
        },
        Command::Bench { which: BenchKind::Environment, out, quick, .. } => crate::bench::environment(&out, quick).map(|table| print!("{table}")),
        Command::Bench { which: BenchKind::Shadows, out, quick, .. } => crate::bench::shadows(&out, quick).map(|table| print!("{table}")),
        Command::Bench { which: BenchKind::Fit, out, scene, kinds, schedule, evaluations, iterations, seed, equal_time, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun-128"));
            let options = crate::bench::FitBenchOptions { scene, schedule, out, kinds, evaluations, iterations, seed, equal_time };
            crate::bench::fit_curves(&options, |line| eprintln!("{line}")).map(|table| print!("{table}")).map_err(|e| e.to_string())
        }
        Command::Bench { which: BenchKind::Steps, out, quick, scene, schedule, run, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun-128"));
            crate::bench::steps(&scene, &schedule, &out, quick, run.as_deref()).map(|table| print!("{table}")).map_err(|e| e.to_string())
        }
        Command::Bench { which: BenchKind::Breakdown, out, quick, scene, schedule, run, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun-128"));
            crate::bench::breakdown(&scene, &schedule, &out, quick, run.as_deref()).map(|table| print!("{table}")).map_err(|e| e.to_string())
        }
        Command::Bench { which: BenchKind::Scenes, out, scenes, schedule, iterations, seed, seeds, .. } => {
            let seeds = if seeds.is_empty() { vec![seed] } else { seeds };
            let options = crate::bench::ScenesBenchOptions { scenes, schedule, iterations, seeds, out };
            crate::bench::scenes(&options, |line| eprintln!("{line}")).map(|table| print!("{table}")).map_err(|e| e.to_string())
        }
        Command::Bench { which: BenchKind::Memory, out, quick, scene, iterations, images, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun"));
            let options =
                crate::bench::MemoryBenchOptions { scene, out, images, sizes: (128, if quick { 512 } else { 1024 }), iterations: iterations.unwrap_or(30) };
            crate::bench::memory(&options, |line| eprintln!("{line}")).map(|table| print!("{table}"))
        }
        Command::Bench { which: BenchKind::Gradients, out, quick, scene, .. } => {
            let scene = scene.or_else(|| Some(PathBuf::from(crate::bench::DEFAULT_SCENE)).filter(|p| p.join("scene.json").exists()));
            crate::bench::gradients(&out, quick, scene.as_deref()).map(|table| print!("{table}"))
        }
    };
    match result {
        Ok(()) => 0,
        Err(message) => {
            eprintln!("error: {message}");
            1
        }
    }
}

/// Progress with an ETA on standard error (a bar, or plain lines in a log).
pub fn progress_bar(total: u64, what: &str) -> crate::progress::Progress {
    crate::progress::Progress::new(total, what)
}

fn inspect(path: &Path) -> Result<(), String> {
    let scene = crate::scene::Scene::load(path).map_err(|e| e.to_string())?;
    print!("{}", crate::scene::summary(&scene));
    Ok(())
}

fn synth(out: &Path, force: bool, options: &crate::synth::SynthOptions) -> Result<(), String> {
    let bar = progress_bar(0, "rendering");
    let report = crate::synth::generate(options, out, force, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    println!("wrote {} ({} images, {:.2} MB)", out.display(), report.images, report.bytes as f64 / 1e6);
    Ok(())
}

fn import(options: &crate::capture::ImportOptions) -> Result<(), String> {
    let bar = progress_bar(0, "importing images");
    let report = crate::capture::import(options, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    println!("wrote {}: {} images, {} cameras, {} frames", options.out.display(), report.images, report.cameras, report.frames);
    for line in &report.assumed {
        println!("  {line}");
    }
    println!("check it with `umbra inspect {}` before fitting", options.out.display());
    Ok(())
}

fn fit(options: &crate::fit::FitOptions) -> Result<(), String> {
    use crate::messages::TrainMessage;
    let bar = progress_bar(0, "fitting");
    let report = crate::fit::fit(options, |message| match message {
        TrainMessage::Loaded { scene, training_images, frames, light } => {
            let light = match light {
                crate::shading::LightKind::Directional => "a sun",
                crate::shading::LightKind::Point => "a point light",
                crate::shading::LightKind::Uniform => "uniform light",
            };
            bar.println(format!("scene {scene}: {training_images} training images, {frames} frames, lit by {light}"));
        }
        TrainMessage::Started { first, iterations } => {
            bar.set_length(iterations as u64);
            bar.set_position(first as u64);
            bar.reset_eta();
        }
        TrainMessage::Step { iteration, stats } => {
            bar.set_position(iteration as u64 + 1);
            if iteration % 10 == 0 {
                let terms: Vec<String> = stats.terms.iter().map(|(k, v)| format!("{k} {v:.4}")).collect();
                bar.set_message(format!("loss {:.4} ({})", stats.total, terms.join(", ")));
            }
        }
        TrainMessage::Checkpoint { .. } => {}
        TrainMessage::Evaluating { images } => {
            bar.set_what("evaluating");
            bar.set_message(String::new());
            bar.set_length(images as u64);
            bar.set_position(0);
            bar.reset_eta();
        }
        TrainMessage::Rendered { done, name, psnr, .. } => {
            bar.set_position(done as u64);
            bar.set_message(psnr.map(|p| format!("{name}: {p:.2} dB")).unwrap_or(name));
        }
        TrainMessage::Meshed { done, total } => bar.println(format!("meshing frame {}/{total} against the scene's mesh", done + 1)),
        TrainMessage::Done => bar.finish_and_clear(),
    })
    .map_err(|e| e.to_string())?;
    println!("wrote {}", options.out.join("fit.json").display());
    if let Some(why) = report["evaluation_skipped"].as_str() {
        println!("not evaluated: {why}");
    } else {
        // The report needs the renders beside the truth that the evaluation writes.
        let report = crate::report::ReportOptions {
            run: options.out.clone(),
            scene: None,
            camera: 0,
            frame: 0,
            directions: crate::report::PANEL_DIRECTIONS,
            backend: options.backend,
        };
        let (html, _) = crate::report::write_report(&report).map_err(|e| format!("the fit is complete (fit.json written), but its report failed: {e}"))?;
        println!("wrote {}", html.display());
    }
    println!("light: {}", describe_light(&report["light"]));
    if let Some(search) = report["sun_search"].as_object() {
        let start = search
            .get("error_against_scene")
            .and_then(|e| e["direction_degrees"].as_f64())
            .map(|e| format!(", {e:.2} degrees from the scene's sun"))
            .unwrap_or_default();
        println!(
            "sun search: {} directions scored on {} surface samples; the light started from the best{start}",
            search.get("candidates").and_then(|c| c.as_u64()).unwrap_or(0),
            search.get("samples").and_then(|c| c.as_u64()).unwrap_or(0)
        );
    }
    if let Some(e) = report["light_error_against_scene"]["direction_degrees"].as_f64() {
        println!("light direction error against the scene's sun: {e:.2} degrees");
    }
    print_evaluation(&report["evaluation"]);
    println!("wall time: {:.1} s", report["wall_seconds"].as_f64().unwrap_or(0.0));
    Ok(())
}

/// Follows a command that renders or writes images one by one on `bar`.
fn image_progress(bar: &crate::progress::Progress) -> impl FnMut(crate::messages::TrainMessage) + '_ {
    use crate::messages::TrainMessage;
    move |message| match message {
        TrainMessage::Evaluating { images } => bar.set_length(images as u64),
        TrainMessage::Rendered { done, name, psnr, .. } => {
            bar.set_position(done as u64);
            bar.set_message(psnr.map(|p| format!("{name}: {p:.2} dB")).unwrap_or(name));
        }
        TrainMessage::Meshed { done, total } => bar.println(format!("meshing frame {}/{total} against the scene's mesh", done + 1)),
        _ => {}
    }
}

fn render(run: PathBuf, scene: Option<PathBuf>, backend: crate::backend::Backend, views: RenderViews) -> Result<(), String> {
    let RenderViews { motion, units, camera, frame, orbit, size, light, samples, out, ground } = views;
    let ground = ground.options();
    if let Some(motion) = motion {
        let camera = match camera.as_deref() {
            None => None,
            Some([c]) => Some(*c),
            Some(_) => return Err("--motion renders through one --camera".into()),
        };
        if frame.is_some() {
            return Err("--motion renders every frame of the clip: --frame does not apply".into());
        }
        let out = out.ok_or("--motion needs --out DIR: the folder for fNNNN.png and animation.png")?;
        let options = crate::animate::AnimateOptions { run, scene, motion, units, camera, orbit, light, size, samples, out, backend, ground };
        let bar = progress_bar(0, "rendering the clip");
        let animated = crate::animate::animate_run(&options, image_progress(&bar)).map_err(|e| e.to_string())?;
        bar.finish_and_clear();
        println!("{}", crate::animate::describe(&animated));
        return Ok(());
    }
    if camera.is_some() || frame.is_some() || orbit.is_some() || size.is_some() || light.is_some() || out.is_some() || ground.is_some() {
        let out = Some(out.unwrap_or_else(|| run.join("views")));
        let rotate = 0.0;
        let options = crate::relight::RelightOptions {
            run,
            scene,
            light,
            cameras: camera,
            frames: frame,
            samples,
            out,
            backend,
            basis: None,
            orbit,
            size,
            rotate,
            intensity: 1.0,
            ground,
        };
        return relight(&options);
    }
    if units.is_some() {
        return Err("--units is the unit of a --motion clip".into());
    }
    let bar = progress_bar(0, "rendering");
    let evaluation = crate::scoring::render_run(&run, scene.as_deref(), backend, image_progress(&bar)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    print_evaluation(&evaluation);
    println!("wrote {}", run.join("renders").display());
    Ok(())
}

fn eval(run: &Path, scene: Option<&Path>, split: EvalSplit, backend: crate::backend::Backend) -> Result<(), String> {
    let split = match split {
        EvalSplit::Test => crate::scene::Split::Test,
        EvalSplit::Train => crate::scene::Split::Train,
    };
    let bar = progress_bar(0, "scoring");
    let (dir, evaluation) = crate::scoring::eval_run(run, scene, split, backend, image_progress(&bar)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    for group in evaluation["groups"].as_array().into_iter().flatten() {
        let f = |k: &str| group[k].as_f64().unwrap_or(f64::NAN);
        let regions = crate::metrics::ErrorRegions::from_json(&group["error_share"])
            .map(|e| e.percentages())
            .map_or(String::new(), |[o, s, i]| format!("; error {o} outside the mask, {s} along the silhouette, {i} inside"));
        println!(
            "{}: PSNR {:.2} dB, foreground {:.2} dB, SSIM {:.4}{regions}",
            group["group"].as_str().unwrap_or("?"),
            f("psnr"),
            f("foreground_psnr"),
            f("ssim")
        );
    }
    if let Some(d) = evaluation["light_error"]["direction_degrees"].as_f64() {
        println!("light direction error: {d:.2} degrees");
    }
    if let Some(m) = evaluation["light_error"]["position_metres"].as_f64() {
        println!("light position error: {m:.3} m");
    }
    for frame in evaluation["geometry"].as_array().into_iter().flatten() {
        let mm = |k: &str| frame[k].as_f64().unwrap_or(f64::NAN) * 1e3;
        println!(
            "geometry, frame {}: accuracy {:.2} mm, completeness {:.2} mm, Chamfer {:.2} mm, normal angle {:.2} degrees, {:.1}% within 2 cm, {}",
            frame["frame"],
            mm("accuracy"),
            mm("completeness"),
            mm("chamfer"),
            frame["normal_angle"].as_f64().unwrap_or(f64::NAN),
            frame["within_2cm"].as_f64().unwrap_or(f64::NAN) * 100.0,
            if frame["closed"].as_bool() == Some(true) { "closed" } else { "not closed" }
        );
    }
    println!("wrote {} (metrics.json, metrics.md, metrics.csv, compare.png)", dir.display());
    Ok(())
}

fn ablate(options: &crate::ablate::AblateOptions) -> Result<(), String> {
    use crate::messages::TrainMessage;
    let bar = progress_bar(0, "fitting");
    let runs = options.schedules.len();
    let summary = crate::ablate::ablate(options, |k, name, message| match message {
        TrainMessage::Started { first, iterations } => {
            bar.set_length(iterations as u64);
            bar.set_position(first as u64);
            bar.reset_eta();
            bar.set_message(format!("run {}/{runs} ({name})", k + 1));
        }
        TrainMessage::Step { iteration, .. } => bar.set_position(iteration as u64 + 1),
        TrainMessage::Evaluating { .. } => bar.set_message(format!("run {}/{runs} ({name}): rendering", k + 1)),
        _ => {}
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    let table = std::fs::read_to_string(options.out.join("ablation.md")).unwrap_or_default();
    print!("{table}");
    println!("wrote {} ({} finished runs, {} fitted now)", options.out.join("ablation.md").display(), summary.rows.len(), summary.fitted);
    if !summary.elsewhere.is_empty() {
        println!("left to the processes fitting them: {} (run ablate again when they end to refresh the table)", summary.elsewhere.join(", "));
    }
    Ok(())
}

fn relight(options: &crate::relight::RelightOptions) -> Result<(), String> {
    let bar = progress_bar(0, "relighting");
    let out = crate::relight::relight_run(options, image_progress(&bar)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    println!("wrote {} (one PNG per view, sheet.png)", out.display());
    if options.basis.is_some() {
        if let Ok(table) = std::fs::read_to_string(out.join("basis.md")) {
            print!("{table}");
        }
    }
    Ok(())
}

fn report(options: &crate::report::ReportOptions) -> Result<(), String> {
    let (html, md) = crate::report::write_report(options).map_err(|e| e.to_string())?;
    println!("wrote {} and {}", html.display(), md.display());
    Ok(())
}

fn export_mesh(
    run: PathBuf,
    frame: Option<usize>,
    out: Option<PathBuf>,
    all_frames: Option<PathBuf>,
    scene: Option<PathBuf>,
    backend: crate::backend::Backend,
) -> Result<(), String> {
    use crate::export::Targets;
    let targets = match (frame, out, all_frames) {
        (Some(frame), Some(out), None) => Targets::One { frame, out },
        (None, None, Some(dir)) => Targets::All { dir },
        _ => return Err("export-mesh needs either --frame F --out FILE.obj or --all-frames DIR".into()),
    };
    let bar = progress_bar(0, "meshing");
    let options = crate::export::ExportOptions { run, scene, targets, backend };
    let exported = crate::export::export_meshes(&options, image_progress(&bar)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    for e in &exported {
        println!(
            "wrote {} (frame {}: {} vertices, {} triangles, {})",
            e.path.display(),
            e.frame,
            e.vertices,
            e.triangles,
            if e.closed { "closed" } else { "not closed: the surface leaves the sampled box" }
        );
    }
    Ok(())
}

/// A fitted light (`fit.json`'s `light`) as a person reads it: a sun's direction as azimuth
/// (degrees from +Z toward +X, about the up axis +Y) and elevation, a point light's position in
/// metres, colours to 3 digits.
pub fn describe_light(light: &serde_json::Value) -> String {
    let triple = |key: &str| -> Option<[f64; 3]> {
        let v = light[key].as_array()?;
        Some([v.first()?.as_f64()?, v.get(1)?.as_f64()?, v.get(2)?.as_f64()?])
    };
    let rgb = |key: &str| triple(key).map(|c| format!("{:.3} {:.3} {:.3}", c[0], c[1], c[2])).unwrap_or_else(|| "-".into());
    match light["type"].as_str() {
        Some("directional") => {
            let Some([x, y, z]) = triple("direction") else { return "a sun of unknown direction".into() };
            let length = (x * x + y * y + z * z).sqrt().max(1e-12);
            let elevation = (y / length).clamp(-1.0, 1.0).asin().to_degrees();
            let azimuth = x.atan2(z).to_degrees();
            format!("sun at azimuth {azimuth:.1} degrees, elevation {elevation:.1} degrees; irradiance {}, ambient {}", rgb("irradiance"), rgb("ambient"))
        }
        Some("point") => {
            let position = triple("position").map(|p| format!("({:.3}, {:.3}, {:.3}) m", p[0], p[1], p[2])).unwrap_or_else(|| "unknown".into());
            format!("point light at {position}; intensity {}, ambient {}", rgb("intensity"), rgb("ambient"))
        }
        Some("uniform") => "uniform light (no direction to fit)".into(),
        _ => light.to_string(),
    }
}

fn print_evaluation(evaluation: &serde_json::Value) {
    for (key, what) in [("novel_pose", "novel pose"), ("novel_view", "novel view"), ("relit", "relit"), ("albedo", "albedo")] {
        if let Some(p) = evaluation[format!("{key}_psnr")].as_f64() {
            let foreground = evaluation[format!("{key}_foreground_psnr")].as_f64().unwrap_or(f64::NAN);
            let ssim = evaluation[format!("{key}_ssim")].as_f64().unwrap_or(f64::NAN);
            println!("{what}: PSNR {p:.2} dB, foreground {foreground:.2} dB, SSIM {ssim:.4}");
        }
    }
    // The fitted surface against the scene's ground-truth meshes, averaged over the frames meshed.
    let frames = evaluation["geometry"].as_array().cloned().unwrap_or_default();
    let mean = |key: &str| {
        let values: Vec<f64> = frames.iter().filter_map(|f| f[key].as_f64()).collect();
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    if let (Some(accuracy), Some(completeness), Some(chamfer)) = (mean("accuracy"), mean("completeness"), mean("chamfer")) {
        let closed = frames.iter().filter(|f| f["closed"].as_bool() == Some(true)).count();
        println!(
            "surface against the scene's meshes ({} frames): accuracy {:.1} mm, completeness {:.1} mm, Chamfer {:.1} mm, {:.1}% within 2 cm, {closed} of {} closed",
            frames.len(),
            accuracy * 1e3,
            completeness * 1e3,
            chamfer * 1e3,
            mean("within_2cm").unwrap_or(f64::NAN) * 100.0,
            frames.len()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::describe_light;
    use serde_json::json;

    #[test]
    fn a_light_is_described_in_degrees_and_three_digit_colours() {
        let sun = |d: [f64; 3]| json!({"type": "directional", "direction": d, "irradiance": [0.30000007152557373, 1, 2], "ambient": [0.25, 0.25, 0.25]});
        assert_eq!(
            describe_light(&sun([0.0, 0.0, 1.0])),
            "sun at azimuth 0.0 degrees, elevation 0.0 degrees; irradiance 0.300 1.000 2.000, ambient 0.250 0.250 0.250"
        );
        assert!(describe_light(&sun([1.0, 0.0, 0.0])).contains("azimuth 90.0 degrees, elevation 0.0"));
        assert!(describe_light(&sun([0.0, 2.0, 0.0])).contains("elevation 90.0"));
        assert!(describe_light(&sun([-1.0, 1.0, -1.0])).contains("azimuth -135.0 degrees, elevation 35.3"));
        let lamp = json!({"type": "point", "position": [1, 2.5, -0.25], "intensity": [8, 8, 8], "ambient": [0, 0, 0]});
        assert!(describe_light(&lamp).starts_with("point light at (1.000, 2.500, -0.250) m; intensity 8.000"));
    }
}
