//! Scoring a fit: its test (or training) images rendered in the fitted light or relit by the
//! light each names, and scored against the truth (PSNR, SSIM, per group; `metrics.*`,
//! `compare.png`), its surface against the scene's ground-truth meshes, its light against the
//! scene's; and the `render` and `eval` commands that restore a run to do it.

use crate::avatar::{Avatar, Fitted};
use crate::eval::Lighting;
use crate::fit_error::{io, FitError};
use crate::imageio::RgbImage;
use crate::messages::TrainMessage;
use crate::metrics::{score, ImageScores};
use crate::run::{albedo_scale, restore, save_png, write_text};
use crate::run_lock::RunLock;
use crate::scene::{Scene, Split};
use burn::module::Module;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod geometry;
mod tables;
use geometry::geometry_scores;
pub use tables::METRICS_COLUMNS;
use tables::*;

/// Renders and scores the test images of a finished (or checkpointed) fit in `run`, with the
/// scene it was fitted on or `scene`; writes `run/renders/` and returns the evaluation.
pub fn render_run(run: &Path, scene: Option<&Path>, backend: crate::backend::Backend, on: impl FnMut(TrainMessage)) -> Result<serde_json::Value, FitError> {
    restore_and_evaluate(run, scene, Split::Test, backend, "render", on).map(|(_, evaluation)| evaluation)
}

/// `umbra eval`: the evaluation of `split` (`evaluate_split`) into `RUN/renders` for the test
/// images or `RUN/renders-train` for the training ones (how well the fit explains what it saw,
/// against how well it generalises).
pub fn eval_run(
    run: &Path,
    scene: Option<&Path>,
    split: Split,
    backend: crate::backend::Backend,
    on: impl FnMut(TrainMessage),
) -> Result<(PathBuf, serde_json::Value), FitError> {
    restore_and_evaluate(run, scene, split, backend, "eval", on)
}

/// The run rebuilt and, under its lock (taken as `command`), evaluated into its folder.
fn restore_and_evaluate(
    run: &Path,
    scene: Option<&Path>,
    split: Split,
    backend: crate::backend::Backend,
    command: &str,
    mut on: impl FnMut(TrainMessage),
) -> Result<(PathBuf, serde_json::Value), FitError> {
    let restored = restore(run, scene, backend)?;
    let _lock = RunLock::acquire(run, command)?;
    let dir = run.join(if split == Split::Test { "renders" } else { "renders-train" });
    let evaluation = evaluate_split(&restored.scene, &restored.fitted, &dir, split, &mut on)?;
    Ok((dir, evaluation))
}

/// How much `compare.png` amplifies the difference between a render and its truth.
pub const COMPARE_GAIN: f32 = 4.0;

/// Samples of the sky per view when relighting by an environment or uniform light.
pub const SKY_SAMPLES: usize = 256;

/// `compare.png`: a row per image, labelled with its name, group and foreground PSNR: the
/// truth, the render, their difference, then the same for its albedo.
fn compare_sheet(rows: &[(String, Vec<RgbImage>)]) -> crate::plot::Canvas {
    let difference = format!("difference x{COMPARE_GAIN}");
    let columns = ["truth", "render", &difference, "albedo truth", "albedo", &difference].map(String::from).to_vec();
    let rows = rows.iter().map(|(label, cells)| (label.clone(), cells.iter().map(Some).collect())).collect();
    crate::plot::Sheet { title: "Renders beside the truth (foreground PSNR)".into(), columns, rows }.render()
}

/// The evaluation `fit` ends with and `render` and `eval` run: `evaluate_split` of the test
/// images into `RUN/renders`.
pub fn evaluate(scene: &Scene, fitted: &Fitted, out: &Path, on: &mut impl FnMut(TrainMessage)) -> Result<serde_json::Value, FitError> {
    evaluate_split(scene, fitted, &out.join("renders"), Split::Test, on)
}

