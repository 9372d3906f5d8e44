//! The command line: argument parsing, progress bars and the report each subcommand prints.
//! Everything it does is a library call, so tests and examples use the same entry points.

mod args;
mod print;

pub use args::*;
pub use print::describe_light;
use print::{print_avatar, print_evaluation};

use clap::Parser;
use std::path::{Path, PathBuf};

/// Runs the CLI and returns the process exit code.
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
        Command::Bench { which, backend: Some(backend), .. } if !matches!(which, BenchKind::Memory) => {
            Err(format!("--backend {backend} is for `bench memory`; `bench device` compares the CPU with the device, the other benchmarks run on flex"))
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
        Command::Bench { which: BenchKind::Device, out, quick, scene, schedule, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun-128"));
            crate::bench::device(&scene, &schedule, &out, quick, |line| eprintln!("{line}")).map(|table| print!("{table}")).map_err(|e| e.to_string())
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
        Command::Bench { which: BenchKind::Memory, out, quick, scene, iterations, images, backend, .. } => {
            let scene = scene.unwrap_or_else(|| PathBuf::from("datasets-synthetic/human-sun"));
            let sizes = (128, if quick { 512 } else { 1024 });
            let backend = backend.unwrap_or(crate::backend::Backend::Flex);
            let options = crate::bench::MemoryBenchOptions { scene, out, images, sizes, iterations: iterations.unwrap_or(30), backend };
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
        TrainMessage::Loading { done, total } => {
            bar.set_what("loading images");
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        }
        TrainMessage::Loaded { scene, training_images, frames, light } => {
            bar.set_what("fitting");
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
        TrainMessage::Checkpoint { .. } | TrainMessage::Planned { .. } => {}
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
        TrainMessage::Meshed { done, total } => meshing(&bar, done, total),
        TrainMessage::Done => bar.finish_and_clear(),
    })
    .map_err(|e| e.to_string())?;
    println!("wrote {}", options.out.join("fit.json").display());
    if let Some(why) = &report.evaluation_skipped {
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
    println!("light: {}", describe_light(&report.light));
    if let Some(search) = report.sun_search.as_object() {
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
    if let Some(e) = report.direction_error() {
        println!("light direction error against the scene's sun: {e:.2} degrees");
    }
    if let Some(line) = crate::fit_report::camera_colours_line(&report.capture) {
        println!("{line}");
    }
    if let Some(line) = crate::fit_report::cameras_line(&report.capture) {
        println!("{line}");
    }
    if let Some(line) = crate::fit_report::motion_line(&report.capture) {
        println!("{line}; the refined training motion: {}", options.out.join(crate::run::REFINED_MOTION).display());
    }
    print_evaluation(&report.evaluation);
    println!("wall time: {:.1} s", report.wall_seconds);
    if let Some(bytes) = report.peak_device_memory_bytes {
        println!("device memory: {:.0} MiB at most, held by the {} backend's allocator", bytes as f64 / (1u64 << 20) as f64, report.backend);
    }
    Ok(())
}

/// The evaluation's geometry check on `bar`: `done` of `total` frames meshed and compared with
/// the scene's meshes, with the time left.
fn meshing(bar: &crate::progress::Progress, done: usize, total: usize) {
    if done == 0 {
        bar.set_what("meshing frames against the scene's meshes");
        bar.set_message(String::new());
        bar.set_length(total as u64);
        bar.set_position(0);
        bar.reset_eta();
    } else {
        bar.set_position(done as u64);
    }
}

/// Follows a command that renders or writes images one by one on `bar`.
fn image_progress(bar: &crate::progress::Progress) -> impl FnMut(crate::messages::TrainMessage) + '_ {
    use crate::messages::TrainMessage;
    move |message| match message {
        TrainMessage::Evaluating { images } => bar.set_length(images as u64),
        TrainMessage::Planned { views, width, height } => {
            let megabytes = (views * width * height * 4) as f64 / 1e6;
            bar.println(format!("rendering {views} views of {width}x{height} pixels (at most {megabytes:.1} MB of PNGs; the time left shows after the first)"));
        }
        TrainMessage::Rendered { done, name, psnr, .. } => {
            bar.set_position(done as u64);
            bar.set_message(psnr.map(|p| format!("{name}: {p:.2} dB")).unwrap_or(name));
        }
        TrainMessage::Meshed { done, total } => meshing(bar, done, total),
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
            "geometry, frame {}: accuracy {:.2} mm, completeness {:.2} mm, Chamfer {:.2} mm, normal angle {:.2} degrees, {:.1}% within 2 cm ({:.1}% of the {:.1}% the training images saw), {}",
            frame["frame"],
            mm("accuracy"),
            mm("completeness"),
            mm("chamfer"),
            frame["normal_angle"].as_f64().unwrap_or(f64::NAN),
            frame["within_2cm"].as_f64().unwrap_or(f64::NAN) * 100.0,
            frame["seen_within_2cm"].as_f64().unwrap_or(f64::NAN) * 100.0,
            frame["seen"].as_f64().unwrap_or(f64::NAN) * 100.0,
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