/// Renders every image of `split` (in the fitted light, or relit by the light the image
/// names) and its albedo when the scene has one, scores them (PSNR, sRGB 8-bit, whole image,
/// foreground and SSIM, `metrics`), scores the fitted surface against every ground-truth mesh
/// the scene's frames carry (`geometry`: accuracy, completeness, Chamfer distance, normal
/// angle), and writes into `dir`: the PNGs, `metrics.csv`, `metrics.md`, `metrics.json` (all of
/// it with the light's error) and `compare.png` (a row per image: the truth, the render and
/// their difference times `COMPARE_GAIN`, then the same for its albedo).
pub fn evaluate_split(scene: &Scene, fitted: &Fitted, dir: &Path, split: Split, on: &mut impl FnMut(TrainMessage)) -> Result<serde_json::Value, FitError> {
    let kinds = TestKinds::new(scene);
    let tests: Vec<&crate::scene::View> = scene.views_in(split).collect();
    if tests.is_empty() {
        let name = match split {
            Split::Train => "training",
            Split::Val => "validation",
            Split::Test => "test",
        };
        return Err(FitError::Input(format!("{}: no {name} images to evaluate", scene.root.join("scene.json").display())));
    }
    on(TrainMessage::Evaluating { images: tests.len() });
    let dir = dir.to_path_buf();
    crate::run::clear_renders(&dir)?;
    std::fs::create_dir_all(&dir).map_err(|e| io(&dir, e))?;
    // Inference on the plain backend: no autodiff graph is recorded (or held) for the renders.
    let model = fitted.model.valid();
    let device = fitted.device.clone().without_autodiff();
    let albedo_scale = albedo_scale(scene, &model);
    // As many views at once as there are threads (one view's render keeps about one busy);
    // each view's samples are seeded by its own camera and frame, so the images do not depend
    // on the schedule, nor on which other lights a view is rendered in.
    let lighting_of = |view: &crate::scene::View| match kinds.of(view).relit {
        false => Lighting::Fitted(kinds.training_light(view)),
        true => Lighting::Known { light: &scene.lights[&view.light], albedo_scale, samples: SKY_SAMPLES },
    };
    // The views that share a camera and a frame are traced once and shaded in each one's light.
    let groups = same_camera_and_frame(&tests);
    let render = |k: usize| {
        let views: Vec<&crate::scene::View> = groups[k].iter().map(|&i| tests[i]).collect();
        let lightings: Vec<Lighting> = views.iter().map(|v| lighting_of(v)).collect();
        groups[k].iter().copied().zip(score_views(&model, scene, &views, &lightings, albedo_scale, &device)).collect::<Vec<_>>()
    };
    // Each view is taken in the test set's order, as soon as it and every one before it are.
    let mut taken = Taken { scene, kinds: &kinds, dir: dir.clone(), total: tests.len(), rows: Vec::new(), compare: Vec::new() };
    let mut waiting = BTreeMap::new();
    in_order_while_rendering(groups.len(), render, |_, scored| {
        waiting.extend(scored);
        while let Some(scored) = waiting.remove(&taken.rows.len()) {
            let done = taken.rows.len();
            taken.take(done, tests[done], scored, on)?;
        }
        Ok::<(), FitError>(())
    })?;
    let Taken { rows, compare, .. } = taken;
    compare_sheet(&compare).save_png(&dir.join("compare.png")).map_err(FitError::Input)?;
    let groups = group_means(&rows);
    write_text(&dir.join("metrics.csv"), &metrics_csv(&rows))?;
    let mut evaluation = evaluation_json(&rows, &groups, albedo_scale);
    let geometry = geometry_scores(scene, &model, &device, on)?;
    let light = light_error(scene, fitted.fit_light, 0, &model.light.report());
    let mut markdown = metrics_markdown(&rows, &groups);
    markdown += &geometry_markdown(geometry.as_array().map(|f| f.as_slice()).unwrap_or_default());
    write_text(&dir.join("metrics.md"), &markdown)?;
    evaluation.insert("geometry".into(), geometry);
    evaluation.insert("light_error".into(), light);
    let evaluation = serde_json::Value::Object(evaluation);
    write_text(&dir.join("metrics.json"), &serde_json::to_string_pretty(&evaluation).unwrap_or_default())?;
    Ok(evaluation)
}

/// What an evaluation has taken of its rendered views so far: their scores, and the rows of
/// `compare.png`.
struct Taken<'a> {
    scene: &'a Scene,
    kinds: &'a TestKinds,
    dir: PathBuf,
    total: usize,
    rows: Vec<ImageScore>,
    compare: Vec<(String, Vec<RgbImage>)>,
}

impl Taken<'_> {
    /// Writes view `done`'s render (and its albedo) into the folder, scores it and reports it.
    fn take(&mut self, done: usize, view: &crate::scene::View, scored: ScoredView, on: &mut impl FnMut(TrainMessage)) -> Result<(), FitError> {
        let (scene, kinds, dir) = (self.scene, self.kinds, &self.dir);
        let TestKind { novel_pose, novel_view, relit, group } = kinds.of(view);
        let name = render_name(scene, view);
        save_png(&dir.join(&name), &scored.image)?;
        let truth = view.colour.to_rgb();
        let mut row = vec![truth.clone(), scored.image.clone(), scored.image.difference(&truth, COMPARE_GAIN)];
        if let Some((albedo, _)) = &scored.albedo {
            save_png(&dir.join(name.replace(".png", "-albedo.png")), albedo)?;
            if let Some(truth) = &view.albedo {
                row.extend([truth.clone(), albedo.clone(), albedo.difference(truth, COMPARE_GAIN)]);
            }
        }
        let label = format!("{} {}: {:.1} dB", name.trim_start_matches("images_").trim_end_matches(".png"), group, scored.scores.foreground_psnr);
        self.compare.push((label, row));
        // Relit images and albedos again after one per-channel least-squares scale: what is
        // left when the absolute scale the fit cannot know is forgiven.
        let relit_scaled = relit.then(|| crate::metrics::score_scaled(&scored.image, &truth, view.mask.as_ref()).0);
        let albedo_scaled = match (&scored.albedo, &view.albedo) {
            (Some((albedo, _)), Some(truth)) => Some(crate::metrics::score_scaled(albedo, truth, view.mask.as_ref()).0),
            _ => None,
        };
        let (scores, albedo) = (scored.scores, scored.albedo.map(|a| a.1));
        on(TrainMessage::Rendered { done: done + 1, total: self.total, name: name.clone(), psnr: Some(scores.psnr) });
        let error_sums = view.mask.as_ref().map(|mask| crate::metrics::error_regions(&scored.image, &truth, mask));
        let error_share = error_sums.map(|e| e.shares());
        self.rows.push(ImageScore {
            image: name,
            light: view.light.clone(),
            group,
            scores,
            albedo,
            relit_scaled,
            albedo_scaled,
            error_share,
            error_sums,
            novel_pose,
            novel_view,
            relit,
        });
        Ok(())
    }
}

/// Renders items `0..count` on rayon's threads in about their order (`par_bridge` hands each
/// free thread the next) while this thread `take`s each result in order, as soon as it and
/// every earlier one are done: writing and scoring one view overlaps rendering the next, and no
/// thread waits for a batch's slowest view (each view's samples are seeded by its own camera and
/// frame, so the results do not depend on the order). After `take` fails, items not yet started
/// are skipped and its error returned.
pub(super) fn in_order_while_rendering<T: Send, E>(
    count: usize,
    render: impl Fn(usize) -> T + Sync,
    mut take: impl FnMut(usize, T) -> Result<(), E>,
) -> Result<(), E> {
    use rayon::prelude::*;
    use std::sync::atomic::{AtomicBool, Ordering};
    let (sender, receiver) = std::sync::mpsc::channel();
    let failed = AtomicBool::new(false);
    std::thread::scope(|scope| {
        scope.spawn(|| {
            (0..count).par_bridge().for_each_with(sender, |sender, k| {
                if !failed.load(Ordering::Relaxed) {
                    // The receiver lives until every sender is gone.
                    let _ = sender.send((k, render(k)));
                }
            })
        });
        let mut waiting = BTreeMap::new();
        let mut next = 0;
        let mut outcome = Ok(());
        for (k, value) in receiver {
            waiting.insert(k, value);
            while let Some(value) = waiting.remove(&next) {
                if outcome.is_ok() {
                    outcome = take(next, value);
                    failed.store(outcome.is_err(), Ordering::Relaxed);
                }
                next += 1;
            }
        }
        outcome
    })
}

/// How a test image differs from the training images, and its evaluation group.
pub struct TestKind {
    pub novel_pose: bool,
    pub novel_view: bool,
    pub relit: bool,
    pub group: &'static str,
}

/// What a scene trains on, to tell its test images apart.
pub struct TestKinds {
    frames: Vec<usize>,
    cameras: Vec<usize>,
    lights: Vec<String>,
}

impl TestKinds {
    pub fn new(scene: &Scene) -> Self {
        Self {
            frames: scene.views_in(Split::Train).map(|v| v.frame).collect(),
            cameras: scene.views_in(Split::Train).map(|v| v.camera).collect(),
            lights: scene.training_lights().into_iter().map(String::from).collect(),
        }
    }

    /// The index of a view's light among the training lights (0 for any other light).
    pub fn training_light(&self, view: &crate::scene::View) -> usize {
        self.lights.iter().position(|l| *l == view.light).unwrap_or(0)
    }

    pub fn of(&self, view: &crate::scene::View) -> TestKind {
        let novel_pose = !self.frames.contains(&view.frame);
        let novel_view = !self.cameras.contains(&view.camera);
        let relit = !self.lights.contains(&view.light);
        let group = match (novel_pose, novel_view, relit) {
            (_, _, true) => "relit",
            (_, true, false) => "novel view",
            (true, false, false) => "novel pose",
            (false, false, false) => "training pose and view",
        };
        TestKind { novel_pose, novel_view, relit, group }
    }
}

/// A test view rendered and scored, with its albedo when the scene has the truth.
pub struct ScoredView {
    pub image: RgbImage,
    pub scores: ImageScores,
    pub albedo: Option<(RgbImage, ImageScores)>,
}

/// The test views that share a camera and a frame (a view's indices into `views`), groups in
/// the order of their first view.
fn same_camera_and_frame(views: &[&crate::scene::View]) -> Vec<Vec<usize>> {
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut group_of: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for (k, view) in views.iter().enumerate() {
        let g = *group_of.entry((view.camera, view.frame)).or_insert_with(|| {
            groups.push(Vec::new());
            groups.len() - 1
        });
        groups[g].push(k);
    }
    groups
}

/// Renders test views of one camera and frame (`eval::VIEW_SAMPLING`), each in its lighting,
/// from one trace of the geometry (`eval::render_view_lights`), with the albedo where any of
/// them has its truth, and scores each (`metrics::score`).
pub fn score_views(
    model: &Avatar,
    scene: &Scene,
    views: &[&crate::scene::View],
    lightings: &[Lighting],
    albedo_scale: glam::DVec3,
    device: &burn::tensor::Device,
) -> Vec<ScoredView> {
    let Some(first) = views.first() else {
        return Vec::new();
    };
    let wants_albedo = views.iter().any(|v| v.albedo.is_some()).then_some(albedo_scale);
    let layers = crate::eval::render_view_lights(
        model,
        scene,
        first.camera,
        first.frame,
        crate::eval::VIEW_SAMPLING,
        device,
        lightings,
        wants_albedo,
        crate::eval::Strata::Shortcuts,
    );
    views
        .iter()
        .zip(layers.images)
        .map(|(view, image)| {
            let scores = score(&image, &view.colour.to_rgb(), view.mask.as_ref());
            // The albedo is the view's, whatever its light: each image with its truth gets a copy.
            let albedo = view.albedo.as_ref().zip(layers.albedo.as_ref()).map(|(truth, albedo)| {
                let s = score(albedo, truth, view.mask.as_ref());
                (albedo.clone(), s)
            });
            ScoredView { image, scores, albedo }
        })
        .collect()
}

/// A render's file name: the test image's path inside the scene, flattened.
fn render_name(scene: &Scene, view: &crate::scene::View) -> String {
    let relative = view.path.strip_prefix(&scene.root).unwrap_or(&view.path).with_extension("png");
    relative.to_string_lossy().replace(['/', '\\'], "_")
}

/// How far the recovered training light `k` is from the one the scene states for it
/// (synthetic and evaluation scenes state it): degrees for a sun, metres for a point light.
pub fn light_error(scene: &Scene, fit_light: bool, k: usize, light: &serde_json::Value) -> serde_json::Value {
    let lights = scene.training_lights();
    let vector = |v: &serde_json::Value| -> Option<glam::DVec3> { Some(glam::DVec3::new(v[0].as_f64()?, v[1].as_f64()?, v[2].as_f64()?)) };
    match (lights.get(k).map(|n| &scene.lights[*n]), fit_light) {
        (Some(crate::light::Light::Directional { direction, .. }), true) => match vector(&light["direction"]) {
            Some(d) => json!({"direction_degrees": d.normalize().dot(*direction).clamp(-1.0, 1.0).acos().to_degrees()}),
            None => json!(null),
        },
        (Some(crate::light::Light::Point { position, .. }), true) => match vector(&light["position"]) {
            Some(p) => json!({"position_metres": (p - *position).length()}),
            None => json!(null),
        },
        _ => json!(null),
    }
}

#[cfg(test)]
mod tests {
    use super::in_order_while_rendering;
    use std::sync::atomic::{AtomicUsize, Ordering};

    #[test]
    fn results_are_taken_in_order_however_the_renders_finish() {
        // Early items take longest, so later ones finish first on the other thread.
        let render = |k: usize| {
            std::thread::sleep(std::time::Duration::from_millis(((40 - k) % 7) as u64));
            k * k
        };
        let mut taken = Vec::new();
        let outcome: Result<(), ()> = in_order_while_rendering(40, render, |k, value| {
            taken.push((k, value));
            Ok(())
        });
        assert_eq!(outcome, Ok(()));
        assert_eq!(taken, (0..40).map(|k| (k, k * k)).collect::<Vec<_>>());
    }

    #[test]
    fn a_failed_take_stops_the_rest_and_is_returned() {
        let started = AtomicUsize::new(0);
        let render = |k: usize| {
            started.fetch_add(1, Ordering::Relaxed);
            std::thread::sleep(std::time::Duration::from_millis(5));
            k
        };
        let mut taken = Vec::new();
        let outcome = in_order_while_rendering(200, render, |k, _| {
            taken.push(k);
            if k == 3 {
                Err(format!("item {k}"))
            } else {
                Ok(())
            }
        });
        assert_eq!(outcome, Err("item 3".to_string()));
        assert_eq!(taken, vec![0, 1, 2, 3], "nothing is taken after the failure");
        assert!(started.load(Ordering::Relaxed) < 200, "items not yet started are skipped");
    }

    #[test]
    fn a_groups_error_shares_sum_its_images_errors_and_need_every_mask() {
        use super::tables::{group_means, ImageScore};
        use crate::metrics::{ErrorRegions, ImageScores};
        let scores = ImageScores { psnr: 30.0, foreground_psnr: 20.0, ssim: 0.9 };
        let row = |group: &'static str, sums: Option<ErrorRegions>| ImageScore {
            image: String::new(),
            light: "sun".into(),
            group,
            scores,
            albedo: None,
            relit_scaled: None,
            albedo_scaled: None,
            error_share: sums.map(|e| e.shares()),
            error_sums: sums,
            novel_pose: group == "novel pose",
            novel_view: false,
            relit: false,
        };
        // Shares of the sums, not means of the shares: (30 + 0) / 40 outside, (0 + 10) / 40 inside.
        let rows = [
            row("novel pose", Some(ErrorRegions { outside: 30.0, silhouette: 0.0, inside: 0.0 })),
            row("novel pose", Some(ErrorRegions { outside: 0.0, silhouette: 0.0, inside: 10.0 })),
            row("novel view", Some(ErrorRegions { outside: 1.0, silhouette: 1.0, inside: 2.0 })),
            row("novel view", None),
        ];
        let groups = group_means(&rows);
        assert_eq!(groups[0].error_share, Some(ErrorRegions { outside: 0.75, silhouette: 0.0, inside: 0.25 }));
        assert_eq!(groups[1].group, "novel view");
        assert_eq!(groups[1].error_share, None, "an image without a mask leaves its group without shares");
    }
}
